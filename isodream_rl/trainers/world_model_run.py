"""``mode=world_model``: the world model trained alone on random-action episodes, scored on held-out ones.

``isodream-train exp=world_model`` (or its alias ``isodream-demo``) collects random-action episodes with held
actions (the sprites scene by default; any env of the ``env`` group), trains the world model of the run's learner
alone (no actor, no value), with the loss and the world-model optimiser a run of that learner gives it
(:class:`~isodream_rl.trainers.components.WorldModelAlone`, :data:`WORLD_MODEL_BUILDERS`):

* the default, ``algo=isodream`` and its ablations (Iso-Dream on DreamerV3's learner):
  :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel` with
  :class:`~isodream_rl.objectives.isodream.IsoDreamModelLoss` and its ``DreamerV3Optimizer``
  (:func:`~isodream_rl.trainers.isodream.make_world_model_alone`);
* the DreamerV2-style learner, ``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2`` (the ``exp`` files' algo):
  :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` with
  :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ModelLoss` and Adam
  (:func:`~isodream_rl.trainers.isodream_v2.make_world_model_alone`).

TorchRL's baselines, whose world models have no branches, are refused. Every ``logging.eval_every`` updates it
scores the world model on held-out episodes
(:func:`~isodream_rl.evaluation.branches.score_branches`: on every env with ground-truth masks (sprites,
highway, DMC), :func:`~isodream_rl.evaluation.decomposition_scores`, each branch against the agent, the
distractors and the background; on sprites, each disc's coverage and reconstruction error too) and draws
``pictures/branches_<updates>.png``. It stops after ``world_model.updates`` updates, or once its wall-clock
passes ``world_model.max_minutes``. At the end, on sprites, it probes what each branch's state knows with the
:class:`LatentProbe` it is given (``isodream-train`` gives :func:`~isodream_rl.evaluation.latent_probe.probe`) and
writes ``summary.json`` (its ``algo``, its ``learner``, the last scores). The loop is the RL run's
(:func:`~isodream_rl.trainers.run_lifecycle.train_with_checkpoints`: TorchRL's ``Trainer``, fed by
:class:`FixedData`, no new env steps), and so is the run folder: ``logs/`` (the TorchRL logger),
``checkpoints/step_<updates>/`` (:class:`~isodream_rl.run_utils.checkpoint.CheckpointManager`, which
``resume=true`` continues from), ``pictures/``.

The data are generated from the seed, so checkpoints hold no replay buffer; evaluations run on a forked
random generator, so how often they run does not change the training.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.trainers import Trainer, TrainerHookBase
from tqdm import tqdm

from isodream_rl.data.sprites_episodes import (
    collect_sprites_episodes,
    held_random_actions,
    make_window_buffer,
)
from isodream_rl.envs.builder import ground_truth_mask_keys
from isodream_rl.evaluation.branches import branch_grid, save_png, score_branches
from isodream_rl.evaluation.decomposition import TRUTH_KEYS
from isodream_rl.evaluation.latent_probe import ProbedModel
from isodream_rl.run_utils.checkpoint import CheckpointError, CheckpointManager
from isodream_rl.trainers import isodream, isodream_v2
from isodream_rl.trainers.builders import (
    REPLAY_KEYS,
    action_dim_of,
    checked_env_factory,
    close_logger,
    make_logger,
)
from isodream_rl.trainers.components import WorldModelAlone
from isodream_rl.trainers.config import ConfigError, RunConfig
from isodream_rl.trainers.learners import (
    learner_name,
    learner_of,
    resolved,
    world_model_algos,
    world_model_mode_error,
)
from isodream_rl.trainers.run_dir import resuming, write_run_config
from isodream_rl.trainers.run_lifecycle import (
    RunResult,
    begin_run,
    probe_action_dim,
    restore_run_state,
    resume_state,
    run_state,
    train_with_checkpoints,
    write_summary,
)
from isodream_rl.trainers.saved_models import load_saved_models, saved_run_config

logger = logging.getLogger(__name__)


class LatentProbe(Protocol):
    """What each branch's state of ``world_model`` knows: scores (``r2_<branch>_<sprite>``) on ``episodes`` fresh
    sprites episodes from ``seed``, made with the scene :func:`probe_scene` gives
    (:func:`isodream_rl.evaluation.latent_probe.probe` is one)."""

    def __call__(
        self, world_model: ProbedModel, *, episodes: int, seed: int, encoder: bool, **scene: Any
    ) -> dict[str, float]: ...


@dataclass(frozen=True)
class WorldModelBuilder:
    """What ``mode=world_model`` builds of one of Iso-Dream's learners: what differs between them in a run of the
    mode and in reading it back (the loop, the data, the scores, the pictures and the checkpoints are the same)."""

    alone: Callable[..., WorldModelAlone]
    """``(cfg, *, action_dim) -> WorldModelAlone``: the world model, its loss and its stepper, to train."""
    world_model: Callable[..., nn.Module]
    """``(cfg, *, action_dim, device) -> world model``: the world model alone, to read a checkpoint's weights
    into."""


#: ``learner -> builder``, one for each of :data:`~isodream_rl.trainers.learners.WORLD_MODEL_LEARNERS` (which the
#: configuration's check reads): the world model of each learner ``mode=world_model`` trains.
WORLD_MODEL_BUILDERS: dict[str, WorldModelBuilder] = {
    "isodream": WorldModelBuilder(
        alone=isodream.make_world_model_alone, world_model=isodream.make_world_model
    ),
    "isodream_v2": WorldModelBuilder(
        alone=isodream_v2.make_world_model_alone, world_model=isodream_v2.make_world_model
    ),
}


def world_model_builder(algo: str) -> WorldModelBuilder:
    """The :class:`WorldModelBuilder` of the learner ``algo=<algo>`` builds.

    Raises:
        ConfigError: a learner whose world model the mode does not train (TorchRL's baselines: no branches); the
            one line names the algorithms it trains
            (:func:`~isodream_rl.trainers.learners.world_model_mode_error`).
    """
    refused = world_model_mode_error(algo)
    if refused:
        raise ConfigError(f"invalid training configuration: {refused}")
    return WORLD_MODEL_BUILDERS[learner_name(algo)]


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
    make = checked_env_factory(cfg)
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


def load_world_model(path: str | Path, *, device: str = "cpu") -> tuple[ProbedModel, RunConfig]:
    """The world model (in fp32) and configuration of a checkpoint of ``isodream-train``, either mode, of either
    Iso-Dream learner: an :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel` for the default's
    (``algo=isodream`` and its ablations), an :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` for
    the DreamerV2-style learner's (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``).

    Args:
        path: a run folder (its newest readable checkpoint) or one of its ``checkpoints/step_*`` folders.
        device: where the model goes.

    Returns:
        ``(world_model, cfg)``: the world model with the checkpoint's weights, and the configuration it was saved
        with, under the name of the learner its weights are of.

    Raises:
        CheckpointError: no readable checkpoint there, or one of a world model without branches (TorchRL's
            baselines), or weights that do not fit the world model of its configuration
            (:class:`~isodream_rl.trainers.saved_models.CheckpointMismatchError`). A run (of either mode) saved by
            ``algo=isodream`` or one of its ablations when those names were the DreamerV2-style learner is read as
            ``algo=isodream_v2``, its weights telling (:func:`~isodream_rl.trainers.saved_models.saved_run_config`).
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
    cfg = saved_run_config(state)
    if learner_name(cfg.algo.name) not in WORLD_MODEL_BUILDERS:
        raise CheckpointError(
            f"{path} holds the world model of algo={cfg.algo.name} ({learner_of(cfg.algo.name).title}), which has "
            f"no branches: load_world_model reads those of {', '.join(f'algo={n}' for n in world_model_algos())}"
        )
    cfg.model.precision = "fp32"
    model = world_model_builder(cfg.algo.name).world_model(
        cfg, action_dim=probe_action_dim(cfg), device=device
    )
    load_saved_models({"world_model": model}, state, algo=cfg.algo.name, checkpoint=path)
    return model, cfg


def wall_clock() -> float:
    """The clock of the run's wall-clock budget (``world_model.max_minutes``), its ``seconds`` and its
    ``updates_per_s``, in seconds: ``time.perf_counter()`` (a test replaces it to spend the budget in a known
    number of updates)."""
    return time.perf_counter()


#: what ``state.pt`` of a world-model run's checkpoint must hold to be read (:func:`~isodream_rl.trainers.
#: run_lifecycle.run_state`; checkpoints written before the mode ran through the RL run's loop have no "hooks")
STATE_KEYS = ("config", "models", "stepper", "counters", "rng")


class FixedData:
    """The collector of a run on data collected before it: ``batches`` empty batches, no new env steps, for a
    TorchRL ``Trainer`` with one update per batch (its ``process_optim_batch`` hook samples the data).

    Args:
        batches: batches (updates) to hand out.
    """

    init_random_frames = 0

    def __init__(self, batches: int) -> None:
        self.batches = batches

    def __iter__(self):
        for _ in range(self.batches):
            # the Trainer counts a batch's frames by its ("collector", "mask"): none here
            yield TensorDict({("collector", "mask"): torch.zeros(0, dtype=torch.bool)}, batch_size=[0])

    def shutdown(self) -> None:
        """Nothing to stop."""


#: the logged name of a score of :class:`BranchEvaluation` is this prefix and the score's name, as an RL run logs
#: its world model's decomposition scores
EVAL_PREFIX = "eval/decomposition/"


class BranchEvaluation:
    """The evaluation of ``mode=world_model``, its counterpart of the RL run's
    :class:`~isodream_rl.trainers.evaluation.Evaluation`: scores on the held-out episodes and, ``train_*``, on as
    many training episodes (:func:`~isodream_rl.evaluation.branches.score_branches`), logged at the update as
    ``eval/decomposition/<score>`` (:data:`EVAL_PREFIX`; ``train_<score>`` for the training episodes'),
    and the branch picture of the first held-out window, ``<pictures>/branches_<updates>.png``.

    It runs on a forked random generator (the posteriors are samples): evaluating does not change the training.

    Args:
        world_model: the world model to score.
        held_out: flat held-out episodes ``[episodes * steps]``.
        seen: as many training episodes.
        window: window length T the episodes are cut into.
        device: where the model runs.
        pictures: folder of the pictures.
        logger: TorchRL logger of the scores.
    """

    def __init__(
        self,
        *,
        world_model: nn.Module,
        held_out: TensorDict,
        seen: TensorDict,
        window: int,
        device: str,
        pictures: Path,
        logger,
    ) -> None:
        self.world_model, self.held_out, self.seen = world_model, held_out, seen
        self.window, self.device, self.pictures, self.logger = window, device, Path(pictures), logger
        self.last = 0
        self.last_scores: dict[str, float] = {}
        self.last_picture: Path | None = None

    def evaluate(self, step: int) -> dict[str, float]:
        """Score and draw now (``step``: the update count); returns the logged scores."""
        with torch.random.fork_rng(devices=[]):
            scores, out = score_branches(
                self.world_model, self.held_out, window=self.window, device=self.device
            )
            train_scores, _ = score_branches(
                self.world_model, self.seen, window=self.window, device=self.device
            )
        scores.update({f"train_{key}": value for key, value in train_scores.items()})
        for key, value in scores.items():
            # an RL run's names for its decomposition scores; the loss's own ``reco_mse`` (the DreamerV2-style
            # loss's, on the training batch) keeps its plain name
            self.logger.log_scalar(f"{EVAL_PREFIX}{key}", value, step=step)
        picture = self.pictures / f"branches_{step:08d}.png"
        self.last_picture = save_png(branch_grid(out, sample=0, steps=self.window), picture)
        self.last, self.last_scores = step, scores
        return scores

    def state_dict(self) -> dict:
        return {"last": self.last}

    def load_state_dict(self, state_dict: dict) -> None:
        self.last = state_dict["last"]


#: ``metric -> (label, format)`` of the progress bar, for the metrics a learner's world-model loss has
#: (``reco_mse`` is the DreamerV2-style loss's)
_POSTFIX = {"loss_model_reco": ("loss", ".1f"), "reco_mse": ("mse", ".4f")}


class UpdateCadence(TrainerHookBase):
    """``post_steps`` hook of ``mode=world_model``: after each update, its losses logged every ``log_every``
    updates, the :class:`BranchEvaluation` every ``eval_every`` updates, and a stop once the wall-clock budget
    is spent; the last update (the ``updates``-th, or the one past the budget) is logged and evaluated.

    Args:
        first: the update count the run starts from (a resumed run's).
        updates: the update count at which the run ends.
        log_every: updates between logged losses.
        eval_every: updates between evaluations (0: after the last update only).
        evaluation: the :class:`BranchEvaluation`.
        logger: TorchRL logger of the losses.
        wall_s: ``() -> seconds`` of the run's wall-clock so far.
        max_minutes: the wall-clock budget in minutes (0: none).
        progress_bar: show a progress bar.
        desc: its label.
    """

    def __init__(
        self,
        *,
        first: int,
        updates: int,
        log_every: int,
        eval_every: int,
        evaluation: BranchEvaluation,
        logger,
        wall_s,
        max_minutes: float,
        progress_bar: bool,
        desc: str,
    ) -> None:
        self.first, self.done, self.updates = first, first, updates
        self.log_every, self.eval_every, self.evaluation = log_every, eval_every, evaluation
        self.logger, self.wall_s, self.max_minutes = logger, wall_s, max_minutes
        self.budget_s = max_minutes * 60.0 if max_minutes else math.inf
        self.out_of_time = False
        self.metrics: dict[str, float] = {}
        self._values = None
        self._trainer = None
        self._clock = wall_clock()
        self.bar = tqdm(total=updates, initial=first, desc=desc, unit="update", disable=not progress_bar)

    def record(self, optim_steps: int, losses) -> None:
        """``post_optim_complete_log``: keep the update's losses."""
        self._values = losses

    def __call__(self) -> None:
        update = self.done
        self.done = done = update + 1
        self.out_of_time = self.wall_s() >= self.budget_s
        last = done == self.updates or self.out_of_time
        if update % self.log_every == 0 or last:
            metrics = {key: float(value) for key, value in self._values.items()}
            metrics["updates_per_s"] = (done - self.first) / (wall_clock() - self._clock)
            for key, value in metrics.items():
                self.logger.log_scalar(key, value, step=update)
            self.bar.set_postfix(
                {name: f"{metrics[key]:{spec}}" for key, (name, spec) in _POSTFIX.items() if key in metrics}
            )
            self.metrics = metrics
        if (self.eval_every and done % self.eval_every == 0) or last:
            scores = self.evaluation.evaluate(done)
            self.bar.write(
                f"update {done}: "
                + ", ".join(f"{k} {v:.3f}" for k, v in scores.items() if not k.startswith("train_"))
            )
        self.bar.update(1)
        if self.out_of_time:
            self.bar.write(f"update {done}: world_model.max_minutes={self.max_minutes} spent, stopping")
            self._trainer.request_stop("world_model.max_minutes spent")

    def register(self, trainer, name: str = "update_cadence") -> None:
        self._trainer = trainer
        trainer.register_op("post_optim_complete_log", self.record)
        trainer.register_op("post_steps", self)


class _WorldModelRun:
    """The parts of one ``mode=world_model`` run and what it does with them: the world model, its loss and stepper
    (no actor, no value: the learner's :class:`~isodream_rl.trainers.components.WorldModelAlone`, from
    :func:`world_model_builder`), the evaluation on held-out episodes, the logger, the checkpoints and the wall
    clock (summed over resumes)."""

    def __init__(
        self,
        cfg: RunConfig,
        *,
        run_dir: Path,
        pictures: Path,
        logs: Path,
        checkpoints: CheckpointManager,
        started: float,
    ) -> None:
        wm, train_cfg = cfg.world_model, cfg.train
        self.cfg, self.logs, self.checkpoints, self.started = cfg, logs, checkpoints, started
        logger.info("collecting %d random-action episodes of %d steps", wm.episodes, wm.episode_length)
        data = collect_episodes(cfg, episodes=wm.episodes, seed=train_cfg.seed)
        held_out = collect_episodes(cfg, episodes=wm.held_out_episodes, seed=train_cfg.seed + 1)
        self.buffer = make_window_buffer(
            data, batch_size=train_cfg.batch_size, window=train_cfg.sequence_length
        )
        parts = world_model_builder(cfg.algo.name).alone(cfg, action_dim=data["action"].shape[-1])
        self.loss, self.world_model, self.stepper = parts.model_loss, parts.world_model, parts.stepper
        self.precision = parts.precision
        self.log = make_logger(cfg, run_dir=run_dir)
        self.evaluation = BranchEvaluation(
            world_model=self.world_model,
            held_out=held_out,
            # as many training episodes, scored beside the held-out ones: a gap between the two is memorisation
            seen=data[: held_out.shape[0]],
            window=train_cfg.sequence_length,
            device=train_cfg.device,
            pictures=pictures,
            logger=self.log,
        )
        self.env_steps = wm.episodes * wm.episode_length
        self.wall_before = 0.0
        self.last_checkpoint: Path | None = None

    def restore(self, state: dict, checkpoint: Path) -> None:
        """Continue from a checkpoint's ``state``: the weights, the stepper, the CSV logs, the evaluation's
        history and the wall clock."""
        models = {"world_model": self.world_model}
        restore_run_state(
            state,
            checkpoint=checkpoint,
            load_models=functools.partial(
                load_saved_models, models, algo=self.cfg.algo.name, checkpoint=checkpoint
            ),
            stepper=self.stepper,
            logs=self.logs,
        )
        if (state.get("hooks") or {}).get("evaluation") is not None:
            self.evaluation.load_state_dict(state["hooks"]["evaluation"])
        self.wall_before = state["counters"]["wall_s"]
        self.last_checkpoint = checkpoint
        logger.info("resumed from %s (%d updates)", checkpoint, self.stepper.updates)

    def wall_s(self) -> float:
        """The run's wall-clock so far, data collection included, summed over resumes."""
        return self.wall_before + wall_clock() - self.started

    def save(self) -> Path:
        """Write a checkpoint at the current update; its folder."""
        saved = run_state(
            self.cfg,
            models={"world_model": self.world_model},
            stepper=self.stepper,
            counters={"env_steps": self.env_steps, "updates": self.stepper.updates, "wall_s": self.wall_s()},
            hooks={"evaluation": self.evaluation.state_dict()},
            logs=self.logs,
        )
        self.last_checkpoint = self.checkpoints.save(self.stepper.updates, saved)
        return self.last_checkpoint

    def trainer(self, cadence: UpdateCadence) -> Trainer:
        """TorchRL's ``Trainer`` over the updates still to run, sampling windows of the collected episodes, with
        ``cadence`` registered."""
        trainer = Trainer(
            collector=FixedData(self.cfg.world_model.updates - self.stepper.updates),
            # no batch brings env steps: the run ends with FixedData's batches, or a hook's stop
            total_frames=self.env_steps + 1,
            frame_skip=1,
            optim_steps_per_batch=1,
            loss_module=self.loss,
            optimization_stepper=self.stepper,
            logger=None,  # UpdateCadence logs the losses at the update count, the Trainer would at env steps
            progress_bar=False,
            save_trainer_file=None,
        )
        trainer.collected_frames = self.env_steps

        def sample(batch: TensorDict) -> TensorDict:
            """``process_optim_batch``: ``batch_size`` windows of the collected episodes, on the CPU (the stepper
            moves them to the model's device)."""
            return self.buffer.sample()

        trainer.register_op("process_optim_batch", sample)
        cadence.register(trainer)
        return trainer

    def cadence(self) -> UpdateCadence:
        """The hook that logs, evaluates and stops at the wall-clock budget, from the current update on."""
        cfg = self.cfg
        return UpdateCadence(
            first=self.stepper.updates,
            updates=cfg.world_model.updates,
            log_every=cfg.logging.log_every,
            eval_every=cfg.logging.eval_every,
            evaluation=self.evaluation,
            logger=self.log,
            wall_s=self.wall_s,
            max_minutes=cfg.world_model.max_minutes,
            progress_bar=cfg.logging.progress_bar,
            desc=f"world model ({cfg.model.size}, {self.precision})",
        )

    def summary(self, *, out_of_time: bool, probe: LatentProbe | None) -> dict[str, Any]:
        """The run's ``summary.json``: its last scores, with the latent probe's on sprites (what each branch's
        state knows, on fresh episodes of the same scene, seeds never trained on)."""
        cfg, wm = self.cfg, self.cfg.world_model
        scores = dict(self.evaluation.last_scores)
        if wm.probe_episodes and _is_sprites(cfg):
            probed = probe(
                self.world_model,
                episodes=wm.probe_episodes,
                seed=cfg.train.seed + 1000,
                encoder=True,
                **probe_scene(cfg),
            )
            scores.update({f"probe_{key}": value for key, value in probed.items()})
            for key, value in probed.items():
                self.log.log_scalar(f"probe_{key}", value, step=wm.updates)
        return {
            "mode": cfg.mode,
            "algo": cfg.algo.name,
            # which learner's world model (a summary written before the mode trained the default's has none: it is
            # the DreamerV2-style learner's, whatever its algo)
            "learner": learner_name(cfg.algo.name),
            "env": cfg.env.name,
            "updates": self.stepper.updates,
            "stopped_by": "max_minutes" if out_of_time else "updates",
            "seconds": round(self.wall_s(), 1),
            "precision": self.precision,
            "size": cfg.model.size,
            "seed": cfg.train.seed,
            **{key: round(value, 3) for key, value in scores.items()},
            "png": str(self.evaluation.last_picture),
            "checkpoint": str(self.last_checkpoint),
            "logs": str(self.logs),
        }


def train(cfg: RunConfig, *, probe: LatentProbe | None = None) -> RunResult:
    """Train (or, with ``resume=true``, continue) the world model of ``cfg`` alone; see the module docstring.

    The loop is the RL run's: a TorchRL ``Trainer`` in
    :func:`~isodream_rl.trainers.run_lifecycle.train_with_checkpoints`, fed by :class:`FixedData` (no new env
    steps) and sampling windows of the episodes collected first; the stepper (the learner's, from
    :func:`world_model_builder`) has no actor and no value.

    Args:
        cfg: the run's configuration (``mode=world_model``).
        probe: the latent probe run at the end on sprites; needed there when ``world_model.probe_episodes > 0``.

    Raises:
        ConfigError: invalid configuration (before anything is built), ``resume`` with other settings, a learner
            whose world model the mode does not train (:func:`world_model_builder`), or a sprites run with
            ``world_model.probe_episodes`` and no ``probe``.
        CheckpointError: ``resume`` without a readable checkpoint.
        NonFiniteLossError: too many NaN/inf updates in a row.
    """
    started = wall_clock()
    cfg = resolved(cfg)
    _, run_dir, pictures, logs = begin_run(cfg)
    wm = cfg.world_model
    if probe is None and wm.probe_episodes and _is_sprites(cfg):
        raise ConfigError(
            f"world_model.probe_episodes={wm.probe_episodes} needs the latent probe: pass "
            "train(cfg, probe=isodream_rl.evaluation.latent_probe.probe) (isodream-train does), or set "
            "world_model.probe_episodes=0"
        )
    checkpoints = CheckpointManager(run_dir / "checkpoints", keep=cfg.checkpoint.keep)
    # the episodes are made again from the settings: a changed scene or seed would continue on other data
    state, resumed_from = (
        resume_state(cfg, checkpoints, required_keys=STATE_KEYS) if resuming(cfg) else (None, None)
    )
    run = _WorldModelRun(
        cfg, run_dir=run_dir, pictures=pictures, logs=logs, checkpoints=checkpoints, started=started
    )
    if state is not None:
        run.restore(state, resumed_from)
    write_run_config(cfg)  # the run starts: its parts are built, the config matches its checkpoint
    first = run.stepper.updates
    if first >= wm.updates:
        close_logger(run.log)
        return RunResult(run_dir, resumed_from, logs, pictures, run.env_steps, first, resumed_from)
    cadence = run.cadence()
    trainer = run.trainer(cadence)
    # a resumed run whose budget was spent before its summary: scored and checkpointed as it is
    out_of_time = run.wall_s() >= (wm.max_minutes * 60.0 if wm.max_minutes else math.inf)
    if out_of_time:
        run.evaluation.evaluate(first)
        run.save()
        stopped_by_signal = None
    else:
        stopped_by_signal = train_with_checkpoints(
            trainer, save=run.save, stepper=run.stepper, every_updates=cfg.checkpoint.every_updates
        )
        out_of_time = cadence.out_of_time
    cadence.bar.close()
    summary = None
    if stopped_by_signal is None:
        summary = run.summary(out_of_time=out_of_time, probe=probe)
        write_summary(run_dir, summary)
    close_logger(run.log)
    return RunResult(
        run_dir=run_dir,
        checkpoint=run.last_checkpoint,
        logs=logs,
        pictures=pictures,
        env_steps=run.env_steps,
        updates=run.stepper.updates,
        resumed_from=resumed_from,
        metrics=cadence.metrics,
        summary=summary,
        stopped_by_signal=stopped_by_signal,
    )
