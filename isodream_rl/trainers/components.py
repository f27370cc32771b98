"""The parts of an Iso-Dream run (any of its variants, and the DreamerV2 baseline): models, losses, optimisers,
stepper, replay buffer and the hooks whose state a checkpoint holds.

:class:`RunComponents` is also the interface other algorithms give their parts (the TorchRL baselines of
:mod:`isodream_rl.baselines` subclass it); :mod:`isodream_rl.trainers.registry` builds the one ``algo.name``
names.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torchrl.data import TensorDictReplayBuffer
from torchrl.trainers import Trainer

from isodream_rl.trainers import trainer_state
from isodream_rl.trainers.builders import (
    collector_env_suffix,
    env_label,
    make_adam,
    make_behavior,
    make_replay_buffer,
    make_world_model_loss,
)
from isodream_rl.trainers.config import RunConfig
from isodream_rl.trainers.hooks import EpisodeReturns, ReplayPreparation
from isodream_rl.trainers.run_lifecycle import run_state
from isodream_rl.trainers.saved_models import load_saved_models
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper


def make_replay_parts(
    cfg: RunConfig, *, scratch_dir: Path
) -> tuple[TensorDictReplayBuffer, ReplayPreparation, EpisodeReturns]:
    """The replay side every algorithm's run shares: the replay buffer
    (:func:`~isodream_rl.trainers.builders.make_replay_buffer`, memmap files under ``scratch_dir``), the hook that
    prepares collected batches for it (``env.num_envs`` envs, ``train.buffer_size`` split evenly between them,
    a NaN/inf an env in a worker marked refused in one line naming the env) and the episode-return hook.

    Returns:
        ``(replay_buffer, preparation, returns)``.
    """
    replay_buffer = make_replay_buffer(cfg, scratch_dir=scratch_dir)
    num_envs = cfg.env.num_envs
    preparation = ReplayPreparation(
        num_envs=num_envs,
        capacity_per_env=cfg.train.buffer_size // num_envs,
        envs=tuple(env_label(cfg) + collector_env_suffix(i, num_envs) for i in range(num_envs)),
    )
    return replay_buffer, preparation, EpisodeReturns()


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

    #: the ``algo.name`` of the run, named by :meth:`load_models` (this class serves Iso-Dream's DreamerV2-style
    #: variants and ``algo=dreamerv2``; a subclass registered under one name sets it on the class)
    algo: str

    def __init__(self, cfg: RunConfig, *, action_dim: int, scratch_dir: Path) -> None:
        train = cfg.train
        self.algo = cfg.algo.name
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
        self.replay_buffer, self.preparation, self.returns = make_replay_parts(cfg, scratch_dir=scratch_dir)

    def modules(self) -> dict[str, torch.nn.Module]:
        return {
            "world_model": self.world_model,
            "actor_loss": self.behavior.actor_loss,
            "value_loss": self.behavior.value_loss,
        }

    def state(
        self, cfg: RunConfig, *, env_steps: int, trainer: Trainer | None, evaluation=None, wall_s: float = 0.0
    ) -> dict:
        """The run's checkpoint state (:func:`~isodream_rl.trainers.run_lifecycle.run_state`)."""
        return run_state(
            cfg,
            models=self.modules(),
            stepper=self.stepper,
            counters={
                "env_steps": env_steps,
                "wall_s": wall_s,
                "optim_count": trainer_state.optim_count(trainer) if trainer is not None else 0,
                "last_log": trainer_state.log_marks(trainer) if trainer is not None else {},
            },
            hooks={
                "preparation": self.preparation.state_dict(),
                "returns": self.returns.state_dict(),
                "evaluation": evaluation.state_dict() if evaluation is not None else None,
            },
        )

    def load_models(self, state: dict, *, checkpoint: str | Path = "the checkpoint") -> None:
        """Load the weights saved by :meth:`state` (checkpoint key ``"models"``).

        Args:
            state: the checkpoint's state.
            checkpoint: the checkpoint's folder (or words naming it), named by the error.

        Raises:
            CheckpointMismatchError: the weights do not fit :meth:`modules` (another algorithm's, other widths, a
                run saved by ``algo=isodream`` when it was the DreamerV2-style learner): one line naming
                ``checkpoint``, the models and what to change
                (:func:`~isodream_rl.trainers.saved_models.check_saved_models`).
        """
        load_saved_models(self.modules(), state, algo=self.algo, checkpoint=checkpoint)
