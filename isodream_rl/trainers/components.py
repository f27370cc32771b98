"""The interface of a run's parts, :class:`RunComponents` (models, losses, optimisers, stepper, replay buffer and the
hooks whose state a checkpoint holds), the replay side every algorithm's run shares (:func:`make_replay_parts`), and
what ``mode=world_model`` trains of a learner, :class:`WorldModelAlone`.

Each learner gives its parts this interface: the default's :class:`~isodream_rl.trainers.isodream.IsoDreamComponents`,
the DreamerV2-style learner's :class:`~isodream_rl.trainers.isodream_v2.IsoDreamV2Components`, the TorchRL baselines'
(:mod:`isodream_rl.baselines`); :mod:`isodream_rl.trainers.registry` builds the one ``algo.name`` names. Iso-Dream's
two learners give their world model alone too (``make_world_model_alone`` in :mod:`~isodream_rl.trainers.isodream`
and :mod:`~isodream_rl.trainers.isodream_v2`), which :mod:`isodream_rl.trainers.world_model_run` trains.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torchrl.data import TensorDictReplayBuffer
from torchrl.trainers import Trainer

from isodream_rl.trainers import trainer_state
from isodream_rl.trainers.builders import collector_env_suffix, env_label, make_replay_buffer
from isodream_rl.trainers.config import RunConfig
from isodream_rl.trainers.hooks import EpisodeReturns, ReplayPreparation
from isodream_rl.trainers.run_lifecycle import run_state
from isodream_rl.trainers.saved_models import load_saved_models
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper


@dataclass
class WorldModelAlone:
    """What ``mode=world_model`` trains of a learner (:mod:`isodream_rl.trainers.world_model_run`): its world model,
    the loss of the world model alone and the stepper of that loss (no actor, no value).

    Attributes:
        world_model: the world model (``[B, T]`` window -> its output, the branches' images and masks under
            ``"next"``).
        model_loss: its loss, ``td -> (losses, model_out)``, with ``loss_model_reco`` among the losses.
        stepper: the update of the world model alone (its learner's optimiser), an
            :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper` with the one optimiser ``"world_model"``.
        precision: the world model's compute precision, as ``summary.json`` names it (``"fp32"``, ``"bf16"``).
    """

    world_model: torch.nn.Module
    model_loss: torch.nn.Module
    stepper: IsoDreamOptimizationStepper
    precision: str


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
    """Models, losses, optimisers, stepper and replay buffer of a run (everything a checkpoint holds): the interface
    a learner's parts give the run. A subclass builds them in ``__init__(cfg, *, action_dim, scratch_dir)`` and names
    its checkpoint's models in :meth:`modules`.

    Attributes:
        model_loss, world_model (``None`` where the evaluation has no open-loop prediction), behavior (with
        ``policy``), stepper (an :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`), replay_buffer,
        preparation, returns (the replay and episode-return hooks).
    """

    #: the ``algo.name`` of the run, named by :meth:`load_models` (set by ``__init__``, or on the class by a subclass
    #: registered under one name)
    algo: str

    def modules(self) -> dict[str, torch.nn.Module]:
        """The trained modules (and any other state a checkpoint holds), by checkpoint name."""
        raise NotImplementedError(f"{type(self).__name__} must define modules(): its checkpoint's models")

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
