"""Checkpoints: atomic rotation, fallback past a corrupted newest one, SIGKILL + resume, SIGTERM save."""

import logging
import signal
import time

import pytest
import torch

from isodream_rl.trainers import CheckpointError, CheckpointManager
from tests.conftest import cli_process, cli_run

RUN = [
    "size=tiny",
    "train.threads=1",
    "logging.progress_bar=false",
    "train.prefill_steps=20",
    "train.frames_per_batch=20",
    "checkpoint.every_updates=4",
    "run_dir=run",
]


class TestCheckpointManager:
    def test_keeps_the_newest_and_ignores_unfinished_writes(self, tmp_path):
        manager = CheckpointManager(tmp_path, keep=2)
        for step in (1, 2, 3):
            manager.save(step, {"step": step})
        (tmp_path / "step_00000009.tmp").mkdir()  # a write that crashed before its rename
        assert [p.name for p in manager.checkpoints()] == ["step_00000002", "step_00000003"]
        assert manager.load_latest()[0]["step"] == 3

    def test_corrupted_newest_falls_back_to_the_previous_with_a_warning(self, tmp_path, caplog):
        manager = CheckpointManager(tmp_path, keep=2)
        manager.save(1, {"step": 1})
        newest = manager.save(2, {"step": 2})
        (newest / "state.pt").write_bytes(b"not a checkpoint")
        with caplog.at_level(logging.WARNING):
            state, path = manager.load_latest()
        assert state["step"] == 1 and path.name == "step_00000001"
        assert "step_00000002" in caplog.text and "falling back to the previous one" in caplog.text

    def test_no_readable_checkpoint_is_a_clear_error(self, tmp_path):
        manager = CheckpointManager(tmp_path, keep=2)
        with pytest.raises(CheckpointError, match="no checkpoint in"):
            manager.load_latest()
        (manager.save(1, {"step": 1}) / "state.pt").write_bytes(b"")
        with pytest.raises(CheckpointError, match="no readable checkpoint"):
            manager.load_latest()

    def test_keep_below_two_is_rejected(self, tmp_path):
        with pytest.raises(ValueError, match="keep must be >= 2"):
            CheckpointManager(tmp_path, keep=1)


def _wait_for_checkpoints(directory, count, proc, timeout=240):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = sorted(directory.glob("step_*[0-9]")) if directory.exists() else []
        if len(found) >= count:
            return found
        if proc.poll() is not None:
            raise AssertionError(f"the run ended early: {proc.communicate()[1][-3000:]}")
        time.sleep(0.5)
    raise AssertionError("no checkpoint in time")


def _counters(path):
    state = torch.load(path / "state.pt", weights_only=False)
    return state["counters"]["env_steps"], state["stepper"]["updates"]


def test_sigkill_then_resume_continues_from_the_last_readable_checkpoint(tmp_path):
    proc = cli_process([*RUN, "train.total_steps=100000"], tmp_path)
    try:
        found = _wait_for_checkpoints(tmp_path / "run" / "checkpoints", 2, proc)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
    newest, previous = found[-1], found[-2]
    (newest / "state.pt").write_bytes(b"\0" * 64)  # corrupt the newest: resume must use the previous one
    env_steps, updates = _counters(previous)
    assert updates > 0

    # no final evaluation: its 10 episodes and the references are no part of the resume
    out = cli_run(
        [*RUN, f"train.total_steps={env_steps + 40}", "resume=true", "logging.final_eval_episodes=0"],
        tmp_path,
        timeout=300,
    )
    stdout, stderr = out.stdout, out.stderr
    assert out.returncode == 0, stderr[-3000:]
    assert "falling back to the previous one" in stderr
    assert f"resumed from run/checkpoints/{previous.name}" in stdout
    # 40 more steps, prefill done: two batches of 20 steps, 4 updates each.
    assert f"run finished: {env_steps + 40} env steps, {updates + 8} updates" in stdout


def test_sigterm_saves_a_checkpoint_and_stops_cleanly(tmp_path):
    proc = cli_process([*RUN, "train.total_steps=100000"], tmp_path)
    try:
        _wait_for_checkpoints(tmp_path / "run" / "checkpoints", 1, proc)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, stderr[-3000:]  # a stopped run is no finished one
    assert "SIGTERM received" in stderr
    newest = sorted((tmp_path / "run" / "checkpoints").glob("step_*[0-9]"))[-1]
    env_steps, _ = _counters(newest)
    assert stderr.strip().splitlines()[-1] == (
        f"isodream-train: stopped at {env_steps} env steps by SIGTERM (checkpoint run/checkpoints/{newest.name}); "
        "continue with resume=true"
    )
    assert "run finished" not in stdout
