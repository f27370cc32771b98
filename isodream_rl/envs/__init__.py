"""Environments: sprites (synthetic, with ground-truth masks), CARLA-like highway, DMC with moving backgrounds."""

import os
import sys
import warnings

# dm_control picks its GL backend from MUJOCO_GL when it is first imported: too late for the default below.
# (mujoco itself, which `import torchrl.envs` imports, does not matter: the highway first-person renderer chooses
# its backend explicitly, see mujoco_render.py.)
_MUJOCO_GL_TOO_LATE = "dm_control" in sys.modules and "MUJOCO_GL" not in os.environ

# Headless rendering defaults; must be set before dm_control / pygame are imported.
# SDL's "dummy" driver silently renders black frames with highway-env: use "offscreen".
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")
# llvmpipe (Mesa's CPU rasteriser) rasterises in the calling thread: as fast as a worker thread for 64x64 frames,
# and fork-safe. With worker threads (LP_NUM_THREADS >= 1), which Mesa starts when dm_control initialises EGL at
# import, a forked process (ParallelEnv with mp_start_method="fork") hangs at its first GL call.
os.environ.setdefault("LP_NUM_THREADS", "0")

if _MUJOCO_GL_TOO_LATE:
    warnings.warn(
        "dm_control was imported before isodream_rl.envs with MUJOCO_GL unset, so it renders with GLFW, which "
        "fails without a display. Run with MUJOCO_GL=egl in the environment, or import isodream_rl.envs first.",
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
