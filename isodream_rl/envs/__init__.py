"""Environments: sprites (synthetic, with ground-truth masks), CARLA-like highway, DMC with moving backgrounds."""

import os
import sys
import warnings

# `import torchrl.envs` imports mujoco, which fixes its GL backend at import time: too late for the
# default below.
_MUJOCO_GL_TOO_LATE = "mujoco" in sys.modules and "MUJOCO_GL" not in os.environ

# Headless rendering defaults; must be set before mujoco / pygame are imported.
# SDL's "dummy" driver silently renders black frames with highway-env: use "offscreen".
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")

if _MUJOCO_GL_TOO_LATE:
    warnings.warn(
        "mujoco was imported before isodream_rl.envs with MUJOCO_GL unset (`import torchrl.envs` does "
        "that), so mujoco.Renderer (the highway first-person view) uses GLFW and fails without a display. "
        "Run with MUJOCO_GL=egl in the environment, or import isodream_rl.envs before torchrl.envs.",
        stacklevel=2,
    )

from isodream_rl.envs.builder import (  # noqa: E402
    SimulatorFaultGuard,
    env_names,
    make_env,
    make_gym_env,
    make_parallel_env,
    wrap_gym_env,
)
from isodream_rl.envs.registration import register_envs  # noqa: E402
from isodream_rl.envs.sprites import SPRITES_TASKS, SpritesEnv  # noqa: E402

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
