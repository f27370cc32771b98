"""Process-wide environment variables: set only where needed, never over a user's value (docs/environment.md)."""

import os
import subprocess
import sys

import pytest

SETTINGS = ("THP_MEM_ALLOC_ENABLE", "MUJOCO_GL", "SDL_VIDEODRIVER", "LP_NUM_THREADS", "PYOPENGL_PLATFORM")


def _run(code: str, **env_vars: str) -> str:
    env = {k: v for k, v in os.environ.items() if k not in SETTINGS}
    env.update(env_vars)
    return subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.strip()


def test_importing_the_envs_sets_nothing_and_loads_no_dm_control():
    # osmesa on a machine without OSMesa: dm_control would fail at import, so it must not be imported
    code = (
        "import os, sys, gymnasium, isodream_rl, isodream_rl.envs;"
        "print('dm_control' in sys.modules, 'isodream/DMC-walker-walk-video_easy-v0' in gymnasium.registry,"
        f" [os.environ.get(k) for k in {SETTINGS!r}])"
    )
    out = _run(code, MUJOCO_GL="osmesa")
    assert out == "False True [None, 'osmesa', None, None, None]"


def test_dmc_module_sets_its_gl_defaults_and_keeps_the_users():
    code = "import os, isodream_rl.envs.dmc; print(os.environ['MUJOCO_GL'], os.environ['LP_NUM_THREADS'])"
    assert _run(code) == "egl 0"
    assert _run(code, MUJOCO_GL="egl", LP_NUM_THREADS="2") == "egl 2"


def test_highway_renderer_sets_pygames_driver_and_keeps_the_users():
    code = "import os, isodream_rl.envs.highway_render; print(os.environ['SDL_VIDEODRIVER'])"
    assert _run(code) == "offscreen"
    assert _run(code, SDL_VIDEODRIVER="x11") == "x11"


@pytest.mark.parametrize("preset", [None, "0"])
def test_training_entry_points_turn_on_huge_pages_unless_the_user_chose(preset):
    extra = {} if preset is None else {"THP_MEM_ALLOC_ENABLE": preset}
    read = "import os; print(os.environ.get('THP_MEM_ALLOC_ENABLE'))"
    assert _run(f"import isodream_rl; {read}", **extra) == str(preset)  # the package alone sets nothing
    for entry in ("isodream_rl.cli", "isodream_rl.cli_demo"):
        assert _run(f"import {entry}; {read}", **extra) == (preset or "1"), entry
    # torch imported first: its allocator has read the variable already, so the entry point leaves it alone
    assert _run(f"import torch, isodream_rl.cli; {read}", **extra) == str(preset)
