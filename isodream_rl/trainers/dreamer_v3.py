"""DreamerV3's update as the run's stepper, and its optimisers: one per parameter group.

- :class:`DreamerV3OptimizationStepper`: TorchRL's ``DreamerV3OptimizationStepper`` (one backward of the sum of a
  ``DreamerV3Loss``'s ``loss_*`` terms, each group's ``DreamerV3Optimizer``, the slow critic's ``SoftUpdate``)
  with what the run's hooks and checkpoints read, which TorchRL's lacks: skipping of non-finite updates, an update
  counter and fixed metric keys (those of :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`).
- :class:`DreamerV3WorldModelStepper`: the same update of the world model alone (``mode=world_model`` of the
  default, :func:`make_dreamer_v3_world_model_stepper`): its loss, its ``DreamerV3Optimizer``, no actor, no critic.
- :func:`make_dreamer_v3_optimizers`: a ``DreamerV3Optimizer`` (adaptive gradient clipping, RMS-scaled momentum,
  linear warm-up) per parameter group. TorchRL's optimiser keeps one update counter per group and is otherwise
  per parameter, so these are the update of one optimiser with three groups, and they let the world model train
  alone during ``train.world_model_warmup`` while the actor's and value's counters (bias correction, learning-rate
  warm-up) start when they do.

Both ``algo=torchrl_dreamer_v3`` (:mod:`isodream_rl.baselines.torchrl_dreamer_v3`) and Iso-Dream's DreamerV3
learner use them.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Protocol

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import DreamerV3ActorLoss, DreamerV3Loss, DreamerV3ModelLoss, DreamerV3ValueLoss
from torchrl.objectives.utils import SoftUpdate
from torchrl.trainers.algorithms import DreamerV3Optimizer

from isodream_rl.modules.dreamer_v3 import PIXELS, DreamerV3Settings
from isodream_rl.trainers.config import RunConfig
from isodream_rl.trainers.stepper import ZeroStateStepper, loss_sum

#: The parameter groups, each with its own optimiser and learning rate.
GROUPS = ("world_model", "actor", "value")
#: What ``DreamerV3ModelLoss`` (and so ``DreamerV3Loss``) reads of a replay sample, besides the zero root
#: ``"state"`` / ``"belief"`` the steppers add: ``"action"``, ``"is_init"``, ``("next", "pixels")`` (as stored,
#: uint8), ``("next", "reward")``, ``("next", "done")``, ``("next", "terminated")``.
LOSS_INPUTS = ("action", "is_init", PIXELS, ("next", "reward"), ("next", "done"), ("next", "terminated"))


def make_dreamer_v3_optimizers(
    parameter_groups: dict[str, list[nn.Parameter]], *, rates: dict[str, float], settings: DreamerV3Settings
) -> dict[str, DreamerV3Optimizer]:
    """A ``DreamerV3Optimizer`` per parameter group, at ``rates[group]``, with the clipping (``settings.agc``),
    epsilon (``settings.optimizer_eps``) and learning-rate warm-up (``settings.lr_warmup``) of ``settings``.

    Args:
        parameter_groups: the trained parameters by group, e.g. ``{"world_model": [...], "actor": [...],
            "value": [...]}`` (:data:`GROUPS`).
        rates: the learning rate of each group.
        settings: DreamerV3's settings (:class:`~isodream_rl.modules.dreamer_v3.DreamerV3Settings`).

    Returns:
        ``{group: DreamerV3Optimizer}``, in ``parameter_groups``' order.

    Raises:
        KeyError: a group without a rate.
    """
    missing = sorted(set(parameter_groups) - set(rates))
    if missing:
        raise KeyError(f"no learning rate for the parameter groups {missing}; rates has {sorted(rates)}")
    return {
        name: DreamerV3Optimizer(
            params,
            lr=rates[name],
            agc=settings.agc,
            eps=settings.optimizer_eps,
            warmup_steps=settings.lr_warmup,
        )
        for name, params in parameter_groups.items()
    }


class DreamerV3OptimizationStepper(ZeroStateStepper):
    """One DreamerV3 update (TorchRL's ``DreamerV3OptimizationStepper``'s, eager) as the run's stepper, for any
    ``DreamerV3Loss`` whose parameters form the groups ``world_model``, ``actor``, ``value`` (:data:`GROUPS`).

    Per :meth:`step` on a flat ``[B * T]`` replay sample, moved to the model's device: :meth:`prepare` (zero root
    ``"state"``/``"belief"``, as TorchRL's reproduction sets them: a
    :class:`~isodream_rl.trainers.stepper.ZeroStateStepper`), windows ``[B, T]``, then ``DreamerV3Loss`` (world
    model, imagination from every posterior, actor, critic, replay critic), one backward of the sum of its
    ``loss_*`` terms, one step of each ``DreamerV3Optimizer`` and of the slow critic's ``SoftUpdate``. During the
    first ``world_model_warmup`` updates only ``DreamerV3ModelLoss`` runs and only the world model's optimiser
    steps (the other terms are logged as NaN).

    An update whose loss or gradient norm (``grad_norm_<group>``, logged before the optimiser's own adaptive
    clipping: no other clipping) is not finite is skipped; ``max_nonfinite`` in a row raise. Counters, metric
    keys and checkpoint state are those of :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`;
    the return normalisation's statistics are module buffers, checkpointed with the models.

    Args:
        loss_module: ``DreamerV3Loss``.
        optimizers: a ``DreamerV3Optimizer`` per parameter group: ``"world_model"``, ``"actor"``, ``"value"``
            (:func:`make_dreamer_v3_optimizers`).
        target_updater: the slow critic's ``SoftUpdate``.
        sequence_length: T, the replay window length.
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        max_nonfinite: non-finite updates in a row that stop the run.
        world_model_warmup: updates of the world model alone first.
    """

    def __init__(
        self,
        *,
        loss_module: DreamerV3Loss,
        optimizers: dict[str, torch.optim.Optimizer],
        target_updater: SoftUpdate,
        sequence_length: int,
        state_dim: int,
        belief_dim: int,
        max_nonfinite: int = 5,
        world_model_warmup: int = 0,
    ) -> None:
        if set(optimizers) != set(GROUPS):
            raise ValueError(f"optimizers must be keyed {list(GROUPS)}, got {sorted(optimizers)}")
        super().__init__(
            model_loss=loss_module.model_loss,
            world_model_optimizer=optimizers["world_model"],
            sequence_length=sequence_length,
            target_updater=target_updater,
            grad_clip=math.inf,
            max_nonfinite=max_nonfinite,
            world_model_warmup=world_model_warmup,
            state_dim=state_dim,
            belief_dim=belief_dim,
        )
        self.optimizers = {name: optimizers[name] for name in GROUPS}
        self.loss_module = loss_module

    def loss_inputs(self, sub_batch: TensorDictBase) -> TensorDictBase:
        """What ``DreamerV3Loss`` reads of a flat ``[N]`` replay sample, :data:`LOSS_INPUTS` (:meth:`prepare` adds
        zero ``"state"`` / ``"belief"``: the rollout reads each window's first step)."""
        return sub_batch.select(*LOSS_INPUTS, strict=False)

    def _losses(self, batch: TensorDictBase, *, world_model_only: bool) -> TensorDictBase:
        if world_model_only:
            losses, _ = self.loss_module.model_loss(batch)
            return losses.apply(torch.squeeze)
        losses = self.loss_module(batch)
        return losses.exclude(self.loss_module.tensor_keys.replay_context)

    @torch.no_grad()
    def _discover_keys(self, batch: TensorDictBase) -> None:
        """The metric names of a full update, from the loss on a ``[1, 2]`` slice of the first batch; the return
        normalisation's statistics it moves are put back, so that a resumed run continues exactly."""
        saved = [(buffer, buffer.clone()) for buffer in self.loss_module.buffers()]
        try:
            keys = list(self._losses(batch, world_model_only=False).keys())
        finally:
            for buffer, value in saved:
                buffer.copy_(value)
        self._metric_keys = [*keys, *(f"grad_norm_{name}" for name in GROUPS), "nonfinite_skipped"]

    def _run(self, batch: TensorDictBase, metrics: dict[str, torch.Tensor]) -> bool:
        warming_up = self.updates < self.world_model_warmup
        losses = self._losses(batch, world_model_only=warming_up)
        metrics.update({k: v.detach() for k, v in losses.items()})
        # grad_clip is inf: _clip_and_step only measures the norms, TorchRL's optimiser clips
        stepped = ["world_model"] if warming_up else list(GROUPS)
        return self._backward(loss_sum(losses), list(GROUPS)) and self._clip_and_step(stepped, metrics)


class DreamerV3WorldModelStepper(ZeroStateStepper):
    """DreamerV3's update of the world model alone, as the stepper of ``mode=world_model``: what
    :class:`DreamerV3OptimizationStepper` does during ``train.world_model_warmup``, without an actor or a critic.

    Per :meth:`step` on a flat ``[B * T]`` replay sample, moved to the model's device: :meth:`prepare`
    (:data:`LOSS_INPUTS` with zero root ``"state"`` ``[N, S]`` / ``"belief"`` ``[N, D]``), windows ``[B, T]``, the
    world model's ``DreamerV3ModelLoss`` (with its terms ``[1]`` each), one backward of the sum of its ``loss_*``
    terms and one step of the world model's ``DreamerV3Optimizer`` (its adaptive gradient clipping is the only
    clipping: ``grad_norm_world_model`` is logged before it). Skipping of non-finite updates, counters, metric keys
    and checkpoint state are those of :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper` with one
    optimiser, ``"world_model"``.

    Args:
        model_loss: the world model's ``DreamerV3ModelLoss`` (``td -> (losses, model_out)``), e.g.
            :class:`~isodream_rl.objectives.isodream.IsoDreamModelLoss`.
        optimizer: the world model's ``DreamerV3Optimizer`` (:func:`make_dreamer_v3_optimizers`' ``"world_model"``).
        sequence_length: T, the replay window length.
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        max_nonfinite: non-finite updates in a row that stop the run.
    """

    def __init__(
        self,
        *,
        model_loss: DreamerV3ModelLoss,
        optimizer: torch.optim.Optimizer,
        sequence_length: int,
        state_dim: int,
        belief_dim: int,
        max_nonfinite: int = 5,
    ) -> None:
        super().__init__(
            model_loss=model_loss,
            world_model_optimizer=optimizer,
            sequence_length=sequence_length,
            grad_clip=math.inf,
            max_nonfinite=max_nonfinite,
            state_dim=state_dim,
            belief_dim=belief_dim,
        )

    def loss_inputs(self, sub_batch: TensorDictBase) -> TensorDictBase:
        """What ``DreamerV3ModelLoss`` reads of a flat ``[N]`` replay sample, :data:`LOSS_INPUTS`."""
        return sub_batch.select(*LOSS_INPUTS, strict=False)


class DreamerV3Learner(Protocol):
    """What a DreamerV3 learner gives its run: the modules and losses its stepper and checkpoints read."""

    world_model: nn.Module
    actor: nn.Module
    actor_loss: DreamerV3ActorLoss
    value_loss: DreamerV3ValueLoss
    loss_module: DreamerV3Loss
    target_updater: SoftUpdate

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]: ...


def run_optimizers(
    cfg: RunConfig, parameter_groups: dict[str, list[nn.Parameter]], *, settings: DreamerV3Settings
) -> dict[str, DreamerV3Optimizer]:
    """The run's :func:`make_dreamer_v3_optimizers`: each group of ``parameter_groups`` (:data:`GROUPS`, or some of
    them) at its rate, ``train.world_model_lr`` / ``actor_lr`` / ``value_lr``, with ``train.lr_warmup`` in place of
    ``settings.lr_warmup`` where set."""
    train = cfg.train
    if train.lr_warmup is not None:
        settings = dataclasses.replace(settings, lr_warmup=train.lr_warmup)
    rates = {"world_model": train.world_model_lr, "actor": train.actor_lr, "value": train.value_lr}
    return make_dreamer_v3_optimizers(parameter_groups, rates=rates, settings=settings)


def make_dreamer_v3_stepper(
    cfg: RunConfig,
    learner: DreamerV3Learner,
    *,
    state_dim: int,
    belief_dim: int,
    settings: DreamerV3Settings,
) -> DreamerV3OptimizationStepper:
    """The run's DreamerV3 update for ``learner``: :func:`make_dreamer_v3_optimizers` at ``train.world_model_lr`` /
    ``actor_lr`` / ``value_lr``, the slow critic's updater, ``train.sequence_length``, ``max_nonfinite_updates``,
    ``world_model_warmup``, ``lr_warmup`` (in place of ``settings.lr_warmup`` where set); ``state_dim`` /
    ``belief_dim`` are the widths of the latent the losses read
    (:class:`~isodream_rl.trainers.stepper.ZeroStateStepper` zeroes them at each window's start)."""
    train = cfg.train
    return DreamerV3OptimizationStepper(
        loss_module=learner.loss_module,
        optimizers=run_optimizers(cfg, learner.parameter_groups(), settings=settings),
        target_updater=learner.target_updater,
        sequence_length=train.sequence_length,
        state_dim=state_dim,
        belief_dim=belief_dim,
        max_nonfinite=train.max_nonfinite_updates,
        world_model_warmup=train.world_model_warmup,
    )


def make_dreamer_v3_world_model_stepper(
    cfg: RunConfig,
    model_loss: DreamerV3ModelLoss,
    world_model: nn.Module,
    *,
    state_dim: int,
    belief_dim: int,
    settings: DreamerV3Settings,
) -> DreamerV3WorldModelStepper:
    """DreamerV3's update of ``world_model`` alone (``mode=world_model``): the ``"world_model"`` optimiser of
    :func:`run_optimizers` (``train.world_model_lr``, ``lr_warmup``: the one a run of the learner gives its world
    model) over ``world_model``'s parameters, ``model_loss`` on windows of ``train.sequence_length``,
    ``max_nonfinite_updates``; ``state_dim`` / ``belief_dim`` as :func:`make_dreamer_v3_stepper`'s."""
    optimizers = run_optimizers(cfg, {"world_model": list(world_model.parameters())}, settings=settings)
    return DreamerV3WorldModelStepper(
        model_loss=model_loss,
        optimizer=optimizers["world_model"],
        sequence_length=cfg.train.sequence_length,
        state_dim=state_dim,
        belief_dim=belief_dim,
        max_nonfinite=cfg.train.max_nonfinite_updates,
    )


def dreamer_v3_checkpoint_modules(learner: DreamerV3Learner) -> dict[str, nn.Module]:
    """The trained modules of a DreamerV3 learner and the return normalisation's statistics, by checkpoint name
    (imagination, the losses and the policy share them)."""
    return {
        "world_model": learner.world_model,
        "actor": learner.actor,
        "value_loss": learner.value_loss,
        "return_norm": learner.actor_loss.retnorm,
    }
