"""The process-wide environment variables isodream-rl sets, each where it is needed and never over a user's value.

Each function sets its variables with ``os.environ.setdefault``, so a value the user exported wins. They are
called by the code that needs them, not at package import: the training entry points (huge pages), the DMC env
module before it imports dm_control, the pygame and MuJoCo renderers before they initialise a display or a GL
context, and ``make_parallel_env`` before it forks workers that render. docs/environment.md lists them with the
reason for each. This module imports nothing heavy (in particular not torch), so entry points can call it first.
"""

from __future__ import annotations

import os
import sys

__all__ = ["use_huge_pages", "dm_control_gl", "pygame_offscreen", "single_threaded_llvmpipe"]


def use_huge_pages() -> None:
    """``THP_MEM_ALLOC_ENABLE=1``: PyTorch backs CPU tensors of 2 MB and more with transparent huge pages.

    A world-model update allocates and frees activations of ~10-100 MB many times; with 4 KB pages each fresh
    one costs a page fault per page, and the update is slower (measured in docs/environment.md). PyTorch reads
    the variable once, at its first allocation, so this does nothing once torch is imported: the training entry
    points call it before importing torch. ``THP_MEM_ALLOC_ENABLE=0`` opts out.
    """
    if "torch" not in sys.modules:
        os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")


def single_threaded_llvmpipe() -> None:
    """``LP_NUM_THREADS=0``: Mesa's CPU rasteriser (llvmpipe) draws in the calling thread.

    For 64x64 frames that is as fast as worker threads, leaves the other cores to torch, and survives ``fork``:
    with worker threads, which Mesa starts when a GL context is first made, a forked process (``ParallelEnv``
    with ``mp_start_method="fork"``) hangs at its first GL call. Mesa reads it when it initialises, so it is
    set before the first GL context of the process.
    """
    os.environ.setdefault("LP_NUM_THREADS", "0")


def dm_control_gl() -> None:
    """``MUJOCO_GL=egl`` (headless rendering without a display) and :func:`single_threaded_llvmpipe`.

    dm_control fixes its GL backend from ``MUJOCO_GL`` when it is first imported (and initialises it then), so
    ``isodream_rl.envs.dmc`` calls this before importing dm_control; its default, GLFW, needs a display.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    single_threaded_llvmpipe()


def pygame_offscreen() -> None:
    """``SDL_VIDEODRIVER=offscreen``: pygame draws highway-env's scene without a display.

    SDL's ``"dummy"`` driver, the usual headless choice, silently renders black frames with highway-env.
    """
    os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")
