"""OpenGL envs across processes and import orders. Each case runs in a fresh interpreter with a timeout, so a hang
(a GL call in a forked worker) fails the test instead of blocking the suite."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from isodream_rl.envs import make_parallel_env

_TIMEOUT_S = (
    120  # a fresh interpreter imports torch and torchrl: ~5 s idle, much more on a loaded 2-core machine
)


def _run(script: str, env: dict[str, str]) -> dict:
    """Runs ``script`` in a fresh interpreter; returns the JSON object it prints on its last line."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", textwrap.dedent(script)],
            env=env,
            capture_output=True,
            text=True,
            timeout=_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"the script hung for {_TIMEOUT_S} s; stderr:\n{err.stderr}")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_forked_first_person_highway_workers_reset_and_step_after_the_parent_rendered():
    # The parent renders first, so forked workers inherit an initialised EGL display and GL context.
    result = _run(
        """
        import json
        from isodream_rl.envs import make_env, make_parallel_env
        local = make_env("highway", seed=0, vehicles_count=5)
        local.reset()
        env = make_parallel_env("highway", num_workers=2, seed=0, mp_start_method="fork", vehicles_count=5)
        td = env.rand_step(env.reset())
        pixels = td["next", "pixels"]
        print(json.dumps({"shape": list(pixels.shape), "std": pixels.float().std(dim=(1, 2, 3)).tolist()}))
        env.close()
        local.close()
        """,
        env=dict(os.environ),
    )
    assert result["shape"] == [2, 3, 64, 64]
    assert min(result["std"]) > 10  # real frames (sky, road, cars), not blank ones


def test_first_person_view_renders_when_torchrl_is_imported_first_without_mujoco_gl():
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    result = _run(
        """
        import json
        import torchrl.envs  # imports mujoco, which then fixes mujoco.GLContext to GLFW (no display here)
        import mujoco
        from isodream_rl.envs import make_gym_env
        env = make_gym_env("highway", vehicles_count=5)
        obs, _ = env.reset(seed=0)
        print(json.dumps({
            "mujoco_default": mujoco.GLContext.__module__,
            "backend": env.unwrapped._renderer._renderer.backend,
            "std": float(obs.std()),
        }))
        env.close()
        """,
        env=env,
    )
    assert result["mujoco_default"] == "mujoco.glfw", "precondition: mujoco chose GLFW at import"
    assert result["backend"] == "egl"
    assert result["std"] > 10


def test_fork_is_refused_for_gl_envs_while_llvmpipe_runs_threads(monkeypatch):
    monkeypatch.setenv("LP_NUM_THREADS", "2")
    for name, cfg in (("highway", {}), ("dmc_walker_walk", {})):
        with pytest.raises(ValueError, match="LP_NUM_THREADS=0"):
            make_parallel_env(name, num_workers=2, mp_start_method="fork", **cfg)
