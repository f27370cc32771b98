"""Environments: sprites (synthetic, with ground-truth masks), CARLA-like highway, DMC with moving backgrounds.

Importing this package registers the gymnasium ids, sets no environment variable and imports neither torchrl nor
dm_control: ``make_env`` and the other builders load on first use, and the DMC and highway env modules, imported
when such an env is made, set their rendering defaults then (docs/environment.md).
"""

import importlib

from isodream_rl.envs.registration import register_envs
from isodream_rl.envs.sprites import SPRITES_TASKS, SpritesEnv


def __getattr__(name: str):
    # make_env and the other builders load at first use: the builder imports torchrl, which imports mujoco,
    # which initialises the GL backend MUJOCO_GL names (and fails where that backend is not installed)
    if not name.startswith("_") and name != "builder":
        builder = importlib.import_module(f"{__name__}.builder")
        if name in getattr(builder, "__all__", ()):
            return getattr(builder, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


register_envs()

__all__ = [
    "SPRITES_TASKS",
    "SimulatorFaultGuard",
    "SpritesEnv",
    "env_names",
    "make_env",
    "make_gym_env",
    "make_parallel_env",
    "register_envs",
    "wrap_gym_env",
]
