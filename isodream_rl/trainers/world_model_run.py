"""``mode=world_model``: the world model trained alone on random-action episodes, scored on held-out ones.

``isodream-train exp=world_model`` (or its alias ``isodream-demo``) collects random-action episodes with held
actions (the sprites scene by default; any env of the ``env`` group), trains
:class:`~isodream_rl.modules.IsoDreamWorldModel` with :class:`~isodream_rl.objectives.IsoDreamModelLoss`
through the trainer's :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper` (no actor, no value),
and every ``logging.eval_every`` updates scores it on held-out episodes
(:func:`~isodream_rl.evaluation.branches.score_branches`: on every env with ground-truth masks (sprites,
highway, DMC), :func:`~isodream_rl.evaluation.decomposition_scores`, each branch against the agent, the
distractors and the background; on sprites, each disc's coverage and reconstruction error too) and draws
``pictures/branches_<updates>.png``. It stops after ``world_model.updates`` updates, or once its wall-clock
passes ``world_model.max_minutes``. At the end, on sprites, it probes what each branch's state knows with the
:class:`LatentProbe` it is given (``isodream-train`` gives :func:`~isodream_rl.recipes.latent_probe.probe`) and
writes ``summary.json``. The run folder is an RL run's: ``logs/`` (the TorchRL logger),
``checkpoints/step_<updates>/`` (:class:`~isodream_rl.trainers.checkpoint.CheckpointManager`, which
``resume=true`` continues from), ``pictures/``.

The data are generated from the seed, so checkpoints hold no replay buffer; evaluations run on a forked
random generator, so how often they run does not change the training.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from tqdm import tqdm

from isodream_rl.csv_logs import csv_log_sizes, cut_csv_logs
from isodream_rl.data.sprites_episodes import (
    collect_sprites_episodes,
    held_random_actions,
    make_window_buffer,
)
from isodream_rl.envs.builder import ground_truth_mask_keys
from isodream_rl.evaluation.branches import branch_grid, save_png, score_branches
from isodream_rl.evaluation.decomposition import TRUTH_KEYS
from isodream_rl.modules import IsoDreamWorldModel
from isodream_rl.objectives.pyramid import PyramidImageTerm
from isodream_rl.trainers.builders import (
    REPLAY_KEYS,
    action_dim_of,
    close_logger,
    env_factory,
    make_adam,
    make_logger,
    make_world_model_config,
    make_world_model_loss,
)
from isodream_rl.trainers.checkpoint import CheckpointError, CheckpointManager, rng_state, set_rng_state
from isodream_rl.trainers.config import ConfigError, RunConfig, config_from_dict
from isodream_rl.trainers.hooks import StopOnSignal
from isodream_rl.trainers.run_dir import resuming, write_run_config
from isodream_rl.trainers.run_lifecycle import (
    RunResult,
    begin_run,
    probe_action_dim,
    resume_state,
    write_summary,
)
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper
from isodream_rl.trainers.world_model_config import TORCHRL_BASELINES

logger = logging.getLogger(__name__)


class LatentProbe(Protocol):
    """What each branch's state of ``world_model`` knows: scores (``r2_<branch>_<sprite>``) on ``episodes`` fresh
    sprites episodes from ``seed``, made with the scene :func:`probe_scene` gives
    (:func:`isodream_rl.recipes.latent_probe.probe` is one)."""

    def __call__(
        self, world_model: IsoDreamWorldModel, *, episodes: int, seed: int, encoder: bool, **scene: Any
    ) -> dict[str, float]: ...


#: the ground-truth masks collected with the episodes of an env that has them
TRUTH_MASKS = tuple(key for _, key in TRUTH_KEYS.values())


def _is_sprites(cfg: RunConfig) -> bool:
    return cfg.env.name == "sprites" and not cfg.env.factory


def _sprites_scene(cfg: RunConfig) -> dict:
    """``env.kwargs`` as ``SpritesEnv`` keywords of every episode (their length is the mode's own)."""
    return {key: value for key, value in cfg.env.kwargs.items() if key != "max_steps"}


def collect_episodes(cfg: RunConfig, *, episodes: int, seed: int) -> TensorDict:
    """``episodes`` random-action episodes of ``world_model.episode_length`` steps, actions held for
    ``world_model.action_hold`` steps, in TorchRL's layout: flat ``[episodes * steps]`` with an ``"episode"``
    id.

    Sprites is stepped directly, with its ground-truth masks
    (:func:`~isodream_rl.data.sprites_episodes.collect_sprites_episodes`, 100x faster than through TorchRL);
    any other env of ``cfg.env`` is rolled out through TorchRL (an episode that ends early is reset, marked by
    ``is_init``), with its ``("next", "mask_agent")`` and ``("next", "mask_distractors")`` where it has them
    (:func:`~isodream_rl.envs.builder.ground_truth_mask_keys`).

    Raises:
        ConfigError: ``env.kwargs`` the sprites scene does not take.
    """
    wm = cfg.world_model
    steps = wm.episode_length
    if _is_sprites(cfg):
        try:
            return collect_sprites_episodes(
                episodes=episodes, steps=steps, seed=seed, action_hold=wm.action_hold, **_sprites_scene(cfg)
            )
        except (TypeError, ValueError) as err:
            raise ConfigError(f"invalid training configuration:\n  - env.kwargs: {err}") from err
    # the classes decomposition_scores reads (the env's other masks are its own names for them)
    masks = () if cfg.env.factory or not ground_truth_mask_keys(cfg.env.name) else TRUTH_MASKS
    make = env_factory(cfg)
    env = functools.partial(make, return_masks=True)() if masks else make()
    try:
        env.set_seed(seed)
        actions = held_random_actions(
            seed, episodes=episodes, steps=steps, hold=wm.action_hold, dim=action_dim_of(env)
        ).split(steps)
        rollouts = []
        for chunk in actions:
            # a policy that reads nothing and hands out the episode's held actions in turn
            policy = TensorDictModule(functools.partial(next, iter(chunk)), in_keys=[], out_keys=["action"])
            rollout = env.rollout(steps, policy=policy, break_when_any_done=False)
            rollouts.append(rollout.select(*REPLAY_KEYS, *(("next", key) for key in masks), strict=False))
    finally:
        env.close()
    data = torch.cat(rollouts)
    data["episode"] = torch.arange(episodes).repeat_interleave(steps)
    return data


def schedule_value(points: Sequence[Sequence[float]], update: int) -> float:
    """The piecewise-linear schedule of ``[update, value]`` points (updates increasing) at ``update``: linear
    from 0 at update 0 through the points (a point at update 0 sets the start), the last value held after the
    last point; 0 before update 0."""
    if not points or update < 0:
        return 0.0
    for (u0, v0), (u1, v1) in zip([(0, 0.0), *points], points):
        if update < u1:
            return v0 + (v1 - v0) * max(0.0, update - u0) / (u1 - u0)
    return float(points[-1][1])


def ramp_weight(weight: float, update: int, start: int, length: int | None = None) -> float:
    """0 before update ``start``, then linearly up to ``weight`` at update ``start + length`` (``length``
    defaults to ``start``; ``start = 0``: ``weight`` throughout)."""
    if not start:
        return weight
    length = start if length is None else length
    # length <= 0: the weight jumps from 0 to its value at update start
    return schedule_value([(start, 0.0), (start + max(length, 0), weight)], update)


def probe_scene(cfg: RunConfig, *, window: int | None = None) -> dict:
    """The :class:`LatentProbe` keywords that make episodes like a sprites run's:
    its scene, action hold and window (``window`` overrides ``train.sequence_length``), episodes of
    ``world_model.episode_length`` steps rounded up to whole windows.

    Raises:
        ConfigError: the run is not on the sprites scene (the probe needs its ground truth).
    """
    if not _is_sprites(cfg):
        raise ConfigError(
            f"the latent probe needs the sprites scene's ground truth; this run is on {cfg.env.name!r}"
        )
    window = window or cfg.train.sequence_length
    episode_length = -(-cfg.world_model.episode_length // window) * window
    return {
        **_sprites_scene(cfg),
        "action_hold": cfg.world_model.action_hold,
        "window": window,
        "episode_length": episode_length,
    }


def load_world_model(path: str | Path, *, device: str = "cpu") -> tuple[IsoDreamWorldModel, RunConfig]:
    """The world model (in fp32) and configuration of a checkpoint of ``isodream-train``, either mode.

    Args:
        path: a run folder (its newest readable checkpoint) or one of its ``checkpoints/step_*`` folders.
        device: where the model goes.

    Raises:
        CheckpointError: no readable checkpoint there, or one of a TorchRL baseline (``algo=torchrl_dreamer``,
            ``torchrl_dreamer_v3``: another world model).
    """
    path = Path(path)
    if path.is_file():
        raise CheckpointError(
            f"{path} is a single file: checkpoints are folders (<run_dir>/checkpoints/step_*/), and the "
            "world_model.pt files of isodream-demo before it became isodream-train exp=world_model are no "
            "longer read; give a run folder"
        )
    single = path.name.startswith("step_")
    manager = CheckpointManager(path.parent if single else path / "checkpoints")
    if single:
        try:
            state = manager.load(path, required_keys=("config", "models"))
        except CheckpointError as err:
            raise CheckpointError(f"checkpoint {path} is unreadable: {err}") from err
    else:
        state, path = manager.load_latest(required_keys=("config", "models"))
    cfg = config_from_dict(state["config"])
    if cfg.algo.name in TORCHRL_BASELINES:
        raise CheckpointError(
            f"{path} holds the world model of algo={cfg.algo.name} (TorchRL's), not Iso-Dream's"
        )
    cfg.model.precision = "fp32"
    model = IsoDreamWorldModel(make_world_model_config(cfg, action_dim=probe_action_dim(cfg)), device=device)
    model.load_state_dict(state["models"]["world_model"])
    return model, cfg


def wall_clock() -> float:
    """The clock of the run's wall-clock budget (``world_model.max_minutes``), its ``seconds`` and its
    ``updates_per_s``, in seconds: ``time.perf_counter()`` (a test replaces it to spend the budget in a known
    number of updates)."""
    return time.perf_counter()


#: what ``state.pt`` of a world-model run's checkpoint holds (a checkpoint without one of them is unreadable)
STATE_KEYS = ("config", "models", "stepper", "counters", "rng")


def train(cfg: RunConfig, *, probe: LatentProbe | None = None) -> RunResult:
    """Train (or, with ``resume=true``, continue) the world model of ``cfg`` alone; see the module docstring.

    Args:
        cfg: the run's configuration (``mode=world_model``).
        probe: the latent probe run at the end on sprites; needed there when ``world_model.probe_episodes > 0``.

    Raises:
        ConfigError: invalid configuration (before anything is built), ``resume`` with other settings, or a
            sprites run with ``world_model.probe_episodes`` and no ``probe``.
        CheckpointError: ``resume`` without a readable checkpoint.
        NonFiniteLossError: too many NaN/inf updates in a row.
    """
    started = wall_clock()
    _, run_dir, pictures, logs = begin_run(cfg)
    wm, train_cfg = cfg.world_model, cfg.train
    if probe is None and wm.probe_episodes and _is_sprites(cfg):
        raise ConfigError(
            f"world_model.probe_episodes={wm.probe_episodes} needs the latent probe: pass "
            "train(cfg, probe=isodream_rl.recipes.latent_probe.probe) (isodream-train does), or set "
            "world_model.probe_episodes=0"
        )
    checkpoints = CheckpointManager(run_dir / "checkpoints", keep=cfg.checkpoint.keep)
    # the episodes are made again from the settings: a changed scene or seed would continue on other data
    state, resumed_from = (
        resume_state(cfg, checkpoints, required_keys=STATE_KEYS) if resuming(cfg) else (None, None)
    )
    window, batch_size = train_cfg.sequence_length, train_cfg.batch_size

    logger.info("collecting %d random-action episodes of %d steps", wm.episodes, wm.episode_length)
    data = collect_episodes(cfg, episodes=wm.episodes, seed=train_cfg.seed)
    held_out = collect_episodes(cfg, episodes=wm.held_out_episodes, seed=train_cfg.seed + 1)
    # as many training episodes, scored beside the held-out ones: a gap between the two is memorisation
    seen = data[: held_out.shape[0]]
    buffer = make_window_buffer(data, batch_size=batch_size, window=window)

    pyramid = (
        [PyramidImageTerm(levels=wm.pyramid_levels, lambda_reco_pyramid=wm.lambda_reco_pyramid)]
        if wm.lambda_reco_pyramid
        else []
    )
    loss = make_world_model_loss(cfg, action_dim=data["action"].shape[-1], extra_terms=pyramid)
    world_model = loss.world_model
    stepper = IsoDreamOptimizationStepper(
        model_loss=loss,
        world_model_optimizer=make_adam(
            loss.parameters(), lr=train_cfg.world_model_lr, eps=train_cfg.adam_eps
        ),
        sequence_length=window,
        grad_clip=train_cfg.grad_clip,
        max_nonfinite=train_cfg.max_nonfinite_updates,
    )
    wall_before = 0.0
    if state is not None:
        world_model.load_state_dict(state["models"]["world_model"])
        stepper.load_state_dict(state["stepper"])
        set_rng_state(state["rng"])
        wall_before = state["counters"]["wall_s"]
        if "log_sizes" in state["counters"]:  # rows written after the checkpoint are of a timeline that ended
            cut_csv_logs(logs, state["counters"]["log_sizes"])
        logger.info("resumed from %s (%d updates)", resumed_from, stepper.updates)
    write_run_config(cfg)  # the run starts: its parts are built, the config matches its checkpoint
    first = stepper.updates
    env_steps = wm.episodes * wm.episode_length
    if first >= wm.updates:
        return RunResult(run_dir, resumed_from, logs, pictures, env_steps, first, resumed_from)
    budget = wm.max_minutes * 60.0 if wm.max_minutes else math.inf

    def wall_s() -> float:
        """The run's wall-clock so far, data collection included, summed over resumes."""
        return wall_before + wall_clock() - started

    def save() -> Path:
        return checkpoints.save(
            stepper.updates,
            {
                "config": dataclasses.asdict(cfg),
                "models": {"world_model": world_model.state_dict()},
                "stepper": stepper.state_dict(),
                "counters": {
                    "updates": stepper.updates,
                    "wall_s": wall_s(),
                    "log_sizes": csv_log_sizes(logs),
                },
                "rng": rng_state(),
            },
        )

    log = make_logger(cfg, run_dir=run_dir)

    def evaluate(update: int) -> tuple[dict[str, float], Path]:
        """Held-out and training scores, logged, and the branch picture of the first held-out window."""
        # on a forked generator (the posteriors are samples): evaluating does not change the training
        with torch.random.fork_rng(devices=[]):
            scores, out = score_branches(world_model, held_out, window=window, device=train_cfg.device)
            train_scores, _ = score_branches(world_model, seen, window=window, device=train_cfg.device)
        scores.update({f"train_{key}": value for key, value in train_scores.items()})
        for key, value in scores.items():
            log.log_scalar(key, value, step=update)
        picture = pictures / f"branches_{update:08d}.png"
        return scores, save_png(branch_grid(out, sample=0, steps=window), picture)

    last_checkpoint, picture, scores, metrics = resumed_from, None, {}, {}
    schedule = wm.static_mask_bias_schedule
    bar = tqdm(
        range(first, wm.updates),
        desc=f"world model ({cfg.model.size}, {world_model.config.precision})",
        unit="update",
        initial=first,
        total=wm.updates,
        disable=not cfg.logging.progress_bar,
    )
    clock = wall_clock()
    # a resumed run whose budget was spent before its summary: scored and checkpointed as it is
    out_of_time = wall_s() >= budget
    if out_of_time:
        scores, picture = evaluate(first)
        last_checkpoint = save()
    with StopOnSignal() as signals:
        for update in [] if out_of_time else bar:
            # the bias holds the schedule's offset of the previous update (a resumed model too): move it on
            change = schedule_value(schedule, update) - schedule_value(schedule, update - 1)
            if change:
                world_model.shift_static_mask_bias(change)
            if pyramid and wm.reco_pyramid_from:
                pyramid[0].lambda_reco_pyramid = ramp_weight(
                    wm.lambda_reco_pyramid, update, wm.reco_pyramid_from, wm.ramp_updates
                )
            values = stepper.step(None, buffer.sample().to(train_cfg.device))
            done = update + 1
            out_of_time = wall_s() >= budget
            last = done == wm.updates or out_of_time
            if update % cfg.logging.log_every == 0 or last:
                metrics = {key: float(value) for key, value in values.items()}
                metrics["updates_per_s"] = (done - first) / (wall_clock() - clock)
                for key, value in metrics.items():
                    log.log_scalar(key, value, step=update)
                bar.set_postfix(loss=f"{metrics['loss_model_reco']:.1f}", mse=f"{metrics['reco_mse']:.4f}")
            if (cfg.logging.eval_every and done % cfg.logging.eval_every == 0) or last:
                scores, picture = evaluate(done)
                bar.write(
                    f"update {done}: "
                    + ", ".join(f"{k} {v:.3f}" for k, v in scores.items() if not k.startswith("train_"))
                )
            if done % cfg.checkpoint.every_updates == 0 or last or signals.received is not None:
                last_checkpoint = save()
            if signals.received is not None or out_of_time:
                if out_of_time:
                    bar.write(f"update {done}: world_model.max_minutes={wm.max_minutes} spent, stopping")
                break
    bar.close()
    summary = None
    if signals.received is None:
        if wm.probe_episodes and _is_sprites(cfg):
            # what each branch's state knows, on fresh episodes of the same scene (seeds never trained on)
            probed = probe(
                world_model,
                episodes=wm.probe_episodes,
                seed=train_cfg.seed + 1000,
                encoder=True,
                **probe_scene(cfg),
            )
            scores.update({f"probe_{key}": value for key, value in probed.items()})
            for key, value in probed.items():
                log.log_scalar(f"probe_{key}", value, step=wm.updates)
        summary = {
            "mode": cfg.mode,
            "algo": cfg.algo.name,
            "env": cfg.env.name,
            "updates": stepper.updates,
            "stopped_by": "max_minutes" if out_of_time else "updates",
            "seconds": round(wall_s(), 1),
            "precision": world_model.config.precision,
            "size": cfg.model.size,
            "seed": train_cfg.seed,
            **{key: round(value, 3) for key, value in scores.items()},
            "png": str(picture),
            "checkpoint": str(last_checkpoint),
            "logs": str(logs),
        }
        write_summary(run_dir, summary)
    close_logger(log)
    return RunResult(
        run_dir=run_dir,
        checkpoint=last_checkpoint,
        logs=logs,
        pictures=pictures,
        env_steps=env_steps,
        updates=stepper.updates,
        resumed_from=resumed_from,
        metrics=metrics,
        summary=summary,
    )
