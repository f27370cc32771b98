"""Algorithm 1 as a TorchRL ``Trainer``: assemble a run from a :class:`RunConfig`, train, resume, evaluate.

:func:`train` is the entry of both modes of ``isodream-train``: it checks the config, holds the run folder and
runs ``mode=rl`` here or ``mode=world_model`` (:mod:`isodream_rl.trainers.world_model_run`). The run's parts
come from the algorithm registry (:func:`~isodream_rl.trainers.registry.make_components`).
"""

from __future__ import annotations

import functools
import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torchrl.envs import EnvBase
from torchrl.trainers import ReplayBufferTrainer, Trainer, UpdateWeights

from isodream_rl.envs.builder import ground_truth_mask_keys
from isodream_rl.evaluation.latent_probe import probe
from isodream_rl.run_utils.checkpoint import CheckpointError, CheckpointManager
from isodream_rl.run_utils.csv_logs import csv_log_sizes
from isodream_rl.run_utils.disk_space import ReplayReservation
from isodream_rl.trainers import trainer_state, world_model_run
from isodream_rl.trainers.builders import checked_env_factory, close_logger, make_logger
from isodream_rl.trainers.collectors import make_collector
from isodream_rl.trainers.components import RunComponents
from isodream_rl.trainers.config import (
    ConfigError,
    RunConfig,
    device_error,
    validate_config,
)
from isodream_rl.trainers.evaluation import (
    Evaluation,
    final_decomposition,
    learning_summary,
    run_episodes,
    save_episode_gif,
)
from isodream_rl.trainers.hooks import Throughput
from isodream_rl.trainers.learners import TORCHRL_BASELINES, WORLD_MODEL_LEARNERS, learner_name, learner_of
from isodream_rl.trainers.registry import make_components
from isodream_rl.trainers.run_dir import hold_run_dir, resuming, write_run_config
from isodream_rl.trainers.run_lifecycle import (
    STATE_KEYS,
    RunResult,
    begin_run,
    probe_action_dim,
    restore_run_state,
    resume_state,
    seed_everything,
    train_with_checkpoints,
    write_summary,
)
from isodream_rl.trainers.saved_models import saved_run_config
from isodream_rl.trainers.world_model_run import LatentProbe, probe_scene

logger = logging.getLogger(__name__)


def train(cfg: RunConfig, *, probe: LatentProbe | None = None) -> RunResult:
    """Train (or resume) a run described by ``cfg``; see ``docs/recipes`` for the recipes.

    Steps: check the config; build env probe, world model + loss, behavior (actor, value, attention,
    acting policy), three Adam optimisers in an :class:`IsoDreamOptimizationStepper`, a
    ``TensorDictReplayBuffer(LazyMemmapStorage, SliceSampler)``, a TorchRL ``Collector`` (random prefill, then
    the policy) and a TorchRL ``Trainer`` with hooks for replay, logging, evaluation and checkpoints; with
    ``resume``, restore the newest readable checkpoint; train until ``train.total_steps`` or a signal.

    The run folder is held by this process while it trains (:func:`~isodream_rl.trainers.run_dir.hold_run_dir`);
    a resumed run cuts its CSV logs back to what they held at its checkpoint (:mod:`isodream_rl.run_utils.csv_logs`).

    Args:
        cfg: the run's configuration.
        probe: ``mode=world_model`` only: the latent probe it runs at the end of a sprites run
            (``world_model.probe_episodes``); ``isodream-train`` passes
            :func:`isodream_rl.evaluation.latent_probe.probe`.

    Raises:
        ConfigError: invalid configuration (before anything is built), a run folder that holds another run or
            cannot be written, a world-model run on sprites with ``world_model.probe_episodes`` but no
            ``probe``.
        RunDirBusyError: another live process uses the run folder.
        CheckpointError: ``resume`` without a readable checkpoint.
        DiskFullError: the disk filled up (the message names the checkpoint to resume from).
        NonFiniteLossError: too many NaN/inf updates in a row.
    """
    validate_config(cfg)
    with hold_run_dir(cfg):
        if cfg.mode == "world_model":  # the world model alone, on episodes collected first, in the same loop
            return world_model_run.train(cfg, probe=probe)
        return _train_rl(cfg)


def _make_run_components(cfg: RunConfig, run_dir: Path) -> RunComponents:
    """The run's parts for the env's action width, the replay buffer's memmap files under
    ``<run_dir>/replay_scratch``."""
    scratch = run_dir / "replay_scratch"
    # The memmap files of an earlier process of this run (killed, or finished) are stale: the replay data
    # that matters is in the checkpoints.
    shutil.rmtree(scratch, ignore_errors=True)
    return make_components(cfg, action_dim=probe_action_dim(cfg), scratch_dir=scratch)


def _decomposes(cfg: RunConfig) -> bool:
    """Whether the evaluations score the decomposition: where the env renders the ground truth and the world model
    is Iso-Dream's (any of its variants)."""
    return (
        cfg.algo.name not in TORCHRL_BASELINES
        and not cfg.env.factory
        and bool(ground_truth_mask_keys(cfg.env.name))
    )


def _eval_env(cfg: RunConfig, policy, masks: bool = False) -> EnvBase:
    """An evaluation env of the run (its ground-truth masks with ``masks``), primed for ``policy``."""
    make = checked_env_factory(cfg, eval_mode=True, which=" (evaluation)")
    env = (functools.partial(make, return_masks=True) if masks else make)()
    env.append_transform(policy.make_tensordict_primer())
    return env


def _restore_components(
    components: RunComponents, state: dict, *, checkpoints: CheckpointManager, checkpoint: Path, logs: Path
) -> None:
    """Continue from ``checkpoint`` (its ``state``): the replay buffer, the weights, the stepper, the CSV logs and
    the replay and episode-return hooks."""
    checkpoints.load_replay(checkpoint, components.replay_buffer)
    restore_run_state(
        state,
        checkpoint=checkpoint,
        load_models=functools.partial(components.load_models, checkpoint=checkpoint),
        stepper=components.stepper,
        logs=logs,
    )
    components.preparation.load_state_dict(state["hooks"]["preparation"])
    components.returns.load_state_dict(state["hooks"]["returns"])
    logger.info("resumed from %s (%d env steps)", checkpoint, state["counters"]["env_steps"])


def _make_trainer(
    cfg: RunConfig, components: RunComponents, collector, *, log, env_steps: int, state: dict | None
) -> Trainer:
    """TorchRL's ``Trainer`` of an RL run from ``env_steps`` on (a resumed run's counters restored), with the
    replay, episode-return, throughput and (several envs or a remote collector) weight-update hooks."""
    train_cfg, stepper = cfg.train, components.stepper
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
    return trainer


def _periodic_evaluation(
    cfg: RunConfig, components: RunComponents, *, env_factory, pictures: Path, clock, log, decomposition: bool
) -> Evaluation:
    """The evaluation every ``logging.eval_every`` env steps: episodes of the policy, an open-loop prediction GIF
    and, with ``decomposition``, the world model's mask scores."""
    return Evaluation(
        policy=components.behavior.policy,
        env_factory=env_factory,
        world_model=components.world_model,
        replay_buffer=components.replay_buffer,
        sequence_length=cfg.train.sequence_length,
        pictures=pictures,
        every=cfg.logging.eval_every,
        episodes=cfg.logging.eval_episodes,
        task=cfg.env.name,
        clock=clock,
        context=cfg.logging.video_context,
        length=cfg.logging.video_length,
        # The CSV logger can only write videos as MP4 through torchcodec (not a dependency); the GIF suffices.
        logger=None if cfg.logging.backend == "csv" else log,
        decomposition=decomposition,
    )


def _train_rl(cfg: RunConfig) -> RunResult:
    """:func:`train` in ``mode=rl``, in the run folder it holds."""
    started, run_dir, pictures, logs = begin_run(cfg)
    train_cfg = cfg.train
    checkpoints = CheckpointManager(run_dir / "checkpoints", keep=cfg.checkpoint.keep)
    resumed_from, state = None, None
    if resuming(cfg):
        state, resumed_from = resume_state(cfg, checkpoints, required_keys=STATE_KEYS)
    components = _make_run_components(cfg, run_dir)
    stepper, policy = components.stepper, components.behavior.policy
    if state is not None:
        _restore_components(components, state, checkpoints=checkpoints, checkpoint=resumed_from, logs=logs)
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
        first_step=env_steps,
    )
    log = make_logger(cfg, run_dir=run_dir)
    trainer = _make_trainer(cfg, components, collector, log=log, env_steps=env_steps, state=state)
    decomposition = _decomposes(cfg)
    eval_env = functools.partial(_eval_env, cfg, policy)
    evaluation = None
    if cfg.logging.eval_every > 0:
        evaluation = _periodic_evaluation(
            cfg,
            components,
            env_factory=functools.partial(eval_env, masks=decomposition),
            pictures=pictures,
            clock=wall_s,
            log=log,
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

    stopped_by_signal = train_with_checkpoints(
        trainer, save=save, stepper=stepper, every_updates=cfg.checkpoint.every_updates
    )
    train_wall_s = wall_s()
    summary = None
    if stopped_by_signal is None and cfg.logging.final_eval_episodes > 0:
        summary = final_evaluation(
            cfg,
            policy,
            env_factory=eval_env,
            env_steps=trainer.collected_frames,
            wall_s=train_wall_s,
            run_dir=run_dir,
            world_model=components.world_model if decomposition else None,
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
        stopped_by_signal=stopped_by_signal,
    )


def final_evaluation(
    cfg: RunConfig,
    policy,
    *,
    env_factory,
    env_steps: int,
    wall_s: float,
    run_dir: Path,
    world_model=None,
) -> dict:
    """Evaluate the trained policy (``logging.final_eval_episodes`` mode-action episodes) next to the task's
    reference policies and write ``<run_dir>/summary.json`` (see :func:`learning_summary`).

    With ``world_model`` (an Iso-Dream world model on an env that renders the ground-truth masks;
    ``env_factory(masks=True)`` must build that env), the summary also holds the decomposition scores of the
    first episode and where they put the agent (:func:`final_decomposition`)."""
    env = env_factory(masks=True) if world_model is not None else env_factory()
    env.set_seed(cfg.train.seed + 1)
    try:
        results = run_episodes(
            policy,
            env,
            episodes=cfg.logging.final_eval_episodes,
            task=cfg.env.name,
            keep_rollout=world_model is not None,
        )
    finally:
        env.close()
    summary = learning_summary(
        results, env_name=cfg.env.name, env_kwargs=dict(cfg.env.kwargs), env_steps=env_steps, wall_s=wall_s
    )
    if world_model is not None:
        summary.update(
            final_decomposition(world_model, results.first_rollout, window=cfg.train.sequence_length)
        )
    summary.update(updates_per_env_step=1.0 / cfg.train.train_every, algo=cfg.algo.name, seed=cfg.train.seed)
    write_summary(run_dir, summary)
    return summary


def _is_scalar(value) -> bool:
    return isinstance(value, (int, float)) or (isinstance(value, torch.Tensor) and value.numel() == 1)


def _checkpoint_components(
    run_dir: str | Path,
    *,
    seed: int,
    device: str,
    refuse: Callable[[RunConfig], str | None] | None = None,
) -> tuple[RunConfig, RunComponents, Path]:
    """The configuration of ``run_dir``'s newest readable checkpoint, its models (loaded and built on ``device``,
    :func:`evaluate_checkpoint`) and the checkpoint's path; seeds everything with ``seed`` and sets the run's
    torch threads.

    ``refuse`` reads the saved configuration before anything is built: the line it returns (``None``: none) is
    raised as a :class:`ConfigError` (a run the caller cannot use, whose env or models need not build here)."""
    unusable = device_error(device, setting="--device")
    if unusable:
        raise ConfigError(unusable)
    checkpoints = CheckpointManager(Path(run_dir) / "checkpoints", keep=2)
    if not checkpoints.checkpoints():
        raise CheckpointError(
            f"no checkpoint in {checkpoints.directory}: give the run_dir that isodream-train wrote"
        )
    state, path = checkpoints.load_latest(required_keys=("config", "models"))
    cfg = saved_run_config(state)
    if cfg.mode == "world_model":
        raise CheckpointError(f"{path} is of a mode=world_model run: it has no policy to evaluate")
    refused = refuse(cfg) if refuse is not None else None
    if refused:
        raise ConfigError(refused)
    torch.set_num_threads(cfg.train.threads)
    seed_everything(seed)
    cfg.train.device = device
    components = make_components(
        cfg, action_dim=probe_action_dim(cfg), scratch_dir=Path(run_dir) / "eval_scratch"
    )
    components.load_models(state, checkpoint=path)
    return cfg, components, path


def evaluate_checkpoint(
    run_dir: str | Path,
    *,
    episodes: int = 5,
    video: str | Path | None = None,
    seed: int = 0,
    device: str = "cpu",
) -> tuple[float, float, list[float]]:
    """Load the newest readable checkpoint of ``run_dir`` and run ``episodes`` mode-action episodes.

    The checkpoint is read onto the CPU and its models built on ``device``, whichever device trained them: a GPU
    run evaluates on a CPU-only machine. The models are those of its saved configuration, an ``algo=isodream`` run
    of the DreamerV2-style learner (saved before that name became Iso-Dream on DreamerV3's learner) read as
    ``algo=isodream_v2`` (:func:`~isodream_rl.trainers.saved_models.saved_run_config`).

    Args:
        run_dir: the run folder given to ``isodream-train``.
        episodes: how many episodes.
        video: write the first episode there as a GIF (``None``: no GIF).
        seed: env and policy seed.
        device: where the policy acts (``"cpu"``, ``"cuda"``).

    Returns:
        ``(mean, std, returns)``.

    Raises:
        ConfigError: ``device`` is not usable on this machine.
        CheckpointError: no readable checkpoint, or one of a ``mode=world_model`` run, or one whose weights do not
            fit the models of its configuration (:class:`~isodream_rl.trainers.saved_models.CheckpointMismatchError`).
    """
    cfg, components, _ = _checkpoint_components(run_dir, seed=seed, device=device)
    policy = components.behavior.policy
    env = checked_env_factory(cfg, eval_mode=True)()
    env.append_transform(policy.make_tensordict_primer())
    env.set_seed(seed)
    try:
        results = run_episodes(policy, env, episodes=episodes, record=video is not None, task=cfg.env.name)
    finally:
        env.close()
    if video is not None:
        save_episode_gif(results.frames, video)
    return results.mean, results.std, results.returns


def checkpoint_decomposition(run_dir: str | Path, *, seed: int | None = None, device: str = "cpu") -> dict:
    """Score the decomposition of ``run_dir``'s newest checkpoint again, as its final evaluation did.

    Plays one mode-action episode on the run's evaluation env with the ground-truth masks, seeded as the final
    evaluation's first episode (``train.seed + 1``) unless ``seed`` is given, and scores the world model's
    branches over up to 8 windows of ``train.sequence_length`` (:func:`final_decomposition`). On the final
    checkpoint this is the run's ``summary.json`` decomposition again, with every score the library has now
    (e.g. which branch draws the sprites target, ``target_share_<branch>``).

    Args:
        run_dir: the run folder given to ``isodream-train`` (``mode=rl``).
        seed: the episode's env and policy seed (``None``: the final evaluation's).
        device: where the models run.

    Returns:
        ``{"decomposition": {score: value}, "isolation": {...}, "episode_steps": int, "checkpoint": str}``
        (the checkpoint read).

    Raises:
        ConfigError: ``device`` is not usable, or the run's world model is not Iso-Dream's or its env renders no
            ground truth (nothing to score).
        CheckpointError: as :func:`evaluate_checkpoint`.
    """
    cfg, components, path = _checkpoint_components(run_dir, seed=0 if seed is None else seed, device=device)
    if not _decomposes(cfg) or components.world_model is None:
        raise ConfigError(
            f"{run_dir} has nothing to score: algo={cfg.algo.name} on env={cfg.env.name} has no Iso-Dream world "
            "model or no ground-truth masks"
        )
    seed = cfg.train.seed + 1 if seed is None else seed
    seed_everything(seed)
    policy = components.behavior.policy
    env = _eval_env(cfg, policy, masks=True)
    env.set_seed(seed)
    try:
        results = run_episodes(policy, env, episodes=1, task=cfg.env.name, keep_rollout=True)
    finally:
        env.close()
    scores = final_decomposition(
        components.world_model, results.first_rollout, window=cfg.train.sequence_length
    )
    return {**scores, "episode_steps": int(results.first_rollout.shape[0]), "checkpoint": str(path)}


def _probe_refusal(cfg: RunConfig, run_dir: str | Path) -> str | None:
    """Why :func:`checkpoint_probe` cannot probe the run of ``cfg`` (one line naming its algo and env), ``None``
    when it can: an Iso-Dream world model (either learner's, :data:`WORLD_MODEL_LEARNERS`) on the sprites scene."""
    problems = []
    if learner_name(cfg.algo.name) not in WORLD_MODEL_LEARNERS:
        problems.append(
            f"algo={cfg.algo.name} ({learner_of(cfg.algo.name).title}) has no Iso-Dream world model"
        )
    if cfg.env.name != "sprites" or cfg.env.factory:
        env = f"env.factory={cfg.env.factory}" if cfg.env.factory else f"env={cfg.env.name}"
        problems.append(f"{env} is not the sprites scene, whose ground truth the probe reads")
    if not problems:
        return None
    return f"{run_dir} cannot be probed: " + " and ".join(problems)


def checkpoint_probe(
    run_dir: str | Path,
    *,
    episodes: int = 32,
    window: int | None = None,
    device: str = "cpu",
    seed: int = 1000,
) -> dict:
    """The latent probe of ``run_dir``'s newest checkpoint: which sprites each branch's posterior state carries.

    Runs :func:`isodream_rl.evaluation.latent_probe.probe` on the checkpoint's world model over fresh
    random-action episodes of the run's scene (its ``env.kwargs``: ``num_distractors``, ``sprite_size``,
    ``num_backgrounds``, ``background_seed``, colours..., as :func:`~isodream_rl.trainers.world_model_run.probe_scene`
    reads them), cut into windows of ``window`` steps; the episodes are ``world_model.episode_length`` steps (96
    unless the run set it) rounded up to whole windows, their actions held ``world_model.action_hold`` steps. Unlike
    the mask IoU of :func:`checkpoint_decomposition`, which a run without a static branch caps (its action-free
    branch draws the background too), the probe says whether the action-free branch's state knows where the
    moving discs are. A scene without distractors probes the agent alone.

    Args:
        run_dir: the run folder given to ``isodream-train`` (``mode=rl``).
        episodes: probe episodes (half fit the ridge regressions, half score them; at least 2).
        window: the windows' length (``None``: the run's ``train.sequence_length``).
        device: where the world model runs.
        seed: the episodes' and the posterior samples' seed (the same scores for one checkpoint on every call).

    Returns:
        ``{"probe": {"r2_<branch>_<sprite>": float}, "checkpoint": str}``: the held-out R^2 of each dynamic
        branch (``control``, and ``free`` with the action-free branch) and sprite (``agent``, ``distractor_0``,
        ...), near 1 where the branch's state tells where the sprite is, at or below 0 where it does not; and the
        checkpoint read.

    Raises:
        ConfigError: ``device`` is not usable, or the run's world model is not Iso-Dream's or its env is not the
            sprites scene (one line naming its ``algo`` and ``env``; nothing is built then).
        CheckpointError: as :func:`evaluate_checkpoint`.
        ValueError: fewer than 2 ``episodes``, or a ``window`` below 1.
    """
    if episodes < 2:
        raise ValueError(
            f"episodes={episodes}: the probe fits on half the episodes and scores the rest: give >= 2"
        )
    if window is not None and window < 1:
        raise ValueError(f"window={window} must be >= 1 (None: the run's train.sequence_length)")
    cfg, components, path = _checkpoint_components(
        run_dir, seed=seed, device=device, refuse=functools.partial(_probe_refusal, run_dir=run_dir)
    )
    scene = probe_scene(cfg, window=window)
    scores = probe(components.world_model, episodes=episodes, seed=seed, **scene)
    return {"probe": scores, "checkpoint": str(path)}
