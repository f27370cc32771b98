"""Hydra configuration groups of ``isodream-train`` (env, size, algo, exp; domain, which the env groups pick);
see ``config.yaml``.

``env/dmc_<domain>_<task>.yaml`` exist for the four tasks of the paper's recipes; :func:`register_dmc_envs`
stores the same preset for every other dm_control suite task, so ``env=dmc_<domain>_<task>`` works for all of
them (``isodream_rl.envs.builder.dmc_env_names``).

A recipe (an ``exp`` file) that sets a value of a setting only one learner reads writes it
``${learner_value:<learner>,<value>}`` (:func:`learner_value`, registered by :func:`register_resolvers`): the value
for the algorithms of that learner, ``None`` ("the learner's value", here "not read") for the others, so that
``exp=decomposition algo=isodream`` takes the recipe without the DreamerV2-style learner's settings, which the
default would refuse.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

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


def learner_value(learner: str, value: Any, *, _root_: Any) -> Any:
    """The resolver ``${learner_value:<learner>,<value>}``: ``value`` where the run's ``algo.name`` builds
    ``learner`` (a key of :data:`~isodream_rl.trainers.learners.LEARNERS`: ``isodream``, ``isodream_v2``...), else
    ``None``, the setting's "not set" (a learner that does not read it refuses any other value).

    Raises:
        ValueError: ``learner`` is none of the learners.
    """
    from isodream_rl.trainers.learners import LEARNERS, learner_name

    if learner not in LEARNERS:
        raise ValueError(f"learner_value: {learner!r} is not a learner; the learners are {list(LEARNERS)}")
    return value if learner_name(_root_.algo.name) == learner else None


def register_resolvers() -> None:
    """Register the OmegaConf resolvers the config files use (:func:`learner_value`); again is a no-op."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("learner_value"):
        OmegaConf.register_new_resolver("learner_value", learner_value)
