"""What every mode of ``isodream-train`` does at the start and the end of a run, and what a run returns.

``mode=rl`` (:mod:`isodream_rl.trainers.run`) and ``mode=world_model`` (:mod:`isodream_rl.trainers.world_model_run`)
both begin with :func:`begin_run` (config check, threads, seeds), read the env's action width with
:func:`probe_action_dim`, continue a resumed run from :func:`resume_state` and :func:`restore_run_state`, train
in a TorchRL ``Trainer`` with :func:`train_with_checkpoints` (checkpoints of the one layout
:func:`run_state`), write ``summary.json`` with :func:`write_summary` and return a :class:`RunResult`.
"""

from __future__ import annotations

import dataclasses
import random
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torchrl.trainers import Trainer

from isodream_rl.modules.pixels import check_pixel_values, check_pixels
from isodream_rl.run_utils.checkpoint import CheckpointManager, rng_state, set_rng_state
from isodream_rl.run_utils.csv_logs import csv_log_sizes, cut_csv_logs
from isodream_rl.run_utils.json_io import write_json
from isodream_rl.run_utils.signals import StopOnSignal
from isodream_rl.trainers.builders import env_factory
from isodream_rl.trainers.config import ConfigError, RunConfig
from isodream_rl.trainers.hooks import PeriodicCheckpoint
from isodream_rl.trainers.learners import resolved
from isodream_rl.trainers.run_dir import check_same_run
from isodream_rl.trainers.saved_models import CheckpointMismatchError
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper
from isodream_rl.user_errors import one_line

#: what ``state.pt`` of a checkpoint of either mode holds (:func:`run_state`)
STATE_KEYS = ("config", "models", "stepper", "counters", "hooks", "rng")


@dataclass
class RunResult:
    """What a finished (or stopped) run produced."""

    run_dir: Path
    checkpoint: Path | None
    logs: Path
    pictures: Path
    env_steps: int
    updates: int
    resumed_from: Path | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    summary: dict | None = None
    """The final evaluation next to the reference policies (``<run_dir>/summary.json``), if it ran."""
    stopped_by_signal: int | None = None
    """The signal (SIGINT, SIGTERM) that stopped the run after its ``checkpoint``, or ``None`` when it ran to its
    end."""


def seed_everything(seed: int) -> None:
    """Seed torch, numpy and python."""
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


def probe_action_dim(cfg: RunConfig) -> int:
    """The width of the action of ``cfg``'s env (built once and closed). An ``env.factory`` env is reset once
    too, and its first frame checked as the world model will check it.

    Raises:
        ConfigError: the env cannot be built from ``env.name`` and ``env.kwargs``, or the frames of an
            ``env.factory`` env are not ``[3, 64, 64]`` uint8 or floats in ``[0, 1]`` (the message says why).
    """
    try:
        env = env_factory(cfg)()
    except (TypeError, ValueError, KeyError, ImportError) as err:
        raise ConfigError(
            f"invalid training configuration: env.name={cfg.env.name!r} with env.kwargs={dict(cfg.env.kwargs)} "
            f"cannot be built: {err}"
        ) from err
    try:
        if cfg.env.factory:
            pixels = env.reset().get("pixels", None)
            try:
                if pixels is None:
                    raise KeyError("its env returns no 'pixels'")
                check_pixels(pixels, name="'pixels'")
                check_pixel_values(pixels, name="'pixels'")
            except (TypeError, ValueError, KeyError) as err:
                message = err.args[0] if isinstance(err, KeyError) else err
                raise ConfigError(
                    f"invalid training configuration: env.factory={cfg.env.factory!r}: {message}"
                ) from err
        return int(env.action_spec.shape[-1])
    finally:
        env.close()


def begin_run(cfg: RunConfig) -> tuple[float, Path, Path, Path]:
    """What every mode does first, in the run folder that :func:`~isodream_rl.trainers.run.train` holds (see
    :func:`~isodream_rl.trainers.run_dir.hold_run_dir`, after checking the config): set threads and seeds.
    ``run_config.json`` is written later (:func:`~isodream_rl.trainers.run_dir.write_run_config`), once the run's
    parts are built and a resumed run's checkpoint is found to match the config.

    Returns:
        ``(start time from time.perf_counter, run_dir, pictures folder, logs folder)``.
    """
    started = time.perf_counter()
    run_dir = Path(cfg.run_dir)
    torch.set_num_threads(cfg.train.threads)
    seed_everything(cfg.train.seed)
    return started, run_dir, run_dir / "pictures", run_dir / "logs"


def resume_state(cfg: RunConfig, checkpoints: CheckpointManager, *, required_keys) -> tuple[dict, Path]:
    """The newest readable checkpoint of a resumed run, once its configuration is found to match ``cfg``.

    Raises:
        CheckpointError: no readable checkpoint.
        ConfigError: the checkpoint's run had settings that change the models or the data (listed).
    """
    state, path = checkpoints.load_latest(required_keys=required_keys)
    check_same_run(state["config"], cfg)
    return state, path


def write_summary(run_dir: str | Path, summary: dict) -> Path:
    """Write ``<run_dir>/summary.json`` atomically (temporary file, then rename), as strict JSON: an absent score
    (``nan``, such as ``mse_distractors`` without distractors) is ``null``
    (:func:`~isodream_rl.run_utils.json_io.write_json`); the path written."""
    return write_json(Path(run_dir) / "summary.json", summary, indent=2, atomic=True)


def run_state(
    cfg: RunConfig,
    *,
    models: Mapping[str, nn.Module],
    stepper: IsoDreamOptimizationStepper,
    counters: dict,
    hooks: dict,
    logs: Path | None = None,
) -> dict:
    """What ``state.pt`` of a checkpoint of either mode holds (:data:`STATE_KEYS`): the config (with the values its
    learner reads, :func:`~isodream_rl.trainers.learners.resolved`), the state of
    each of ``models``, the stepper's (optimisers and update counts), ``counters``, the state of the ``hooks``
    that have one, the RNG states and, with ``logs``, the size of each CSV log (what a resume cuts them back
    to, :func:`restore_run_state`)."""
    if logs is not None:
        counters = {**counters, "log_sizes": csv_log_sizes(logs)}
    return {
        "config": dataclasses.asdict(resolved(cfg)),
        "models": {name: module.state_dict() for name, module in models.items()},
        "stepper": stepper.state_dict(),
        "counters": counters,
        "hooks": hooks,
        "rng": rng_state(),
    }


def restore_run_state(
    state: dict,
    *,
    checkpoint: Path,
    load_models: Callable[[dict], None],
    stepper: IsoDreamOptimizationStepper,
    logs: Path,
) -> None:
    """Continue from a checkpoint's :func:`run_state`: the models (``load_models(state)``), the stepper, the
    RNG states, and the CSV logs cut back to what they held then (rows written after it are of a timeline that
    ended).

    Args:
        state: the state of the checkpoint ``checkpoint`` (its folder, named by the errors).
        load_models: loads ``state["models"]`` into the run's models (raising
            :class:`~isodream_rl.trainers.saved_models.CheckpointMismatchError` where they do not fit, as
            :func:`~isodream_rl.trainers.saved_models.load_saved_models` does).
        stepper: the run's stepper.
        logs: the run's CSV logs folder.

    Raises:
        CheckpointMismatchError: the weights (``load_models``) or the optimiser state do not fit the run's.
    """
    load_models(state)
    try:
        stepper.load_state_dict(state["stepper"])
    except (KeyError, ValueError) as err:  # torch's optimiser loading: another parameter layout
        raise CheckpointMismatchError(
            f"{checkpoint}'s optimiser state does not fit the run's optimisers ({type(err).__name__}: "
            f"{one_line(err)}): the run's algo and model settings must be the ones it was saved with"
        ) from err
    set_rng_state(state["rng"])
    if "log_sizes" in state["counters"]:
        cut_csv_logs(logs, state["counters"]["log_sizes"])


def train_with_checkpoints(
    trainer: Trainer, *, save: Callable[[], Path], stepper: IsoDreamOptimizationStepper, every_updates: int
) -> int | None:
    """The training loop of both modes: ``trainer.train()`` with a checkpoint every ``every_updates`` updates
    (:class:`~isodream_rl.trainers.hooks.PeriodicCheckpoint`, registered after the run's other hooks) and a
    last one when it ends; SIGINT/SIGTERM save a checkpoint and stop at the end of the batch
    (:class:`~isodream_rl.run_utils.signals.StopOnSignal`).

    Returns:
        the signal that stopped the run, or ``None`` if it ran to its end (or a hook stopped it).
    """
    with StopOnSignal() as signals:
        PeriodicCheckpoint(save=save, stepper=stepper, every_updates=every_updates, signals=signals).register(
            trainer
        )
        try:
            trainer.train()
        finally:
            trainer.collector.shutdown()
        if signals.received is None:
            save()
    return signals.received
