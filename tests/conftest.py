import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")

import importlib.util  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

BENCH = Path(__file__).resolve().parents[1] / "bench"


def load_bench(name: str):
    """A script of ``bench/`` (not a package) as a module, e.g. ``load_bench("learning")``."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


def cli_env():
    """The environment of the CLI commands the tests run: one torch thread, one-line errors."""
    return dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="0")


def cli_process(args, cwd):
    """``python -m isodream_rl.cli *args`` started in ``cwd`` (:func:`cli_env`), text pipes."""
    import subprocess
    import sys

    return subprocess.Popen(
        [sys.executable, "-m", "isodream_rl.cli", *args],
        cwd=cwd,
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def cli_run(args, cwd, *, timeout=600):
    """``python -m isodream_rl.cli *args`` run to its end in ``cwd`` (:func:`cli_env`), a
    ``subprocess.CompletedProcess``: a process of its own, forked from one that paid the imports once
    (``tests/forked_commands.py``)."""
    from tests.forked_commands import run_module

    return run_module("isodream_rl.cli", list(args), cwd, cli_env(), timeout=timeout)


def tiny_run_config(run_dir, **changes):
    """A sprites ``RunConfig`` of Iso-Dream on the DreamerV2-style learner (``algo=isodream_v2``; the DreamerV3
    learner's tiny runs are ``tests/test_isodream.py``'s) at test sizes: tiny world model, 16-unit actor and
    value, windows of 2 x 6, 10 prefill steps, one batch every 10 steps, 20 steps in all, horizon 3. ``changes``
    override fields by ``section__name`` (``train__total_steps=30``; a plain name sets a top-level field)."""
    from isodream_rl.trainers import RunConfig

    cfg = RunConfig(run_dir=str(run_dir), size_name="tiny")
    cfg.algo.name = "isodream_v2"
    cfg.model.size, cfg.model.actor_units, cfg.model.value_units, cfg.model.attention_dim = "tiny", 16, 16, 8
    cfg.train.batch_size, cfg.train.sequence_length, cfg.train.buffer_size = 2, 6, 100
    cfg.train.prefill_steps, cfg.train.frames_per_batch, cfg.train.total_steps = 10, 10, 20
    cfg.train.threads = 1
    cfg.algo.horizon, cfg.algo.attention_window = 3, 2
    cfg.logging.video_length, cfg.logging.video_context = 6, 3
    for key, value in changes.items():
        section, _, name = key.rpartition("__")
        setattr(getattr(cfg, section) if section else cfg, name, value)
    return cfg


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
