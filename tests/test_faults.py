"""Fault injection: every fault of issue 27 reproduced, each ending in a clear error or a documented recovery.

Faults (``fault``): a second run in a used run folder, a truncated replay memmap, a ``state.pt`` without its keys,
a corrupted byte, a resume with another algorithm, SIGKILL and a full disk while a checkpoint is written, a
corrupted CSV log, an env raising mid-episode in a parallel collector, NaN losses. Bad inputs (``refused``):
pixels in the wrong range or NaN, NaN actions, no ``is_init``, 1-step windows, image sizes, argument types, and
the CLI's user errors. Where a checkpoint survives, it is the last verified one and continuing from it gives the
very losses the run gave after it (``continued``). ``bench/reliability_table.py`` runs this file and writes
``docs/results/reliability.md`` from its report; each test's docstring is its row.
"""

import copy
import dataclasses
import errno
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDict

from isodream_rl.envs import make_env
from isodream_rl.modules import IsoDreamWorldModel, WorldModelConfig
from isodream_rl.objectives import IsoDreamModelLoss
from isodream_rl.trainers import (
    CheckpointError,
    CheckpointManager,
    ConfigError,
    NonFiniteLossError,
    RunComponents,
    RunConfig,
    train,
)
from isodream_rl.trainers import checkpoint as checkpoint_module
from isodream_rl.trainers.checkpoint import set_rng_state, write_manifest
from isodream_rl.trainers.hooks import ReplayPreparation
from tests.conftest import tiny_run_config

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
    """``said(text)``: what the library said, recorded in the JUnit report (``bench/reliability_table.py``
    shows it); ``tmp_path`` prefixes are cut."""

    def record(text: str) -> None:
        text = " ".join(str(text).split())
        text = re.sub(r"/tmp/\S*?/(?=run\b|checkpoints\b|lineage\b)", "", text)
        record_property("said", text[:300])

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

    def components(self, scratch: Path) -> RunComponents:
        return RunComponents(self.cfg, action_dim=A, scratch_dir=scratch)

    def state(self, components: RunComponents) -> dict:
        return components.state(self.cfg, env_steps=0, trainer=None)

    @staticmethod
    def update(components: RunComponents) -> float:
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
        ConfigError, match=r"algo.free_branch: True -> False.*algo.name: 'isodream' -> 'dreamerv2'"
    ) as error:
        train(cfg)
    said(error.value)
    assert snapshot(run_dir) == before


def test_resume_with_a_corrupted_csv_log_continues(finished_run, tmp_path):
    """fault: a CSV log file corrupted (binary junk, a cut line) | recovered: the resumed run appends its rows
    after it; the checkpoints, not the logs, hold the run's state"""
    run_dir = copy_of(finished_run, tmp_path)
    log = next((run_dir / "logs").rglob("loss_model_reco.csv"))
    log.write_bytes(log.read_bytes()[:-7] + b"\x00\xff garbage,\n12,")
    size = log.stat().st_size
    result = train(tiny_run(run_dir, resume=True, train__total_steps=40))
    assert result.env_steps == 40 and result.resumed_from is not None
    assert log.stat().st_size > size


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
    return IsoDreamModelLoss(IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=A)))


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
    """refused: IsoDreamModelLoss (through the world model) on a bad batch | a ValueError naming what is
    wrong and the fix (the range [0, 1] and how to get there for pixels)"""
    entries, message = BAD_INPUTS[case]
    with pytest.raises(ValueError, match=message) as error:
        model_loss(model_batch(entries))
    said(error.value)


def test_one_step_window_is_refused_and_checks_can_be_skipped(model_loss, said):
    """refused: IsoDreamModelLoss on a window of T=1 (was an internal tensordict error) | a ValueError asking
    for 2 steps or more; IsoDreamWorldModel(check_inputs=False) skips the value checks"""
    with pytest.raises(ValueError, match="at least 2 steps.*got T=1") as error:
        model_loss(model_batch(time=1))
    said(error.value)
    unchecked = IsoDreamModelLoss(
        IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=A), check_inputs=False)
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
}


def run_command(module: str, args: list[str], cwd: Path, **env) -> subprocess.CompletedProcess:
    environment = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT), **env)
    environment.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=environment,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.skipif(torch.cuda.is_available(), reason="train.device=cuda is valid here")
@pytest.mark.parametrize("case", list(CLI_ERRORS), ids=list(CLI_ERRORS))
def test_train_cli_says_a_user_error_in_one_line(case, tmp_path, said):
    """refused: isodream-train with a user error | one line on stderr, exit status 2, no traceback, no
    run_config.json"""
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
    assert "algo.name: 'isodream' -> 'dreamerv2'" in line
    assert snapshot(run_dir) == before
    debug = run_command("isodream_rl.cli", ["size=tiny", "run_dir=run", "--debug"], tmp_path)
    assert debug.returncode != 0 and "Traceback" in debug.stderr


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
