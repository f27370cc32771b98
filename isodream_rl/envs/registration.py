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
#: The backgrounds of :class:`~isodream_rl.envs.dmc.DMCBackgroundEnv`.
BACKGROUNDS = ("video_easy", "video_hard", "none")
#: ``dm_control.suite.ALL_TASKS`` as ``"domain-task"``, written out so that registering the ids does not import
#: dm_control, which initialises its GL backend at import (tests/test_env_dmc.py checks it against the suite).
DMC_SUITE_TASKS = (
    "acrobot-swingup",
    "acrobot-swingup_sparse",
    "ball_in_cup-catch",
    "cartpole-balance",
    "cartpole-balance_sparse",
    "cartpole-swingup",
    "cartpole-swingup_sparse",
    "cartpole-three_poles",
    "cartpole-two_poles",
    "cheetah-run",
    "dog-fetch",
    "dog-run",
    "dog-stand",
    "dog-trot",
    "dog-walk",
    "finger-spin",
    "finger-turn_easy",
    "finger-turn_hard",
    "fish-swim",
    "fish-upright",
    "hopper-hop",
    "hopper-stand",
    "humanoid-run",
    "humanoid-run_pure_state",
    "humanoid-stand",
    "humanoid-walk",
    "humanoid_CMU-run",
    "humanoid_CMU-stand",
    "humanoid_CMU-walk",
    "lqr-lqr_2_1",
    "lqr-lqr_6_2",
    "manipulator-bring_ball",
    "manipulator-bring_peg",
    "manipulator-insert_ball",
    "manipulator-insert_peg",
    "pendulum-swingup",
    "point_mass-easy",
    "point_mass-hard",
    "quadruped-escape",
    "quadruped-fetch",
    "quadruped-run",
    "quadruped-walk",
    "reacher-easy",
    "reacher-hard",
    "stacker-stack_2",
    "stacker-stack_4",
    "swimmer-swimmer15",
    "swimmer-swimmer6",
    "walker-run",
    "walker-stand",
    "walker-walk",
)


def dmc_env_id(domain: str, task: str, background: str) -> str:
    """The gymnasium id of a DMC task with a background, e.g. ``isodream/DMC-walker-walk-video_easy-v0``."""
    return f"{NAMESPACE}/DMC-{domain}-{task}-{background}-v0"


def register_envs() -> list[str]:
    """Registers every isodream-rl gymnasium id not registered yet; returns all of them."""
    specs = {
        f"{NAMESPACE}/Sprites-v0": ("isodream_rl.envs.sprites:SpritesEnv", {}),
        f"{NAMESPACE}/Highway-v0": ("isodream_rl.envs.highway:HighwayIsoEnv", {}),
    }
    for domain, task in (name.split("-") for name in DMC_SUITE_TASKS):
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
