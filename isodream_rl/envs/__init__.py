"""Environments: sprites (synthetic, with ground-truth masks), CARLA-like highway, DMC with moving backgrounds.

Importing this package registers the gymnasium ids, sets no environment variable and imports neither torchrl nor
dm_control: ``make_env`` and the other builders load on first use, and the DMC and highway env modules, imported
when such an env is made, set their rendering defaults then (docs/environment.md).
"""

from isodream_rl.envs.registration import register_envs
from isodream_rl.envs.sprites import SPRITES_TASKS, SpritesEnv

#: names served from :mod:`isodream_rl.envs.builder` at first use: it imports torchrl, which imports mujoco,
#: which initialises the GL backend that ``MUJOCO_GL`` names (and fails if that backend is not installed)
_BUILDER_NAMES = (
    "SimulatorFaultGuard",
    "env_names",
    "make_env",
    "make_gym_env",
    "make_parallel_env",
    "wrap_gym_env",
)


def __getattr__(name: str):
    if name in _BUILDER_NAMES:
        from isodream_rl.envs import builder

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
