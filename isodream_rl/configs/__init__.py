"""Hydra configuration groups of ``isodream-train`` (env, size, algo, exp; domain, which the env groups pick);
see ``config.yaml``.

``env/dmc_<domain>_<task>.yaml`` exist for the four tasks of the paper's recipes; :func:`register_dmc_envs`
stores the same preset for every other dm_control suite task, so ``env=dmc_<domain>_<task>`` works for all of
them (``isodream_rl.envs.builder.dmc_env_names``).
"""

from __future__ import annotations

from pathlib import Path

#: the DMC env preset of the paper (§4.1): moving natural backgrounds, action repeat 2; the algorithm's choices
#: on DMC are ``domain/dmc.yaml``'s, which the stored presets pick as the YAML ones do
DMC_PRESET = {
    "kwargs": {"background": "video_easy", "action_repeat": 2},
    "action_repeat": 2,
}


def register_dmc_envs() -> list[str]:
    """Store ``env=dmc_<domain>_<task>`` in Hydra's ``ConfigStore`` for every suite task without a YAML file
    (the same settings as ``env/dmc_walker_walk.yaml``); the names stored."""
    from hydra.core.config_store import ConfigStore

    from isodream_rl.envs.builder import dmc_env_names

    files = {p.stem for p in (Path(__file__).parent / "env").glob("dmc_*.yaml")}
    store = ConfigStore.instance()
    stored = []
    for name in dmc_env_names():
        if name in files:
            continue
        node = {"defaults": [{"/domain": "dmc"}, "_self_"], "env": {"name": name, **DMC_PRESET}}
        store.store(group="env", name=name, node=node, package="_global_")
        stored.append(name)
    return stored
