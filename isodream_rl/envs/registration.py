"""Gymnasium ids for the isodream-rl environments, registered when ``isodream_rl.envs`` is imported.

- ``isodream/Sprites-v0``: ``SpritesEnv`` (``task="none"`` unless ``gym.make(..., task="reach")``);
- ``isodream/Highway-v0``: ``HighwayIsoEnv`` (first-person view unless ``view="top_down"``);
- ``isodream/DMC-<domain>-<task>-<background>-v0``: ``DMCBackgroundEnv`` for every dm_control suite task and
  every background, e.g. ``isodream/DMC-walker-walk-video_easy-v0``.

The ids give the raw gymnasium envs (HWC uint8 frames); ``make_env`` gives the TorchRL ones.
"""

from __future__ import annotations

import gymnasium as gym

NAMESPACE = "isodream"


def dmc_env_id(domain: str, task: str, background: str) -> str:
    """The gymnasium id of a DMC task with a background, e.g. ``isodream/DMC-walker-walk-video_easy-v0``."""
    return f"{NAMESPACE}/DMC-{domain}-{task}-{background}-v0"


def register_envs() -> list[str]:
    """Registers every isodream-rl gymnasium id not registered yet; returns all of them."""
    from isodream_rl.envs.dmc import BACKGROUNDS, dmc_tasks

    specs = {
        f"{NAMESPACE}/Sprites-v0": ("isodream_rl.envs.sprites:SpritesEnv", {}),
        f"{NAMESPACE}/Highway-v0": ("isodream_rl.envs.highway:HighwayIsoEnv", {}),
    }
    for domain, task in (name.split("-") for name in dmc_tasks()):
        for background in BACKGROUNDS:
            specs[dmc_env_id(domain, task, background)] = (
                "isodream_rl.envs.dmc:DMCBackgroundEnv",
                {"domain": domain, "task": task, "background": background},
            )
    for env_id, (entry_point, kwargs) in specs.items():
        if env_id not in gym.registry:
            # The envs truncate their own episodes, so no TimeLimit (max_episode_steps) is added here.
            gym.register(id=env_id, entry_point=entry_point, kwargs=kwargs)
    return list(specs)
