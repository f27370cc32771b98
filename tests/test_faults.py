"""Fault injection: each fault of issues 27, 37 and 45, ending in a clear error or a documented recovery.

Faults (``fault``): a second run in a used run folder, a truncated replay memmap, a ``state.pt`` without its keys,
a checkpoint without its manifest, a corrupted byte, a resume with another algorithm, SIGKILL and a full disk
while a checkpoint is written, a corrupted CSV log, an env raising mid-episode in a parallel collector, NaN
losses; and, from the command line with real processes and real disks: two runs in one run folder, a resume
while the run trains, SIGKILL then resume (one lock, one timeline of logs), Ctrl-C then resume (exit 130), NaN
or inf frames and rewards mid-run (in this process and in collector workers), a corrupt ``run_config.json`` and
a run-dir check that raises, a checkpoint of ``algo=isodream`` from when it was the DreamerV2-style learner and
weights of other widths, a tmpfs that fills up,
a start that fails, ``isodream-video train`` twice into one folder and stopped by a signal. Bad inputs
(``refused``): pixels in the wrong range or NaN, NaN actions, no ``is_init``, 1-step windows, image sizes, argument
types, and the CLIs' user errors (unknown settings and group options, run folders that cannot be written, damaged
files). Where a checkpoint survives, it
is the last verified one and continuing from it gives the very losses the run gave after it (``continued``).
``bench/reliability_table.py`` runs this file and writes ``docs/results/reliability.md`` from its report; each
test's docstring is its row.
"""

import copy
import dataclasses
import errno
import json
import logging
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.transforms import DTypeCastTransform, ObservationNorm, Transform

from isodream_rl.data import write_tiny_bair
from isodream_rl.envs import make_env
from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel
from isodream_rl.objectives.isodream_v2 import IsoDreamV2ModelLoss
from isodream_rl.run_utils import checkpoint as checkpoint_module
from isodream_rl.run_utils.checkpoint import set_rng_state, write_manifest
from isodream_rl.run_utils.run_folder import existing_run_files
from isodream_rl.run_utils.run_lock import LOCK_FILE, lock_owner
from isodream_rl.trainers import (
    CheckpointError,
    CheckpointManager,
    ConfigError,
    IsoDreamV2Components,
    NonFiniteLossError,
    RunConfig,
    evaluate_checkpoint,
    train,
)
from isodream_rl.trainers.config import config_from_dict
from isodream_rl.trainers.hooks import ReplayPreparation
from isodream_rl.trainers.run_dir import RUN_FILES
from isodream_rl.trainers.saved_models import CheckpointMismatchError
from tests.conftest import tiny_run_config
from tests.forked_commands import run_module

ROOT = Path(__file__).resolve().parents[1]
A = 2  # sprites' action width


def tiny_run(run_dir, **changes) -> RunConfig:
    """A sprites run of 30 steps (prefill 10, an update every 5 steps), checkpoints every 2 updates."""
    defaults = {
        "train__total_steps": 30,
        "env__kwargs": {"task": "reach", "max_steps": 20},
        "logging__eval_every": 0,
        "logging__final_eval_episodes": 0,
        "logging__progress_bar": False,
        "logging__log_every": 5,
        "checkpoint__every_updates": 2,
    }
    return tiny_run_config(run_dir, **{**defaults, **changes})


@pytest.fixture
def said(record_property):
    """``said(text, limit=300)``: what the library said, recorded in the JUnit report
    (``bench/reliability_table.py`` shows it), cut to ``limit`` characters; ``tmp_path`` prefixes are cut."""

    def record(text: str, *, limit: int = 300) -> None:
        text = " ".join(str(text).split())
        text = re.sub(r"/tmp/\S*?/(?=run\b|checkpoints\b|lineage\b)", "", text)
        record_property("said", text[:limit])

    return record


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A finished tiny run (never modified: tests copy it)."""
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    result = train(tiny_run(run_dir))
    assert result.env_steps == 30 and result.checkpoint is not None
    return run_dir


def copy_of(run_dir: Path, tmp_path: Path) -> Path:
    target = tmp_path / "run"
    shutil.copytree(run_dir, target)
    return target


# ---------------------------------------------------------------- checkpoints written by a known run


class Lineage:
    """Components trained on fixed replay data with checkpoints at updates 2 and 4; ``after[k]`` are the losses
    of the two updates that followed checkpoint ``k`` in that process (the run that was not interrupted)."""

    def __init__(self, tmp_path: Path) -> None:
        self.cfg = tiny_run(tmp_path / "lineage")
        self.manager = CheckpointManager(tmp_path / "lineage" / "checkpoints", keep=2)
        torch.manual_seed(0)
        components = self.components(tmp_path / "scratch_a")
        prep = ReplayPreparation(num_envs=1, capacity_per_env=100)
        steps = TensorDict(
            {
                "action": torch.rand(40, A) * 2 - 1,
                "is_init": (torch.arange(40) % 20 == 0)[:, None],
                ("next", "pixels"): torch.randint(0, 256, (40, 3, 64, 64), dtype=torch.uint8),
                ("next", "reward"): torch.randn(40, 1),
            },
            [40],
        )
        components.replay_buffer.extend(prep(steps))
        self.after: dict[int, list[float]] = {}
        for _ in range(2):
            self.update(components)
        for step in (2, 4):
            self.manager.save(step, self.state(components), replay_buffer=components.replay_buffer)
            self.after[step] = [self.update(components) for _ in range(2)]
        self.live = components

    def components(self, scratch: Path) -> IsoDreamV2Components:
        return IsoDreamV2Components(self.cfg, action_dim=A, scratch_dir=scratch)

    def state(self, components: IsoDreamV2Components) -> dict:
        return components.state(self.cfg, env_steps=0, trainer=None)

    @staticmethod
    def update(components: IsoDreamV2Components) -> float:
        return float(components.stepper.step(None, components.replay_buffer.sample())["loss_model_reco"])

    def continue_from(self, tmp_path: Path, name: str = "scratch_b") -> tuple[Path, list[float]]:
        """Load the newest readable checkpoint into fresh components; its path and the next two losses."""
        components = self.components(tmp_path / name)
        state, path = self.manager.load_latest(replay_buffer=components.replay_buffer)
        components.load_models(state)
        components.stepper.load_state_dict(state["stepper"])
        set_rng_state(state["rng"])
        return path, [self.update(components) for _ in range(2)]


@pytest.fixture(scope="module")
def trained_lineage(tmp_path_factory):
    return Lineage(tmp_path_factory.mktemp("lineage"))


@pytest.fixture
def lineage(trained_lineage, tmp_path):
    """The trained lineage with a copy of its checkpoints (a test may break them)."""
    lineage = copy.copy(trained_lineage)
    shutil.copytree(trained_lineage.manager.directory, tmp_path / "checkpoints")
    lineage.manager = CheckpointManager(tmp_path / "checkpoints", keep=2)
    return lineage


def test_resume_is_exact(lineage, tmp_path):
    """fault: none (reference) | continued: the newest checkpoint continues with the uninterrupted run's losses,
    bit for bit (the stepper's first-update key discovery draws from a forked generator)"""
    path, losses = lineage.continue_from(tmp_path)
    assert path.name == "step_00000004" and losses == lineage.after[4]


def test_truncated_replay_memmap_falls_back_and_is_never_written(lineage, tmp_path, caplog, said):
    """fault: the newest checkpoint's replay pixels.memmap truncated | recovered: a warning, the previous
    checkpoint loads, the truncated file is left as it was"""
    newest = lineage.manager.checkpoints()[-1]
    memmap = next((newest / "replay").rglob("pixels.memmap"))
    memmap.write_bytes(memmap.read_bytes()[: memmap.stat().st_size // 2])
    before = snapshot(lineage.manager.directory)
    stamps = {p: p.stat().st_mtime_ns for p in lineage.manager.directory.rglob("*") if p.is_file()}
    with caplog.at_level(logging.WARNING):
        path, losses = lineage.continue_from(tmp_path)
    assert "truncated" in caplog.text and "falling back to the previous one" in caplog.text
    said(caplog.records[0].getMessage())
    assert path.name == "step_00000002" and losses == lineage.after[2]
    # loading wrote nothing: neither the truncated checkpoint nor the one it loaded (replay read from a copy)
    assert snapshot(lineage.manager.directory) == before
    assert {p: p.stat().st_mtime_ns for p in lineage.manager.directory.rglob("*") if p.is_file()} == stamps


def test_checkpoint_without_manifest_is_unverified_and_falls_back(lineage, tmp_path, caplog, said):
    """fault: the newest checkpoint's manifest.json deleted and its replay pixels.memmap cut to a third (was:
    read without verification, the missing frames filled with zeros) | recovered: a warning that it cannot be
    verified, the previous (verified) checkpoint loads and continues exactly"""
    newest = lineage.manager.checkpoints()[-1]
    (newest / "manifest.json").unlink()
    memmap = next((newest / "replay").rglob("pixels.memmap"))
    memmap.write_bytes(memmap.read_bytes()[: memmap.stat().st_size // 3])
    with caplog.at_level(logging.WARNING):
        path, losses = lineage.continue_from(tmp_path)
    assert "no manifest.json" in caplog.text and "falling back to the previous one" in caplog.text
    said(caplog.records[0].getMessage())
    assert path.name == "step_00000002" and losses == lineage.after[2]


def test_state_without_its_keys_falls_back(lineage, tmp_path, caplog, said):
    """fault: the newest state.pt a valid torch file without 'config' (manifest rewritten to match) |
    recovered: a warning naming the key, the previous checkpoint loads"""
    newest = lineage.manager.checkpoints()[-1]
    state = torch.load(newest / "state.pt", weights_only=False)
    del state["config"]
    torch.save(state, newest / "state.pt")
    write_manifest(newest)
    components = lineage.components(tmp_path / "scratch_b")
    with caplog.at_level(logging.WARNING):
        _, path = lineage.manager.load_latest(
            replay_buffer=components.replay_buffer, required_keys=("config", "models")
        )
    assert path.name == "step_00000002" and "['config']" in caplog.text
    said(caplog.records[0].getMessage())


def test_flipped_byte_falls_back_and_none_readable_is_a_checkpoint_error(lineage, tmp_path, said):
    """fault: one byte of each checkpoint's state.pt flipped (same size) | recovered: checksum mismatch, the
    previous one loads; with none readable, CheckpointError lists every checkpoint and its fault"""
    first, newest = lineage.manager.checkpoints()
    for folder in (newest, first):
        data = bytearray((folder / "state.pt").read_bytes())
        data[len(data) // 2] ^= 0xFF
        (folder / "state.pt").write_bytes(bytes(data))
        if folder is newest:
            assert lineage.manager.load_latest()[1].name == "step_00000002"
    with pytest.raises(CheckpointError, match="(?s)no readable checkpoint.*checksum.*checksum") as error:
        lineage.manager.load_latest()
    said(error.value)


def test_full_disk_while_writing_keeps_the_previous_checkpoints(lineage, tmp_path, monkeypatch, said):
    """fault: the disk fills up (OSError ENOSPC) while a checkpoint is written | recovered: CheckpointError
    saying to free space and resume, no half checkpoint, the last verified checkpoint continues exactly"""

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoint_module, "write_manifest", full_disk)
    with pytest.raises(CheckpointError, match="No space left on device.*free disk space") as error:
        lineage.manager.save(6, lineage.state(lineage.live), replay_buffer=lineage.live.replay_buffer)
    said(error.value)
    monkeypatch.undo()
    assert sorted(p.name for p in lineage.manager.directory.iterdir()) == ["step_00000002", "step_00000004"]
    path, losses = lineage.continue_from(tmp_path)
    assert path.name == "step_00000004" and losses == lineage.after[4]


def test_rotation_after_a_fallback_keeps_the_verified_checkpoint(lineage, tmp_path):
    """fault: resumed from the previous checkpoint (newest corrupted), then saved | recovered: the corrupted
    newer one is deleted only after the new one is verified; the one resumed from is kept"""
    newest = lineage.manager.checkpoints()[-1]
    (newest / "state.pt").write_bytes(b"\0" * 64)
    components = lineage.components(tmp_path / "scratch_b")
    state, path = lineage.manager.load_latest(replay_buffer=components.replay_buffer)
    components.load_models(state)
    components.stepper.load_state_dict(state["stepper"])
    lineage.update(components)
    lineage.manager.save(3, lineage.state(components), replay_buffer=components.replay_buffer)
    assert [p.name for p in lineage.manager.checkpoints()] == ["step_00000002", "step_00000003"]
    assert lineage.manager.load_latest()[1].name == "step_00000003"


_KILLED_WRITER = textwrap.dedent(
    """
    import sys, time
    import torch
    from isodream_rl.trainers import CheckpointManager

    class SlowReplay:  # a replay buffer whose dump never ends
        def dumps(self, path):
            path.mkdir()
            (path / "pixels.memmap").write_bytes(b"x" * 1000)
            print("writing", flush=True)
            time.sleep(600)

    manager = CheckpointManager(sys.argv[1], keep=2)
    manager.save(1, {"step": 1})
    manager.save(2, {"step": 2}, replay_buffer=SlowReplay())
    """
)


def test_sigkill_during_a_checkpoint_write(tmp_path):
    """fault: SIGKILL while a checkpoint is being written | recovered: the half-written step_*.tmp is ignored,
    the previous checkpoint loads, the next save removes the leftover"""
    directory = tmp_path / "checkpoints"
    proc = subprocess.Popen(
        [sys.executable, "-c", _KILLED_WRITER, str(directory)],
        stdout=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1"),
    )
    try:
        assert proc.stdout.readline().strip() == "writing"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert (directory / "step_00000002.tmp").exists()
    manager = CheckpointManager(directory, keep=2)
    state, path = manager.load_latest()
    assert state["step"] == 1 and path.name == "step_00000001"
    manager.save(3, {"step": 3})
    assert sorted(p.name for p in directory.iterdir()) == ["step_00000001", "step_00000003"]


def test_nan_loss_is_skipped_then_stops_the_run(lineage, tmp_path, monkeypatch, said):
    """fault: NaN injected in the world-model loss | recovered: the update is skipped (weights and counter
    unchanged), K in a row raise NonFiniteLossError naming the learning rates; the last checkpoint continues
    exactly"""
    components = lineage.live
    loss = components.model_loss
    forward = type(loss).forward

    def nan_forward(self, td):
        losses, out = forward(self, td)
        losses["loss_model_reco"] = losses["loss_model_reco"] * float("nan")
        return losses, out

    weights = {k: v.clone() for k, v in components.world_model.state_dict().items()}
    updates = components.stepper.updates
    monkeypatch.setattr(type(loss), "forward", nan_forward)
    metrics = components.stepper.step(None, components.replay_buffer.sample())
    assert metrics["nonfinite_skipped"] == 1 and components.stepper.updates == updates
    assert all(torch.equal(v, components.world_model.state_dict()[k]) for k, v in weights.items())
    with pytest.raises(NonFiniteLossError, match="train.world_model_lr") as error:
        for _ in range(components.stepper.max_nonfinite):
            components.stepper.step(None, components.replay_buffer.sample())
    said(error.value)
    monkeypatch.undo()
    path, losses = lineage.continue_from(tmp_path)
    assert path.name == "step_00000004" and losses == lineage.after[4]


# ---------------------------------------------------------------- whole runs


def test_second_run_in_a_used_run_dir_is_refused_untouched(finished_run, tmp_path, said):
    """fault: a second run (another seed, shorter) started in a finished run's folder without resume |
    refused with one message naming resume=true and overwrite=true, not one file of the first run changed;
    overwrite=true replaces it"""
    run_dir = copy_of(finished_run, tmp_path)
    before = snapshot(run_dir)
    with pytest.raises(ConfigError, match="holds another run.*resume=true.*overwrite=true") as error:
        train(tiny_run(run_dir, train__seed=3, train__total_steps=20))
    said(error.value)
    assert snapshot(run_dir) == before
    result = train(tiny_run(run_dir, train__seed=3, train__total_steps=20, overwrite=True))
    assert result.env_steps == 20
    saved = json.loads((run_dir / "run_config.json").read_text())
    assert saved["train"]["seed"] == 3
    assert [p.name for p in CheckpointManager(run_dir / "checkpoints").checkpoints()][-1] == "step_00000004"


def test_resume_with_another_algorithm_is_refused_before_writing(finished_run, tmp_path, said):
    """fault: resume=true with algo=dreamerv2 settings on an Iso-Dream run | refused with the differing
    settings listed with both values; run_config.json and the checkpoints untouched"""
    run_dir = copy_of(finished_run, tmp_path)
    before = snapshot(run_dir)
    cfg = tiny_run(run_dir, resume=True, train__total_steps=40)
    cfg.algo = dataclasses.replace(
        cfg.algo, name="dreamerv2", free_branch=False, static_branch=False, inverse_dynamics=False
    )
    cfg.algo.policy_input = "controllable"
    with pytest.raises(
        ConfigError, match=r"algo.free_branch: True -> False.*algo.name: 'isodream_v2' -> 'dreamerv2'"
    ) as error:
        train(cfg)
    said(error.value)
    assert snapshot(run_dir) == before


def test_resume_with_a_corrupted_csv_log_continues(finished_run, tmp_path):
    """fault: a CSV log file corrupted after the last checkpoint (binary junk, a cut line) | recovered: resuming
    cuts it back to its size at the checkpoint (the junk past it dropped, the cut row ended with a newline) and
    appends its rows on lines of their own; the checkpoints, not the logs, hold the run's state"""
    run_dir = copy_of(finished_run, tmp_path)
    log = next((run_dir / "logs").rglob("loss_model_reco.csv"))
    original = log.read_bytes()
    log.write_bytes(original[:-7] + b"\x00\xff garbage,\n12,")
    result = train(tiny_run(run_dir, resume=True, train__total_steps=40))
    assert result.env_steps == 40 and result.resumed_from is not None
    content = log.read_bytes()
    assert content.startswith(original[:-7]) and b"garbage," not in content and b"\n12," not in content
    step, value = content.splitlines()[-1].split(b",")
    assert 30 < int(step) <= 40 and float(value) > 0


class RaisingEnv(gym.Wrapper):
    """Sprites whose simulator raises at step 7 of every episode."""

    def reset(self, **kwargs):
        self.steps = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        self.steps += 1
        if self.steps == 7:
            raise RuntimeError("injected simulator fault")
        return self.env.step(action)


def raising_sprites(**kwargs):
    """``env.factory`` of the parallel-collector test."""
    from isodream_rl.envs.builder import make_gym_env, wrap_gym_env

    return wrap_gym_env(RaisingEnv(make_gym_env("sprites", **kwargs)), name="sprites")


def test_env_raising_mid_episode_in_a_parallel_collector(tmp_path):
    """fault: the env raises mid-episode in each of 2 collector worker processes | recovered: the episode ends
    there (truncated, sim_error=True, a warning) and the run completes"""
    cfg = tiny_run(tmp_path / "run", env__num_envs=2, env__factory="tests.test_faults:raising_sprites")
    cfg.train.frames_per_batch, cfg.train.total_steps, cfg.train.prefill_steps = 10, 30, 20
    result = train(cfg)
    assert result.env_steps == 30 and result.updates > 0


# ---------------------------------------------------------------- whole runs from the command line

#: a tiny isodream-train run: no final evaluation, no progress bar, one thread
TINY_TRAIN = ["size=tiny", "train.threads=1", "logging.final_eval_episodes=0", "logging.progress_bar=false"]


def start_command(module: str, args: list[str], cwd: Path) -> subprocess.Popen:
    """``python -m <module> *args`` started in ``cwd``, as :func:`run_command` runs it, with text pipes."""
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=command_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_for(condition, process: subprocess.Popen, *, timeout: float = 300.0) -> None:
    """Poll ``condition()`` every 0.1 s while ``process`` runs."""
    deadline = time.monotonic() + timeout
    while not condition():
        if process.poll() is not None:
            raise AssertionError(f"the process ended first: {process.communicate()[1][-2000:]}")
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.1)


def user_error(out: subprocess.CompletedProcess | tuple[str, str], prog: str = "isodream-train") -> str:
    """The one ``<prog>: ...`` line of a refused command's stderr (asserting there is one, and no traceback)."""
    stderr = out.stderr if isinstance(out, subprocess.CompletedProcess) else out[1]
    lines = [line for line in stderr.splitlines() if line.startswith(f"{prog}:")]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr[-3000:]
    return lines[0]


def logged_steps(run_dir: Path) -> dict[str, list[int]]:
    """``{scalar: [steps]}`` of the run's CSV logs."""
    return {
        path.stem: [int(line.split(",")[0]) for line in path.read_text().splitlines()]
        for path in (run_dir / "logs").rglob("*.csv")
    }


def assert_one_timeline(run_dir: Path) -> None:
    """Every CSV log holds each step once, in order."""
    steps = logged_steps(run_dir)
    assert steps and all(rows == sorted(set(rows)) for rows in steps.values()), steps


def test_two_runs_started_together_in_one_run_dir(tmp_path, said):
    """fault: two isodream-train started together on one empty run_dir, seeds 0 and 1 (was: both passed the
    guard; the second rewrote run_config.json with its seed, and resume was then refused with either seed) |
    refused: one of them, in one line naming the other's pid (exit 2), before writing anything; run_config.json,
    the checkpoints and the logs are the other's alone"""
    args = [*TINY_TRAIN, "run_dir=run", "train.total_steps=150"]
    runs = {
        seed: start_command("isodream_rl.cli", [*args, f"train.seed={seed}"], tmp_path) for seed in (0, 1)
    }
    outs = {seed: run.communicate(timeout=900) for seed, run in runs.items()}
    assert sorted(run.returncode for run in runs.values()) == [0, 2], outs
    winner = next(seed for seed, run in runs.items() if run.returncode == 0)
    line = user_error(outs[1 - winner])
    assert f"in use by process {runs[winner].pid}" in line
    said(line)
    run_dir = tmp_path / "run"
    assert json.loads((run_dir / "run_config.json").read_text())["train"]["seed"] == winner
    state, _ = CheckpointManager(run_dir / "checkpoints").load_latest()
    assert state["config"]["train"]["seed"] == winner and state["counters"]["env_steps"] == 150
    assert_one_timeline(run_dir)
    assert not (run_dir / LOCK_FILE).exists()


def test_resume_while_the_run_trains_is_refused_naming_its_pid(tmp_path, said):
    """fault: resume=true, then a new run with another seed, started in a run_dir whose run still trains (was:
    both trained, each checkpoint save deleted the other's checkpoint in progress, both wrote the logs) |
    refused: each in one line naming the training process's pid (exit 2); that run trains on alone (stopped
    with SIGTERM: a checkpoint, then exit 143)"""
    run_dir = tmp_path / "run"
    first = start_command(
        "isodream_rl.cli", [*TINY_TRAIN, "run_dir=run", "train.total_steps=20000"], tmp_path
    )
    try:
        wait_for(
            lambda: lock_owner(run_dir) == first.pid and any((run_dir / "checkpoints").glob("step_*")), first
        )
        lines = []
        for extra in (["resume=true"], ["train.seed=1"]):
            out = run_command("isodream_rl.cli", [*TINY_TRAIN, "run_dir=run", *extra], tmp_path)
            assert out.returncode == 2
            lines.append(user_error(out))
            assert f"in use by process {first.pid}" in lines[-1]
        said(lines[0])
        assert first.poll() is None
    finally:
        first.send_signal(signal.SIGTERM)
        out = first.communicate(timeout=900)
    assert first.returncode == 128 + signal.SIGTERM, out[1][-2000:]
    assert user_error(out).startswith("isodream-train: stopped at ")
    state, _ = CheckpointManager(run_dir / "checkpoints").load_latest()
    assert (
        state["config"]["train"]["seed"] == 0
        and json.loads((run_dir / "run_config.json").read_text())["train"]["seed"] == 0
    )
    assert_one_timeline(run_dir)


def test_sigkill_then_resume_takes_over_the_lock_and_logs_one_timeline(tmp_path, said):
    """fault: SIGKILL after the run logged rows past its last checkpoint, then resume=true (was: those rows stayed
    and the resumed run logged the same steps again, step 150 twice) | recovered: the resumed run takes over the
    dead process's lock (a warning naming its pid), cuts the CSV logs back to the checkpoint and logs each step
    once"""
    run_dir = tmp_path / "run"
    args = [
        *TINY_TRAIN,
        "run_dir=run",
        "train.total_steps=300",
        "logging.log_every=49",
        "checkpoint.every_updates=20",
    ]
    first = start_command("isodream_rl.cli", args, tmp_path)
    try:  # rows every 50 steps, checkpoints every 100: kill once step 150 is logged, before the next checkpoint
        wait_for(lambda: 150 in logged_steps(run_dir).get("loss_model_reco", []), first)
    finally:
        first.send_signal(signal.SIGKILL)
        first.communicate()
    state, checkpoint = CheckpointManager(run_dir / "checkpoints").load_latest()
    assert max(logged_steps(run_dir)["loss_model_reco"]) > state["counters"]["env_steps"]
    assert (run_dir / LOCK_FILE).read_text().strip() == str(first.pid)
    out = run_command("isodream_rl.cli", [*args, "resume=true"], tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    takeover = next(line for line in out.stderr.splitlines() if "taking over" in line)
    assert f"process {first.pid}" in takeover
    assert f"resumed from run/checkpoints/{checkpoint.name}" in out.stdout
    said(takeover.partition(": ")[2])
    assert_one_timeline(run_dir)
    assert logged_steps(run_dir)["loss_model_reco"][-1] == 300 and not (run_dir / LOCK_FILE).exists()


def test_ctrl_c_exits_as_a_stopped_run_and_resume_continues_it(tmp_path, said):
    """fault: SIGINT (Ctrl-C) to isodream-train after its first checkpoint (was: a checkpoint, then exit 0, as a
    finished run: `isodream-train ... && isodream-eval ...` or a scheduler took it for done) | recovered: a
    checkpoint, one line saying where it stopped and to continue with resume=true, exit status 130 (143 for
    SIGTERM, the shell's convention); resume=true continues from that checkpoint to the end"""
    run_dir = tmp_path / "run"
    first = start_command(
        "isodream_rl.cli", [*TINY_TRAIN, "run_dir=run", "train.total_steps=20000"], tmp_path
    )
    try:
        wait_for(lambda: any((run_dir / "checkpoints").glob("step_*[0-9]")), first)
    finally:
        first.send_signal(signal.SIGINT)
        out = first.communicate(timeout=900)
    assert first.returncode == 130, out[1][-3000:]
    state, checkpoint = CheckpointManager(run_dir / "checkpoints").load_latest()
    steps = state["counters"]["env_steps"]
    line = user_error(out)
    assert line == (
        f"isodream-train: stopped at {steps} env steps by SIGINT (checkpoint run/checkpoints/{checkpoint.name}); "
        "continue with resume=true"
    )
    said(line)
    assert "run finished" not in out[0]
    resumed = run_command(
        "isodream_rl.cli",
        [*TINY_TRAIN, "run_dir=run", f"train.total_steps={steps + 50}", "resume=true"],
        tmp_path,
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resumed from run/checkpoints/{checkpoint.name}" in resumed.stdout
    assert f"run finished: {steps + 50} env steps" in resumed.stdout
    assert_one_timeline(run_dir)


#: ``{case: (entry, value, also resumed once the env is fixed)}``
BAD_ENV_CASES = {
    "NaN pixels": ("pixels", "nan", True),
    "inf pixels": ("pixels", "inf", False),
    "NaN reward": ("reward", "nan", False),
    "-inf reward": ("reward", "-inf", False),
}


#: the cases also run with two collector worker processes (``env.num_envs=2``)
BAD_ENV_WORKER_CASES = ("NaN pixels", "-inf reward")


@pytest.mark.parametrize(
    "case,num_envs",
    [(case, 1) for case in BAD_ENV_CASES] + [(case, 2) for case in BAD_ENV_WORKER_CASES],
    ids=[*BAD_ENV_CASES, *(f"{case}, 2 worker envs" for case in BAD_ENV_WORKER_CASES)],
)
def test_nan_or_inf_env_data_stops_the_run_in_one_line(case, num_envs, tmp_path, said):
    """fault: an env.factory whose float frames in [0, 1], or rewards, turn NaN or inf after 80 frames, once the
    policy acts (was: for NaN frames the policy's `normal expects all elements of std >= 0.0` traceback, exit 1,
    before the loss's own check saw the batch), in this process or in each of 2 collector worker processes
    (was there: the worker died with a traceback of its own and the run stopped later on "a process failed")
    | refused: one line naming the entry, the env step and the env (which worker's), and the last checkpoint to
    continue from (exit 2), the step refused before the policy acts on it or the replay stores it (a worker
    marks it in the batch, which the run refuses); once the env is fixed, resume=true continues from that
    checkpoint (checked in this process: `NaN pixels`)"""
    key, value, resume = BAD_ENV_CASES[case]
    total = 120 * num_envs
    args = [
        *TINY_TRAIN,
        "run_dir=run",
        "env.factory=tests.test_faults:bad_data_sprites",
        "train.prefill_steps=20",
        "train.frames_per_batch=20",
        "checkpoint.every_updates=4",
        f"train.total_steps={total}",
        f"env.num_envs={num_envs}",
    ]
    out = run_command("isodream_rl.cli", args, tmp_path, **{BAD_ENV_DATA: f"{key}:{value}"})
    assert out.returncode == 2, out.stderr[-3000:]
    line = user_error(out)
    state, checkpoint = CheckpointManager(tmp_path / "run" / "checkpoints").load_latest()
    found = {"nan": "NaN", "inf": "inf", "-inf": "inf"}[value]
    which = (
        " (collector env 1 of 2)" if num_envs == 2 else ""
    )  # both go bad at their 80th step; the first named
    assert line == (
        f"isodream-train: env.factory=tests.test_faults:bad_data_sprites{which} gave {key!r} holding {found} at "
        f"env step 80; the last checkpoint, run/checkpoints/{checkpoint.name}, is intact: fix the env, then "
        "continue with resume=true"
    )
    said(line)
    assert state["counters"]["env_steps"] < 80 * num_envs
    if resume and num_envs == 1:  # resuming with 2 worker envs takes the same path: checked once, here
        resumed = run_command("isodream_rl.cli", [*args, "resume=true"], tmp_path)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
        assert f"resumed from run/checkpoints/{checkpoint.name}" in resumed.stdout
        assert f"run finished: {total} env steps" in resumed.stdout


@pytest.fixture
def tmpfs(tmp_path):
    """``tmpfs(size, *options)``: a new tmpfs of ``size`` (mount's ``size=``, e.g. ``"70m"``) under ``tmp_path``,
    unmounted after the test; the test is skipped where it cannot be mounted (not root, or not allowed here)."""
    mounted = []

    def mount(size: str, *options: str) -> Path:
        if os.geteuid() != 0:
            pytest.skip("a real full disk is a small tmpfs, and mounting one needs root")
        point = tmp_path / f"disk{len(mounted)}"
        point.mkdir()
        out = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", ",".join([f"size={size}", *options]), "tmpfs", str(point)],
            capture_output=True,
            text=True,
        )
        if out.returncode:
            pytest.skip(f"cannot mount a tmpfs here: {out.stderr.strip()}")
        mounted.append(point)
        return point

    yield mount
    for point in mounted:
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


def test_full_disk_at_a_checkpoint_on_a_real_disk(tmpfs, tmp_path, said):
    """fault: run_dir on a 70 MB tmpfs that fills at the second checkpoint, then resume=true on the still full
    disk (a crashed save's .tmp left there too), then resume=true once space is freed (was: SIGBUS, exit 135 and
    no word, the half checkpoint left; the resume a traceback) | recovered: one line naming the checkpoint kept and
    saying to free disk space and resume=true (exit 2), no half checkpoint; the resume on the full disk one such
    line too, the checkpoint intact, the leftover .tmp removed; once space is freed, the run continues from the
    last verified checkpoint"""
    disk = tmpfs("70m")  # the replay memory takes 24 MB, each checkpoint 29 MB: the second one does not fit
    args = [*TINY_TRAIN, f"run_dir={disk / 'run'}", "train.total_steps=150"]
    out = run_command("isodream_rl.cli", args, tmp_path)
    assert out.returncode == 2, out.stderr[-3000:]
    line = user_error(out)
    assert "step_00000020 failed" in line and "No space left on device" in line and "step_00000010" in line
    assert "free disk space" in line and "resume=true" in line
    manager = CheckpointManager(disk / "run" / "checkpoints")
    assert sorted(p.name for p in manager.directory.iterdir()) == ["step_00000010"]
    before = snapshot(manager.directory)
    leftover = manager.directory / "step_00000020.tmp" / "replay"  # as a save killed mid-write leaves it
    leftover.mkdir(parents=True)
    (leftover / "pixels.memmap").write_bytes(b"\0" * (2 << 20))
    out = run_command("isodream_rl.cli", [*args, "resume=true"], tmp_path)
    assert out.returncode == 2, out.stderr[-3000:]
    full = user_error(out)
    assert "No space left on device" in full and "free disk space, then continue with resume=true" in full
    said(f"{line} -- resumed on the full disk: {full}".replace(str(tmp_path) + "/", ""), limit=800)
    assert snapshot(manager.directory) == before
    subprocess.run(["mount", "-o", "remount,size=256m", str(disk)], check=True)
    out = run_command("isodream_rl.cli", [*args, "resume=true"], tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "resumed from" in out.stdout and "step_00000010" in out.stdout
    assert manager.load_latest()[0]["counters"]["env_steps"] == 150


def test_full_disk_before_the_replay_memory_is_written(tmpfs, tmp_path, said):
    """fault: run_dir on a 16 MB tmpfs, smaller than the replay memory (24 MB; was: SIGBUS once its memory-mapped
    pages met the full disk) | refused: one line saying what the replay memory needs and what is free, and to free
    disk space (exit 2), before a page of it is written"""
    disk = tmpfs("16m")
    out = run_command(
        "isodream_rl.cli", [*TINY_TRAIN, f"run_dir={disk / 'run'}", "train.total_steps=100"], tmp_path
    )
    assert out.returncode == 2, out.stderr[-3000:]
    line = user_error(out)
    assert "replay memory" in line and "MB are free" in line and "free disk space" in line
    said(line.replace(str(tmp_path) + "/", ""))


@pytest.mark.parametrize("case", ["a file", "under a file", "on a read-only disk"])
def test_train_cli_refuses_a_run_dir_it_cannot_write(case, tmpfs, tmp_path, said):
    """refused: isodream-train with a run_dir that is a file, under a file, or on a read-only disk (was: a
    traceback; two for the read-only disk, ending in Hydra's logging handler) | one line naming the path and
    what is wrong, exit 2"""
    if case == "a file":
        (tmp_path / "run").write_text("not a folder")
        run_dir = "run"
    elif case == "under a file":
        (tmp_path / "notes").write_text("not a folder")
        run_dir = "notes/run"
    else:
        run_dir = str(tmpfs("1m", "ro") / "run")
    out = run_command("isodream_rl.cli", [*TINY_TRAIN, f"run_dir={run_dir}"], tmp_path)
    assert out.returncode == 2, out.stderr[-3000:]
    line = user_error(out)
    assert f"run_dir {run_dir}" in line
    said(line.replace(str(tmp_path) + "/", ""))


def test_a_start_that_fails_leaves_no_run_and_the_corrected_command_starts(tmp_path, monkeypatch):
    """fault: a start that fails while its parts are built (was: run_config.json written before, so the corrected
    command was refused until overwrite=true) | recovered: run_config.json is written once the run has started, a
    failed start leaves no run files (nor its lock), and the corrected command starts without overwrite=true"""
    from isodream_rl.trainers import run as run_module

    def broken(*args, **kwargs):
        raise RuntimeError("injected build failure")

    monkeypatch.setattr(run_module, "make_components", broken)
    with pytest.raises(RuntimeError, match="injected build failure"):
        train(tiny_run(tmp_path / "run"))
    assert (
        existing_run_files(tmp_path / "run", RUN_FILES) == [] and not (tmp_path / "run" / LOCK_FILE).exists()
    )
    monkeypatch.undo()
    assert train(tiny_run(tmp_path / "run")).env_steps == 30


@pytest.fixture(scope="module")
def bair_files(tmp_path_factory):
    """A tiny BAIR-format data set (3 training and 2 test clips of 5 frames)."""
    return write_tiny_bair(tmp_path_factory.mktemp("bair"))


#: a tiny isodream-video training protocol (clips of 5 frames, 1-layer 4-channel model), without --out-dir
TINY_VIDEO = ["--sequence-length", "5", "--train-frames", "4", "--test-frames", "5", "--horizons", "2", "3",
              "--no-progress", "--checkpoint-every", "1", "--hidden-channels", "4", "--encoder-channels", "4", "4",
              "--kernel-size", "3", "--num-layers", "1", "--action-embedding", "4", "--batch-size", "2",
              "--threads", "1"]  # fmt: skip


@pytest.fixture(scope="module")
def video_run(bair_files, tmp_path_factory):
    """``(out_dir, train arguments)`` of a finished 2-iteration isodream-video run (tests copy it)."""
    from isodream_rl.video_prediction.cli import main

    out_dir = tmp_path_factory.mktemp("video") / "run"
    args = ["train", "--dataset", "bair", "--data-path", str(bair_files), *TINY_VIDEO]
    assert main([*args, "--iterations", "2", "--out-dir", str(out_dir)]) == 0
    return out_dir, args


def video_error(argv: list[str], capsys) -> str:
    """The one line ``isodream-video`` says when it refuses ``argv`` (exit status 2)."""
    from isodream_rl.video_prediction.cli import main

    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("isodream-video: "), err
    return err


def test_video_train_refuses_a_used_out_dir(video_run, tmp_path, capsys, said):
    """fault: isodream-video train run again into an --out-dir holding a run, without --resume (was: the first
    run's checkpoint.pt replaced, both runs' rows in one set of CSVs) | refused: one line naming --resume and
    --overwrite (exit 2), the first run's files untouched; --resume continues it (its logs cut back to its
    checkpoint), --overwrite replaces it"""
    from isodream_rl.video_prediction.cli import main
    from isodream_rl.video_prediction.trainer import read_checkpoint

    out_dir, args = video_run
    out_dir = copy_of(out_dir, tmp_path)
    before = snapshot(out_dir)
    line = video_error([*args, "--iterations", "3", "--out-dir", str(out_dir)], capsys)
    assert "holds another run" in line and "--resume" in line and "--overwrite" in line
    said(line.replace(str(tmp_path) + "/", ""))
    assert snapshot(out_dir) == before
    assert main([*args, "--iterations", "3", "--out-dir", str(out_dir), "--resume"]) == 0
    assert read_checkpoint(out_dir)["iteration"] == 3
    assert_one_timeline(out_dir)
    assert main([*args, "--iterations", "1", "--out-dir", str(out_dir), "--overwrite"]) == 0
    assert read_checkpoint(out_dir)["iteration"] == 1
    assert max(max(rows) for rows in logged_steps(out_dir).values()) == 1
    assert not (out_dir / LOCK_FILE).exists()


@pytest.mark.parametrize("case", ["truncated checkpoint.pt", "random checkpoint.pt", "truncated pusher .npz"])
def test_video_cli_names_an_unreadable_file_in_one_line(case, video_run, tmp_path, capsys, said):
    """refused: isodream-video eval on a truncated or random checkpoint.pt, train on a truncated cached pusher
    .npz (was: a torch.load or BadZipFile traceback, the file not named) | one line naming the file, exit 2"""
    if case.endswith(".npz"):
        from isodream_rl.data import load_pusher_dataset

        load_pusher_dataset(2, 5, seed=0, split="train", cache_dir=tmp_path)
        (path,) = tmp_path.glob("pusher-*.npz")
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
        argv = ["train", "--dataset", "pusher", "--cache-dir", str(tmp_path), "--train-sequences", "2",
                "--test-sequences", "2", "--iterations", "1", "--out-dir", str(tmp_path / "run"),
                *TINY_VIDEO]  # fmt: skip
    else:
        path = tmp_path / "checkpoint.pt"
        data = (video_run[0] / "checkpoints" / "step_00000002" / "state.pt").read_bytes()
        path.write_bytes(data[: len(data) // 3] if case.startswith("truncated") else os.urandom(len(data)))
        argv = ["eval", "--checkpoint", str(path)]
    line = video_error(argv, capsys)
    assert str(path) in line
    said(line.replace(str(tmp_path) + "/", ""))


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_video_train_stopped_by_a_signal_exits_as_stopped_and_resumes(signum, bair_files, tmp_path, said):
    """fault: SIGINT or SIGTERM to isodream-video train after its first checkpoint (was: a KeyboardInterrupt
    traceback, no checkpoint of the iteration reached; SIGTERM killed it) | recovered: a checkpoint of the
    iteration reached, one line saying where it stopped and to continue with --resume, exit status 130 or 143;
    --resume continues from that checkpoint with one timeline of logs"""
    from isodream_rl.video_prediction.trainer import read_checkpoint

    out_dir = tmp_path / "run"
    args = ["train", "--dataset", "bair", "--data-path", str(bair_files), *TINY_VIDEO, "--out-dir", "run"]
    proc = start_command("isodream_rl.video_prediction.cli", [*args, "--iterations", "100000"], tmp_path)
    try:
        wait_for(lambda: any((out_dir / "checkpoints").glob("step_*[0-9]")), proc)
    finally:
        proc.send_signal(signum)
        out = proc.communicate(timeout=600)
    assert proc.returncode == 128 + signum, out[1][-3000:]
    stopped = read_checkpoint(out_dir)["iteration"]
    line = user_error(out, "isodream-video")
    assert line == (
        f"isodream-video: stopped at {stopped} iterations by {signum.name} (checkpoint "
        f"run/checkpoints/step_{stopped:08d}); continue with --resume"
    )
    said(line)
    resumed = run_command(
        "isodream_rl.video_prediction.cli", [*args, "--iterations", str(stopped + 1), "--resume"], tmp_path
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert read_checkpoint(out_dir)["iteration"] == stopped + 1
    assert_one_timeline(out_dir)


# ---------------------------------------------------------------- bad inputs at the boundary


def model_batch(entries: dict | None = None, *, time: int = 4) -> TensorDict:
    data = {
        "action": torch.zeros(2, time, A),
        "is_init": torch.zeros(2, time, 1, dtype=torch.bool),
        ("next", "pixels"): torch.randint(0, 256, (2, time, 3, 64, 64), dtype=torch.uint8),
        ("next", "reward"): torch.zeros(2, time, 1),
    }
    data.update(entries or {})
    return TensorDict({k: v for k, v in data.items() if v is not None}, [2, time])


@pytest.fixture(scope="module")
def model_loss():
    return IsoDreamV2ModelLoss(IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=A)))


PIXELS = torch.randint(0, 256, (2, 4, 3, 64, 64), dtype=torch.uint8)
BAD_INPUTS = {
    "float pixels in [0, 255]": (
        {("next", "pixels"): PIXELS.float()},
        r"must be in \[0, 1\].*\[0, 255\].*divide .* by 255",
    ),
    "float pixels in [-0.5, 0.5]": (
        {("next", "pixels"): PIXELS.float() / 255 - 0.5},
        r"must be in \[0, 1\].*add 0.5",
    ),
    "NaN pixels": ({("next", "pixels"): torch.full((2, 4, 3, 64, 64), float("nan"))}, "NaN or inf"),
    "inf action": ({"action": torch.full((2, 4, A), float("inf"))}, "'action' holds NaN or inf"),
    "no is_init": ({"is_init": None}, "needs 'is_init'"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS), ids=list(BAD_INPUTS))
def test_model_loss_refuses_bad_inputs(model_loss, case, said):
    """refused: IsoDreamV2ModelLoss (through the world model) on a bad batch | a ValueError naming what is
    wrong and the fix (the range [0, 1] and how to get there for pixels)"""
    entries, message = BAD_INPUTS[case]
    with pytest.raises(ValueError, match=message) as error:
        model_loss(model_batch(entries))
    said(error.value)


def test_one_step_window_is_refused_and_checks_can_be_skipped(model_loss, said):
    """refused: IsoDreamV2ModelLoss on a window of T=1 (was an internal tensordict error) | a ValueError asking
    for 2 steps or more; IsoDreamV2WorldModel(check_inputs=False) skips the value checks"""
    with pytest.raises(ValueError, match="at least 2 steps.*got T=1") as error:
        model_loss(model_batch(time=1))
    said(error.value)
    unchecked = IsoDreamV2ModelLoss(
        IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=A), check_inputs=False)
    )
    losses, _ = unchecked(model_batch({("next", "pixels"): PIXELS.float()}))
    assert losses["loss_model_reco"] > 1e5  # the [0, 255] floats, taken as [0, 1]: why the check is on


@pytest.mark.parametrize(
    "name, kwargs, error, message",
    [
        ("sprites", {"image_size": 63}, ValueError, "image_size=63.*any_image_size=True"),
        ("sprites", {"seed": "abc"}, TypeError, "seed='abc' must be an int"),
        ("highway", {"vehicles_count": "many"}, TypeError, "vehicles_count='many' must be a number"),
        ("sprites", {"num_distractors": "x"}, TypeError, "num_distractors='x' must be a number"),
    ],
    ids=["image_size=63", "seed='abc'", "highway vehicles_count='many'", "sprites num_distractors='x'"],
)
def test_make_env_refuses_bad_arguments_naming_them(name, kwargs, error, message, said):
    """refused: make_env with a bad argument | a ValueError/TypeError naming the argument and its value
    (any_image_size=True allows other sizes)"""
    with pytest.raises(error, match=message) as raised:
        make_env(name, **kwargs)
    said(raised.value)
    assert make_env("sprites", image_size=32, any_image_size=True).reset()["pixels"].shape == (3, 32, 32)


# ---------------------------------------------------------------- the CLI's user errors

CLI_ERRORS = {
    "env.name=carla": (["env.name=carla"], "env.name='carla'.*Unknown env name"),
    "+env.kwargs.bogus=1": (["+env.kwargs.bogus=1"], "unexpected keyword argument 'bogus'"),
    "train.world_model_lr=-1": (["train.world_model_lr=-1"], r"train.world_model_lr=-1.0 must be >= 0"),
    "train.device=cuda": (["train.device=cuda"], "no usable CUDA GPU: set train.device=cpu"),
    "+train.totl_steps=300": (
        ["+train.totl_steps=300"],
        r"train has no setting 'totl_steps' \(did you mean train.total_steps\?\).*: total_steps, prefill_steps",
    ),
    "train.seed=-1": (["train.seed=-1"], r"train.seed=-1 must be in \[0, 2\*\*32 - 1\]"),
    "model.precison=bf16": (
        ["model.precison=bf16"],
        r"model has no setting 'precison' \(did you mean model.precision\?\)",
    ),
    "env=dmc_walker_wlak": (
        ["env=dmc_walker_wlak"],
        r"env group has no config 'dmc_walker_wlak' \(did you mean env=dmc_walker_walk\?\); valid: .*sprites",
    ),
    "size=huge": (
        ["size=huge"],
        "size group has no config 'huge'; valid: bench, paper, quickstart, small, tiny",
    ),
    "algo=isodream_v3": (
        ["algo=isodream_v3"],
        r"algo=isodream_v3 is now algo=isodream \(.*the DreamerV2-style learner is algo=isodream_v2\)",
    ),
    "env.factory with float pixels in [0, 255]": (
        ["env.factory=tests.test_faults:float_pixel_sprites"],
        r"env.factory=.*float 'pixels' must be in \[0, 1\].*got values in \[0, 255\]: divide .* by 255",
    ),
}


def float_pixel_sprites(**kwargs):
    """``env.factory`` of a CLI test: sprites whose pixels are floats in [0, 255]."""
    env = make_env("sprites", **kwargs)
    env.append_transform(DTypeCastTransform(torch.uint8, torch.float32, in_keys=["pixels"]))
    return env


class GoesBad(Transform):
    """Sets ``key`` to ``value`` in every frame from frame ``after + 1`` on (resets count): data going bad mid-run."""

    def __init__(self, key: str, value: float, after: int) -> None:
        super().__init__(in_keys=[])
        self.key, self.value, self.after, self.frames = key, value, after, 0

    def _call(self, next_tensordict):
        self.frames += 1
        if self.frames > self.after and self.key in next_tensordict.keys():
            next_tensordict.set(self.key, torch.full_like(next_tensordict.get(self.key), self.value))
        return next_tensordict

    def _reset(self, tensordict, tensordict_reset):
        return self._call(tensordict_reset)


#: ``<key>:<value>`` in the environment of a command makes :func:`bad_data_sprites` go bad after 80 frames
BAD_ENV_DATA = "ISODREAM_TEST_BAD_ENV_DATA"


def bad_data_sprites(**kwargs):
    """``env.factory`` of a CLI test: sprites with float frames in [0, 1]; with ``$ISODREAM_TEST_BAD_ENV_DATA``
    set to ``<key>:<value>`` (``pixels:nan``), that entry holds the value from frame 81 on; unset, the env is
    fixed."""
    env = make_env("sprites", **kwargs)
    env.append_transform(DTypeCastTransform(torch.uint8, torch.float32, in_keys=["pixels"]))
    env.append_transform(ObservationNorm(loc=0.0, scale=1 / 255, in_keys=["pixels"]))
    if os.environ.get(BAD_ENV_DATA):
        key, _, value = os.environ[BAD_ENV_DATA].partition(":")
        env.append_transform(GoesBad(key, float(value), after=80))
    return env


def command_env(**extra: str) -> dict[str, str]:
    """The environment of the commands the tests run: one thread, this checkout first, one-line errors, and
    ``extra``."""
    environment = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT), **extra)
    environment.pop("HYDRA_FULL_ERROR", None)
    return environment


def run_command(module: str, args: list[str], cwd: Path, **extra_env: str) -> subprocess.CompletedProcess:
    """``python -m <module> *args`` run to its end in ``cwd`` with :func:`command_env` (``extra_env`` added): a
    process of its own, forked from one that paid the imports once (``tests/forked_commands.py``)."""
    return run_module(module, args, cwd, command_env(**extra_env), timeout=600)


@pytest.mark.skipif(torch.cuda.is_available(), reason="train.device=cuda is valid here")
@pytest.mark.parametrize("case", list(CLI_ERRORS), ids=list(CLI_ERRORS))
def test_train_cli_says_a_user_error_in_one_line(case, tmp_path, said):
    """refused: isodream-train with a user error (issue 37 added: a key unknown to the schema with or without +, a
    seed outside numpy's range, a misspelled model override, Hydra's unknown group options, an env.factory's float
    frames in [0, 255]; were silently ignored or tracebacks) | one line on stderr naming the valid names, exit
    status 2, no traceback, no run_config.json"""
    args, message = CLI_ERRORS[case]
    out = run_command("isodream_rl.cli", ["size=tiny", "run_dir=run", *args], tmp_path)
    assert out.returncode == 2, out.stderr[-2000:]
    lines = [line for line in out.stderr.splitlines() if line.startswith("isodream-train:")]
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert re.search(message, lines[0]), lines[0]
    said(lines[0][:200] + ("..." if len(lines[0]) > 200 else ""))
    assert not (tmp_path / "run" / "run_config.json").exists()


def test_train_cli_refuses_a_used_run_dir_before_hydra_writes(finished_run, tmp_path, said):
    """refused: isodream-train into a used run folder, then resume=true with algo=dreamerv2 | one line each
    (naming resume=true and overwrite=true; listing the differing settings), exit 2, the first run's files
    (Hydra's .hydra/ too) untouched; --debug shows the traceback"""
    run_dir = copy_of(finished_run, tmp_path)
    before = snapshot(run_dir)
    out = run_command("isodream_rl.cli", ["size=tiny", "run_dir=run"], tmp_path)
    assert out.returncode == 2 and out.stderr.strip().splitlines()[-1].startswith("isodream-train: run holds")
    said(out.stderr.strip().splitlines()[-1])
    assert "resume=true" in out.stderr and "overwrite=true" in out.stderr and "Traceback" not in out.stderr
    assert snapshot(run_dir) == before
    out = run_command(
        "isodream_rl.cli", ["size=tiny", "run_dir=run", "resume=true", "algo=dreamerv2"], tmp_path
    )
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
    line = out.stderr.strip().splitlines()[-1]
    assert line.startswith("isodream-train: resume=true continues the run in run")
    assert "algo.name: 'isodream_v2' -> 'dreamerv2'" in line
    assert snapshot(run_dir) == before
    debug = run_command("isodream_rl.cli", ["size=tiny", "run_dir=run", "--debug"], tmp_path)
    assert debug.returncode != 0 and "Traceback" in debug.stderr


def test_train_cli_refuses_a_corrupt_run_config_naming_it(tmp_path, said):
    """fault: resume=true on a run whose run_config.json was cut short into invalid JSON (was: Hydra's
    `UserWarning: Callback RunDirGuard.on_run_start raised JSONDecodeError`, and the run trained on past the
    guard) | refused: one line naming the file and saying to delete it and resume (exit 2), the run's files
    (Hydra's .hydra/ too) untouched; with it deleted, resume=true continues from the checkpoints and writes it again"""
    args = [*TINY_TRAIN, "run_dir=run", "train.prefill_steps=20", "train.frames_per_batch=20"]
    out = run_command("isodream_rl.cli", [*args, "train.total_steps=40"], tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    run_dir = tmp_path / "run"
    saved = run_dir / "run_config.json"
    saved.write_bytes(saved.read_bytes()[:100])
    before = snapshot(run_dir)
    out = run_command("isodream_rl.cli", [*args, "train.total_steps=60", "resume=true"], tmp_path)
    assert out.returncode == 2, out.stderr[-3000:]
    line = user_error(out)
    assert line.startswith(
        "isodream-train: run/run_config.json holds no readable run configuration (JSONDecodeError"
    )
    assert "delete it and continue with resume=true" in line and "UserWarning" not in out.stderr
    said(line, limit=400)
    assert snapshot(run_dir) == before
    saved.unlink()
    out = run_command("isodream_rl.cli", [*args, "train.total_steps=60", "resume=true"], tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "resumed from" in out.stdout and "run finished: 60 env steps" in out.stdout
    assert json.loads(saved.read_text())["train"]["total_steps"] == 60


def saved_as(run_dir: Path, algo: str) -> None:
    """Rewrite the ``algo.name`` a run saved (``run_config.json``, every checkpoint's config, its manifest made
    again), as a run of another version of the library would have it."""
    path = run_dir / "run_config.json"
    config = json.loads(path.read_text())
    config["algo"]["name"] = algo
    path.write_text(json.dumps(config, indent=2))
    for folder in CheckpointManager(run_dir / "checkpoints").checkpoints():
        state = torch.load(folder / "state.pt", weights_only=False)
        state["config"]["algo"]["name"] = algo
        torch.save(state, folder / "state.pt")
        write_manifest(folder)


def test_a_checkpoint_of_algo_isodream_before_its_rename_names_algo_isodream_v2(tmp_path, said):
    """fault: resume=true of a run saved by algo=isodream when it was the DreamerV2-style learner (its config
    cannot tell it from one of Iso-Dream on DreamerV3's learner, today's algo=isodream; was: a traceback) |
    refused: one line naming the checkpoint, the rename and algo=isodream_v2 (exit 2), the checkpoints, logs and
    run_config.json untouched; isodream-eval reads it as algo=isodream_v2, and resume=true algo=isodream_v2
    continues it"""
    args = [
        *TINY_TRAIN,
        "run_dir=run",
        "train.prefill_steps=20",
        "train.frames_per_batch=20",
        "env.kwargs.max_steps=20",
    ]
    out = run_command("isodream_rl.cli", [*args, "algo=isodream_v2", "train.total_steps=40"], tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    run_dir = tmp_path / "run"
    saved_as(run_dir, "isodream")
    newest = CheckpointManager(run_dir / "checkpoints").checkpoints()[-1].name
    kept = {name: snapshot(run_dir / name) for name in ("checkpoints", "logs")}
    config = (run_dir / "run_config.json").read_bytes()
    out = run_command("isodream_rl.cli", [*args, "train.total_steps=60", "resume=true"], tmp_path)
    assert out.returncode == 2, out.stderr[-3000:]
    line = user_error(out)
    assert line == (
        f"isodream-train: run/checkpoints/{newest} was saved by algo=isodream before it became Iso-Dream on "
        "DreamerV3's learner: its weights are the DreamerV2-style learner's, now algo=isodream_v2; resume it with "
        "algo=isodream_v2"
    )
    said(line)
    assert {name: snapshot(run_dir / name) for name in kept} == kept
    assert (run_dir / "run_config.json").read_bytes() == config
    mean, _, returns = evaluate_checkpoint(run_dir, episodes=1)
    assert len(returns) == 1 and math.isfinite(mean)
    cfg = config_from_dict(json.loads(config))
    cfg.algo.name, cfg.resume, cfg.train.total_steps, cfg.run_dir = "isodream_v2", True, 60, str(run_dir)
    result = train(cfg)
    assert result.resumed_from is not None and result.resumed_from.name == newest and result.env_steps == 60
    assert json.loads((run_dir / "run_config.json").read_text())["algo"]["name"] == "isodream_v2"


def test_weights_of_other_widths_are_named_in_one_line(tmp_path, said):
    """fault: a checkpoint loaded into models of other widths (model.actor_units; was: a traceback of
    load_state_dict's size mismatches) | refused: one line naming the checkpoint, the model, a few keys with both
    shapes, and that the run's algo and model settings must be the saved ones"""
    cfg = tiny_run(tmp_path / "a")
    state = IsoDreamV2Components(cfg, action_dim=A, scratch_dir=tmp_path / "scratch_a").state(
        cfg, env_steps=0, trainer=None
    )
    narrow = IsoDreamV2Components(
        tiny_run(tmp_path / "b", model__actor_units=8), action_dim=A, scratch_dir=tmp_path / "b"
    )
    with pytest.raises(CheckpointMismatchError) as error:
        narrow.load_models(state, checkpoint="run/checkpoints/step_00000004")
    assert str(error.value) == (
        "run/checkpoints/step_00000004 does not fit the models of algo=isodream_v2 (actor_loss: 9 keys of another "
        "shape (saved -> here: actor.net.0.weight 16x24 -> 8x24, actor.net.0.bias 16 -> 8, actor.net.2.weight "
        "16x16 -> 8x8, ...)): the run's algo and model settings (size, widths, branches) must be the ones it was "
        "saved with, on a version of isodream_rl whose models have these weights"
    )
    said(error.value)


_BROKEN_GUARD = textwrap.dedent(
    """
    import sys
    from isodream_rl import cli
    from isodream_rl.trainers import run_dir

    def broken(*args, **kwargs):
        raise RuntimeError("injected check failure")

    run_dir.run_dir_problem = broken  # the first check of the run-dir guard
    sys.argv = ["isodream-train", *sys.argv[1:]]
    cli.train()
    """
)


def test_run_dir_guard_fails_closed_whatever_a_check_raises(tmp_path, said):
    """fault: a check of isodream-train's run-dir guard raising an unexpected error (was: Hydra turns an exception
    in a callback into a warning, so the run went past the guard) | refused: one line naming run_dir and the
    error (exit 2), nothing written; with --debug the traceback, then the same line and exit status"""
    for debug in ([], ["--debug"]):  # python -c _BROKEN_GUARD ..., forked as run_command's commands
        out = run_module(
            None,
            [*TINY_TRAIN, "run_dir=run", *debug],
            tmp_path,
            command_env(),
            code=_BROKEN_GUARD,
            timeout=600,
        )
        assert out.returncode == 2, out.stderr[-3000:]
        line = out.stderr.strip().splitlines()[-1]
        assert line == (
            "isodream-train: checking run_dir run failed (RuntimeError: injected check failure); nothing was "
            "started: --debug shows the traceback"
        )
        assert ("Traceback" in out.stderr) == bool(debug) and "UserWarning" not in out.stderr
        assert not (tmp_path / "run").exists()
    said(line)


@pytest.mark.parametrize(
    "module, args, message",
    [
        (
            "isodream_rl.video_prediction.cli",
            ["eval", "--checkpoint", "missing.pt"],
            "isodream-video: --checkpoint",
        ),
        (
            "isodream_rl.video_prediction.cli",
            ["train", "--dataset", "bair", "--data-path", "missing"],
            "isodream-video: data_path='missing': no such folder",
        ),
        ("isodream_rl.cli", ["eval", "missing"], "isodream-eval: no checkpoint in missing"),
    ],
    ids=["isodream-video eval --checkpoint", "isodream-video train --data-path", "isodream-eval RUN_DIR"],
)
def test_eval_and_video_cli_say_a_missing_path_in_one_line(module, args, message, tmp_path, said):
    """refused: a missing path | one line naming the path, exit status 2"""
    out = run_command(module, args, tmp_path)
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [out.stderr.strip()], out.stderr[-2000:]
    assert out.stderr.startswith(message)
    said(out.stderr.strip())


def test_every_dmc_task_has_an_env_preset():
    """refused: env=dmc_<domain>_<task> beyond the 4 DMC presets (was a Hydra error) | every dm_control suite
    task composes (presets stored in Hydra's ConfigStore)"""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import isodream_rl.cli
    from isodream_rl.envs.builder import dmc_env_names

    configs = Path(isodream_rl.cli.__file__).parent / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        for name in dmc_env_names():
            cfg = OmegaConf.to_object(compose(config_name="config", overrides=[f"env={name}", "size=tiny"]))
            assert cfg.env.name == name and cfg.algo.policy_input == "controllable"
