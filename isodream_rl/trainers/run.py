"""Algorithm 1 as a TorchRL ``Trainer``: assemble a run from a :class:`RunConfig`, train, resume, evaluate."""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import random
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torchrl.trainers import ReplayBufferTrainer, Trainer, UpdateWeights

from isodream_rl.csv_logs import csv_log_sizes, cut_csv_logs
from isodream_rl.envs.builder import ground_truth_mask_keys
from isodream_rl.modules.encoder import check_pixel_values, check_pixels
from isodream_rl.trainers import trainer_state
from isodream_rl.trainers.builders import (
    close_logger,
    env_factory,
    make_adam,
    make_behavior,
    make_logger,
    make_replay_buffer,
    make_world_model_loss,
)
from isodream_rl.trainers.checkpoint import CheckpointError, CheckpointManager, rng_state, set_rng_state
from isodream_rl.trainers.collectors import make_collector
from isodream_rl.trainers.config import ConfigError, RunConfig, config_from_dict, validate_config
from isodream_rl.trainers.disk_space import ReplayReservation
from isodream_rl.trainers.evaluation import Evaluation, learning_summary, run_episodes, save_episode_gif
from isodream_rl.trainers.hooks import (
    EpisodeReturns,
    PeriodicCheckpoint,
    ReplayPreparation,
    StopOnSignal,
    Throughput,
)
from isodream_rl.trainers.run_dir import check_same_run, hold_run_dir, resuming, write_run_config
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper
from isodream_rl.trainers.world_model_config import TORCHRL_BASELINES

logger = logging.getLogger(__name__)

#: what ``state.pt`` of an RL run's checkpoint holds (a checkpoint without one of them is unreadable)
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


class RunComponents:
    """Models, losses, optimisers, stepper and replay buffer of a run (everything a checkpoint holds).

    Args:
        cfg: the run configuration.
        action_dim: width of the env's action.
        scratch_dir: folder of the replay buffer's memmap files.

    Attributes:
        model_loss, world_model, behavior (:class:`~isodream_rl.trainers.builders.Behavior`), stepper
        (:class:`IsoDreamOptimizationStepper`), replay_buffer, preparation, returns (the replay and
        episode-return hooks).
    """

    def __init__(self, cfg: RunConfig, *, action_dim: int, scratch_dir: Path) -> None:
        train = cfg.train
        self.model_loss = make_world_model_loss(cfg, action_dim=action_dim)
        self.world_model = self.model_loss.world_model
        self.behavior = make_behavior(cfg, self.world_model)
        groups = self.behavior.actor_loss.parameter_groups()
        self.stepper = IsoDreamOptimizationStepper(
            model_loss=self.model_loss,
            world_model_optimizer=make_adam(
                groups["world_model"], lr=train.world_model_lr, eps=train.adam_eps
            ),
            actor_loss=self.behavior.actor_loss,
            value_loss=self.behavior.value_loss,
            actor_optimizer=make_adam(groups["actor"], lr=train.actor_lr, eps=train.adam_eps),
            value_optimizer=make_adam(groups["value"], lr=train.value_lr, eps=train.adam_eps),
            target_updater=self.behavior.target_updater,
            sequence_length=train.sequence_length,
            grad_clip=train.grad_clip,
            max_nonfinite=train.max_nonfinite_updates,
            world_model_warmup=train.world_model_warmup,
        )
        self.replay_buffer = make_replay_buffer(cfg, scratch_dir=scratch_dir)
        self.preparation = ReplayPreparation(
            num_envs=cfg.env.num_envs, capacity_per_env=train.buffer_size // cfg.env.num_envs
        )
        self.returns = EpisodeReturns()

    def modules(self) -> dict[str, torch.nn.Module]:
        return {
            "world_model": self.world_model,
            "actor_loss": self.behavior.actor_loss,
            "value_loss": self.behavior.value_loss,
        }

    def state(
        self, cfg: RunConfig, *, env_steps: int, trainer: Trainer | None, evaluation=None, wall_s: float = 0.0
    ) -> dict:
        return {
            "config": dataclasses.asdict(cfg),
            "models": {name: module.state_dict() for name, module in self.modules().items()},
            "stepper": self.stepper.state_dict(),
            "counters": {
                "env_steps": env_steps,
                "wall_s": wall_s,
                "optim_count": trainer_state.optim_count(trainer) if trainer is not None else 0,
                "last_log": trainer_state.log_marks(trainer) if trainer is not None else {},
            },
            "hooks": {
                "preparation": self.preparation.state_dict(),
                "returns": self.returns.state_dict(),
                "evaluation": evaluation.state_dict() if evaluation is not None else None,
            },
            "rng": rng_state(),
        }

    def load_models(self, state: dict) -> None:
        for name, module in self.modules().items():
            module.load_state_dict(state["models"][name])


def begin_run(cfg: RunConfig) -> tuple[float, Path, Path, Path]:
    """What every mode does first, in the run folder that :func:`train` holds (see
    :func:`~isodream_rl.trainers.run_dir.hold_run_dir`): check the config, set threads and seeds.
    ``run_config.json`` is written later (:func:`~isodream_rl.trainers.run_dir.write_run_config`), once the run's
    parts are built and a resumed run's checkpoint is found to match the config.

    Returns:
        ``(start time from time.perf_counter, run_dir, pictures folder, logs folder)``.

    Raises:
        ConfigError: an invalid configuration.
    """
    validate_config(cfg)
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


def make_components(cfg: RunConfig, *, action_dim: int, scratch_dir: Path):
    """The run's components for ``cfg.algo.name``: :class:`RunComponents` (Iso-Dream, its ablations and the
    DreamerV2 baseline), or, for ``torchrl_dreamer`` and ``torchrl_dreamer_v3``, TorchRL's own Dreamer and
    DreamerV3 pieces with the same interface (``isodream_rl.baselines``)."""
    if cfg.algo.name == "torchrl_dreamer":
        from isodream_rl.baselines.torchrl_dreamer import TorchRLDreamerComponents

        return TorchRLDreamerComponents(cfg, action_dim=action_dim, scratch_dir=scratch_dir)
    if cfg.algo.name == "torchrl_dreamer_v3":
        from isodream_rl.baselines.torchrl_dreamer_v3 import TorchRLDreamerV3Components

        return TorchRLDreamerV3Components(cfg, action_dim=action_dim, scratch_dir=scratch_dir)
    return RunComponents(cfg, action_dim=action_dim, scratch_dir=scratch_dir)


def train(cfg: RunConfig) -> RunResult:
    """Train (or resume) a run described by ``cfg``; see ``docs/recipes`` for the recipes.

    Steps: check the config; build env probe, world model + loss, behavior (actor, value, attention,
    acting policy), three Adam optimisers in an :class:`IsoDreamOptimizationStepper`, a
    ``TensorDictReplayBuffer(LazyMemmapStorage, SliceSampler)``, a TorchRL ``Collector`` (random prefill, then
    the policy) and a TorchRL ``Trainer`` with hooks for replay, logging, evaluation and checkpoints; with
    ``resume``, restore the newest readable checkpoint; train until ``train.total_steps`` or a signal.

    The run folder is held by this process while it trains (:func:`~isodream_rl.trainers.run_dir.hold_run_dir`);
    a resumed run cuts its CSV logs back to what they held at its checkpoint (:mod:`isodream_rl.csv_logs`).

    Raises:
        ConfigError: invalid configuration (before anything is built), a run folder that holds another run or
            cannot be written.
        RunDirBusyError: another live process uses the run folder.
        CheckpointError: ``resume`` without a readable checkpoint.
        DiskFullError: the disk filled up (the message names the checkpoint to resume from).
        NonFiniteLossError: too many NaN/inf updates in a row.
    """
    validate_config(cfg)
    with hold_run_dir(cfg):
        if cfg.mode == "world_model":
            # the world model alone: its own loop, this run folder and checkpoint format (imported here, as it
            # builds on this module)
            from isodream_rl.trainers import world_model_run

            return world_model_run.train(cfg)
        return _train_rl(cfg)


def _train_rl(cfg: RunConfig) -> RunResult:
    """:func:`train` in ``mode=rl``, in the run folder it holds."""
    started, run_dir, pictures, logs = begin_run(cfg)
    train_cfg = cfg.train
    checkpoints = CheckpointManager(run_dir / "checkpoints", keep=cfg.checkpoint.keep)
    resumed_from, state = None, None
    if resuming(cfg):
        state, resumed_from = resume_state(cfg, checkpoints, required_keys=STATE_KEYS)
    action_dim = probe_action_dim(cfg)

    scratch = run_dir / "replay_scratch"
    # The memmap files of an earlier process of this run (killed, or finished) are stale: the replay data
    # that matters is in the checkpoints.
    shutil.rmtree(scratch, ignore_errors=True)
    components = make_components(cfg, action_dim=action_dim, scratch_dir=scratch)
    stepper, policy = components.stepper, components.behavior.policy
    if state is not None:
        checkpoints.load_replay(resumed_from, components.replay_buffer)
        components.load_models(state)
        stepper.load_state_dict(state["stepper"])
        components.preparation.load_state_dict(state["hooks"]["preparation"])
        components.returns.load_state_dict(state["hooks"]["returns"])
        set_rng_state(state["rng"])
        if "log_sizes" in state["counters"]:  # rows written after the checkpoint are of a timeline that ended
            cut_csv_logs(logs, state["counters"]["log_sizes"])
        logger.info("resumed from %s (%d env steps)", resumed_from, state["counters"]["env_steps"])
    write_run_config(cfg)  # the run starts: its parts are built, the config matches its checkpoint
    env_steps = state["counters"]["env_steps"] if state else 0
    wall_before = state["counters"].get("wall_s", 0.0) if state else 0.0

    def wall_s() -> float:
        return wall_before + time.perf_counter() - started

    if env_steps >= train_cfg.total_steps:
        return RunResult(run_dir, resumed_from, logs, pictures, env_steps, stepper.updates, resumed_from)

    collector = make_collector(
        cfg,
        policy,
        total_frames=train_cfg.total_steps - env_steps,
        init_random_frames=max(0, train_cfg.prefill_steps - env_steps),
        env_transform=policy.make_tensordict_primer,
    )
    log = make_logger(cfg, run_dir=run_dir)
    trainer = Trainer(
        collector=collector,
        total_frames=train_cfg.total_steps,
        frame_skip=1,
        optim_steps_per_batch=train_cfg.frames_per_batch // train_cfg.train_every,
        loss_module=components.model_loss,
        optimization_stepper=stepper,
        logger=log,
        progress_bar=cfg.logging.progress_bar,
        log_interval=cfg.logging.log_every,
        save_trainer_file=None,
    )
    trainer.collected_frames = env_steps
    if state is not None:
        counters = state["counters"]
        trainer_state.restore(trainer, optim_count=counters["optim_count"], log_marks=counters["last_log"])
        # The collector restarts its prefill count at 0; the Trainer compares against the remaining prefill.
        collector.init_random_frames = max(0, train_cfg.prefill_steps - env_steps)

    components.preparation.register(trainer)
    # ReplayBufferTrainer.register would also add a priority hook on the legacy post_loss stage, which the
    # stepper path never runs: register its two useful ops directly.
    replay_hook = ReplayBufferTrainer(components.replay_buffer, flatten_tensordicts=False)
    storage = getattr(components.replay_buffer, "storage", None)
    if getattr(storage, "scratch_dir", None):
        ReplayReservation(storage).register(trainer, replay_hook.extend)
    else:
        trainer.register_op("batch_process", replay_hook.extend)
    trainer.register_op("process_optim_batch", replay_hook.sample)
    components.returns.register(trainer)
    Throughput(stepper).register(trainer)
    if cfg.env.num_envs > 1 or train_cfg.collector_backend != "sync":
        UpdateWeights(collector, update_weights_interval=1).register(trainer)

    # the decomposition scores of the evaluations, where the env renders the ground truth and the world model
    # is Iso-Dream's (any of its variants)
    decomposition = (
        cfg.algo.name not in TORCHRL_BASELINES
        and not cfg.env.factory
        and bool(ground_truth_mask_keys(cfg.env.name))
    )

    def eval_env(masks: bool = False):
        make = env_factory(cfg, eval_mode=True)
        env = (functools.partial(make, return_masks=True) if masks else make)()
        env.append_transform(policy.make_tensordict_primer())
        return env

    evaluation = None
    if cfg.logging.eval_every > 0:
        evaluation = Evaluation(
            policy=policy,
            env_factory=functools.partial(eval_env, masks=decomposition),
            world_model=components.world_model,
            replay_buffer=components.replay_buffer,
            sequence_length=train_cfg.sequence_length,
            pictures=pictures,
            every=cfg.logging.eval_every,
            episodes=cfg.logging.eval_episodes,
            task=cfg.env.name,
            clock=wall_s,
            context=cfg.logging.video_context,
            length=cfg.logging.video_length,
            # The CSV logger can only write videos as MP4 through torchcodec (not a dependency); the GIF suffices.
            logger=None if cfg.logging.backend == "csv" else log,
            decomposition=decomposition,
        )
        if state is not None and state["hooks"]["evaluation"] is not None:
            evaluation.load_state_dict(state["hooks"]["evaluation"])
        evaluation.register(trainer)
    if cfg.logging.progress_bar and env_steps:
        trainer.register_op("setup", lambda: trainer_state.advance_progress_bar(trainer, env_steps))

    last_checkpoint: list[Path | None] = [resumed_from]

    def save() -> Path:
        saved = components.state(
            cfg, env_steps=trainer.collected_frames, trainer=trainer, evaluation=evaluation, wall_s=wall_s()
        )
        saved["counters"]["log_sizes"] = csv_log_sizes(logs)  # what a resume cuts the logs back to
        path = checkpoints.save(
            stepper.updates, saved, replay_buffer=components.replay_buffer if cfg.checkpoint.replay else None
        )
        last_checkpoint[0] = path
        return path

    with StopOnSignal() as signals:
        PeriodicCheckpoint(
            save=save, stepper=stepper, every_updates=cfg.checkpoint.every_updates, signals=signals
        ).register(trainer)
        try:
            trainer.train()
        finally:
            collector.shutdown()
        if signals.received is None:
            save()
    train_wall_s = wall_s()
    summary = None
    if signals.received is None and cfg.logging.final_eval_episodes > 0:
        summary = final_evaluation(
            cfg,
            policy,
            env_factory=eval_env,
            env_steps=trainer.collected_frames,
            wall_s=train_wall_s,
            run_dir=run_dir,
        )
        for key, value in summary.items():
            if isinstance(value, (int, float)):
                log.log_scalar(f"final/{key}", value, step=trainer.collected_frames)
    close_logger(log)
    metrics = {
        key: float(values[-1])
        for key, values in trainer_state.logged_values(trainer).items()
        if values and _is_scalar(values[-1])
    }
    return RunResult(
        run_dir=run_dir,
        checkpoint=last_checkpoint[0],
        logs=logs,
        pictures=pictures,
        env_steps=trainer.collected_frames,
        updates=stepper.updates,
        resumed_from=resumed_from,
        metrics=metrics,
        summary=summary,
    )


def final_evaluation(
    cfg: RunConfig, policy, *, env_factory, env_steps: int, wall_s: float, run_dir: Path
) -> dict:
    """Evaluate the trained policy (``logging.final_eval_episodes`` mode-action episodes) next to the task's
    reference policies and write ``<run_dir>/summary.json`` (see :func:`learning_summary`)."""
    env = env_factory()
    env.set_seed(cfg.train.seed + 1)
    try:
        results = run_episodes(policy, env, episodes=cfg.logging.final_eval_episodes, task=cfg.env.name)
    finally:
        env.close()
    summary = learning_summary(
        results, env_name=cfg.env.name, env_kwargs=dict(cfg.env.kwargs), env_steps=env_steps, wall_s=wall_s
    )
    summary.update(updates_per_env_step=1.0 / cfg.train.train_every, algo=cfg.algo.name, seed=cfg.train.seed)
    write_summary(run_dir, summary)
    return summary


def write_summary(run_dir: str | Path, summary: dict) -> Path:
    """Write ``<run_dir>/summary.json`` atomically (temporary file, then rename); the path written."""
    path = Path(run_dir) / "summary.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(path)
    return path


def _is_scalar(value) -> bool:
    return isinstance(value, (int, float)) or (isinstance(value, torch.Tensor) and value.numel() == 1)


def evaluate_checkpoint(
    run_dir: str | Path, *, episodes: int = 5, video: str | Path | None = None, seed: int = 0
) -> tuple[float, float, list[float]]:
    """Load the newest readable checkpoint of ``run_dir`` and run ``episodes`` mode-action episodes.

    Returns:
        ``(mean, std, returns)``; with ``video``, the first episode is written there as a GIF.
    """
    checkpoints = CheckpointManager(Path(run_dir) / "checkpoints", keep=2)
    if not checkpoints.checkpoints():
        raise CheckpointError(
            f"no checkpoint in {checkpoints.directory}: give the run_dir that isodream-train wrote"
        )
    state, path = checkpoints.load_latest(required_keys=("config", "models"))
    cfg = config_from_dict(state["config"])
    if cfg.mode == "world_model":
        raise CheckpointError(f"{path} is of a mode=world_model run: it has no policy to evaluate")
    torch.set_num_threads(cfg.train.threads)
    seed_everything(seed)
    components = make_components(
        cfg, action_dim=probe_action_dim(cfg), scratch_dir=Path(run_dir) / "eval_scratch"
    )
    components.load_models(state)
    policy = components.behavior.policy
    env = env_factory(cfg, eval_mode=True)()
    env.append_transform(policy.make_tensordict_primer())
    env.set_seed(seed)
    try:
        results = run_episodes(policy, env, episodes=episodes, record=video is not None, task=cfg.env.name)
    finally:
        env.close()
    if video is not None:
        save_episode_gif(results.frames, video)
    return results.mean, results.std, results.returns
