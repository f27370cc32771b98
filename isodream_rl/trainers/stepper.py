"""One Iso-Dream update (Algorithm 1, lines 3-13) as a TorchRL ``OptimizationStepper``: three optimisers.

TorchRL's ``DefaultOptimizationStepper`` sums every ``loss_*`` entry into one backward pass through one
optimiser; Iso-Dream needs three (world model; actor; value + attention), each stepped on its own loss, with
the world-model output feeding imagination, so the stepper is written here.

:class:`ZeroStateStepper` is the base of the steppers whose loss rolls a TorchRL RSSM over replay windows (the
baselines', DreamerV3's in :mod:`isodream_rl.trainers.dreamer_v3`): zero root ``state``/``belief`` added.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.trainers import OptimizationStepper

logger = logging.getLogger(__name__)


class NonFiniteLossError(RuntimeError):
    """Raised after ``max_nonfinite`` updates in a row had a NaN/inf loss or gradient."""


def loss_sum(losses: TensorDictBase) -> torch.Tensor:
    """The sum of a loss module's ``loss_*`` entries (the diagnostics beside them are left out)."""
    return sum(value for key, value in losses.items() if key.startswith("loss"))


class IsoDreamOptimizationStepper(OptimizationStepper):
    """World-model, actor and value updates on one replay batch, with NaN/inf update skipping.

    Per call of :meth:`step` (one update):

    1. the flat replay sample ``[B * T]`` (stored on the CPU) moves to the model's device (:attr:`device`), the
       one place an update moves it, becomes the loss's input (:meth:`prepare`) and is reshaped to windows
       ``[B, T]``;
    2. the world-model loss (eq. 5) is backpropagated and its optimiser stepped;
    3. ``actor_loss(model_output)`` imagines from the detached posteriors (eq. 7) and ``value_loss`` regresses
       the value on the returned rollout; both losses are backpropagated (their sum) before the actor and the
       value + attention optimisers step, so that with ``attention_through_actor=True`` the actor loss's
       gradient on the attention is kept and added to the value loss's;
    4. the slow value target is updated (``target_updater.step()``, a TorchRL ``TargetNetUpdater``).

    Each optimiser's parameters are clipped to a gradient norm of ``grad_clip``. An update whose loss or
    gradient norm is not finite is skipped (no optimiser of that update steps after the fault; the skip is
    logged as ``nonfinite_skipped``); ``max_nonfinite`` of them in a row raise :class:`NonFiniteLossError`.

    Args:
        model_loss: an :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ModelLoss` (``td -> (losses, model_out)``).
        world_model_optimizer: optimiser of the world-model parameters.
        sequence_length: T, the replay window length.
        actor_loss: :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ActorLoss` (``model_out -> (losses, imagined)``),
            or ``None`` to train the world model only.
        value_loss: :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ValueLoss` (``imagined -> (losses, _)``).
        actor_optimizer: optimiser of the actor.
        value_optimizer: optimiser of the value network and attention.
        target_updater: object with ``step()`` updating the slow value target, or ``None``.
        grad_clip: max gradient norm per optimiser.
        max_nonfinite: K, consecutive non-finite updates that stop the run.
        world_model_warmup: updates of the world model alone before the actor and value start learning
            (their losses are logged as NaN until then). An actor trained on an untrained world model
            follows its errors and saturates its actions before the reward is learnt; 0 as the authors.
    """

    def __init__(
        self,
        *,
        model_loss: nn.Module,
        world_model_optimizer: torch.optim.Optimizer,
        sequence_length: int,
        actor_loss: nn.Module | None = None,
        value_loss: nn.Module | None = None,
        actor_optimizer: torch.optim.Optimizer | None = None,
        value_optimizer: torch.optim.Optimizer | None = None,
        target_updater=None,
        grad_clip: float = 100.0,
        max_nonfinite: int = 5,
        world_model_warmup: int = 0,
    ) -> None:
        behavior = (actor_loss, value_loss, actor_optimizer, value_optimizer)
        if any(x is None for x in behavior) and any(x is not None for x in behavior):
            raise ValueError(
                "actor_loss, value_loss, actor_optimizer and value_optimizer go together: give all four or none"
            )
        if max_nonfinite < 1:
            raise ValueError(f"max_nonfinite must be >= 1, got {max_nonfinite}")
        if world_model_warmup < 0:
            raise ValueError(f"world_model_warmup must be >= 0, got {world_model_warmup}")
        self.model_loss = model_loss
        self.actor_loss, self.value_loss = actor_loss, value_loss
        self.optimizers = {"world_model": world_model_optimizer}
        if actor_loss is not None:
            self.optimizers.update(actor=actor_optimizer, value=value_optimizer)
        self.target_updater = target_updater
        self.sequence_length = sequence_length
        self.grad_clip = grad_clip
        self.max_nonfinite = max_nonfinite
        self.world_model_warmup = world_model_warmup
        self.updates = 0
        self.nonfinite_in_a_row = 0
        self.nonfinite_total = 0
        self._metric_keys: list[str] = []

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict:
        return {
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
            "updates": self.updates,
            "nonfinite_in_a_row": self.nonfinite_in_a_row,
            "nonfinite_total": self.nonfinite_total,
        }

    def load_state_dict(self, state_dict: dict) -> None:
        missing = set(self.optimizers) - set(state_dict["optimizers"])
        if missing:
            raise KeyError(f"checkpoint has no optimiser state for {sorted(missing)}")
        for name, opt in self.optimizers.items():
            opt.load_state_dict(state_dict["optimizers"][name])
        self.updates = state_dict["updates"]
        self.nonfinite_in_a_row = state_dict["nonfinite_in_a_row"]
        self.nonfinite_total = state_dict["nonfinite_total"]

    # ------------------------------------------------------------------ one update
    def _params(self, name: str) -> list[torch.Tensor]:
        return [p for group in self.optimizers[name].param_groups for p in group["params"]]

    @property
    def device(self) -> torch.device:
        """The model's device (the world-model loss's parameters'), where :meth:`step` moves each replay sample:
        read at every update, so that a model moved after the stepper was built takes its samples along."""
        return next(self.model_loss.parameters()).device

    def prepare(self, sample: TensorDictBase) -> TensorDictBase:
        """The loss's input from a flat ``[N]`` replay sample already on :attr:`device`: the sample itself here; a
        subclass whose loss reads other keys or dtypes returns them (without moving anything)."""
        return sample

    def _backward(self, loss: torch.Tensor, names: Sequence[str]) -> bool:
        """Zero the grads of optimisers ``names`` and backpropagate ``loss``; ``False`` if it is not finite."""
        for name in names:
            self.optimizers[name].zero_grad(set_to_none=True)
        if not torch.isfinite(loss):
            return False
        loss.backward()
        return True

    def _clip_and_step(self, names: Sequence[str], metrics: dict[str, torch.Tensor]) -> bool:
        """Clip each optimiser's gradient and step them all, or none if any norm is not finite."""
        for name in names:
            norm = nn.utils.clip_grad_norm_(self._params(name), self.grad_clip)
            metrics[f"grad_norm_{name}"] = norm.detach()
            if not torch.isfinite(norm):
                return False
        for name in names:
            self.optimizers[name].step()
        return True

    def _run(self, batch: TensorDictBase, metrics: dict[str, torch.Tensor]) -> bool:
        losses, model_out = self.model_loss(batch)
        metrics.update({k: v.detach() for k, v in losses.items()})
        if not self._backward(loss_sum(losses), ["world_model"]):
            return False
        if not self._clip_and_step(["world_model"], metrics):
            return False
        if self.actor_loss is None or self.updates < self.world_model_warmup:
            return True
        actor_losses, imagined = self.actor_loss(model_out)
        metrics.update({k: v.detach() for k, v in actor_losses.items()})
        value_losses, _ = self.value_loss(imagined)
        metrics.update({k: v.detach() for k, v in value_losses.items()})
        # Both backward passes run before either step: with ``attention_through_actor`` the actor loss's
        # gradient reaches the attention, which the value optimiser steps, so its grads must not be zeroed
        # between the two passes. The world model is held out of the actor loss and the rollout given to the
        # value loss is detached, so nothing else is shared.
        behavior = ["actor", "value"]
        total = loss_sum(actor_losses) + loss_sum(value_losses)
        if not self._backward(total, behavior):
            return False
        return self._clip_and_step(behavior, metrics)

    def step(self, trainer, sub_batch: TensorDictBase) -> TensorDictBase:
        """One update on a flat ``[B * T]`` replay sample; returns detached scalar metrics."""
        if sub_batch.numel() % self.sequence_length:
            raise ValueError(
                f"the replay sample has {sub_batch.numel()} steps, not a multiple of the window length "
                f"{self.sequence_length}; sample with SliceSampler(slice_len={self.sequence_length}, "
                "strict_length=True)"
            )
        # the one place a replay sample changes device: the replay stays on the CPU, the model may not
        batch = self.prepare(sub_batch.reshape(-1).to(self.device)).reshape(-1, self.sequence_length)
        if not self._metric_keys:
            # on a forked generator: a resumed stepper discovers its keys again, and the updates that follow
            # must draw the same numbers as those of the run it continues
            device = self.device
            with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
                self._discover_keys(batch[:1, : min(2, self.sequence_length)].clone())
        metrics: dict[str, torch.Tensor] = {}
        finite = self._run(batch, metrics)
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        if finite:
            self.nonfinite_in_a_row = 0
            self.updates += 1
            if self.target_updater is not None:
                self.target_updater.step()
        else:
            self.nonfinite_in_a_row += 1
            self.nonfinite_total += 1
            logger.warning(
                "non-finite loss or gradient: update skipped (%d in a row, limit %d)",
                self.nonfinite_in_a_row,
                self.max_nonfinite,
            )
            if self.nonfinite_in_a_row >= self.max_nonfinite:
                raise NonFiniteLossError(
                    f"{self.nonfinite_in_a_row} updates in a row had a NaN/inf loss or gradient "
                    f"(train.max_nonfinite_updates={self.max_nonfinite}); the last losses were "
                    f"{ {k: float(v) for k, v in metrics.items() if k.startswith('loss')} }. Lower the "
                    "learning rates (train.world_model_lr, train.actor_lr, train.value_lr) or check the "
                    "env's rewards for NaN/inf"
                )
        metrics["nonfinite_skipped"] = torch.tensor(float(not finite))
        return self._complete(metrics)

    @torch.no_grad()
    def _discover_keys(self, batch: TensorDictBase) -> None:
        """The metric names of a full update, from the losses on a ``[1, 2]`` slice of the first batch.

        The Trainer averages the metrics of the updates of a batch key by key, starting from the first
        update's keys, so every update must return the same keys, a skipped one included. :meth:`step` runs it
        on a forked random generator, so that it draws nothing from the run's.
        """
        losses, model_out = self.model_loss(batch)
        keys = [*losses.keys(), "grad_norm_world_model"]
        if self.actor_loss is not None:
            actor_losses, imagined = self.actor_loss(model_out)
            value_losses, _ = self.value_loss(imagined)
            keys += [*actor_losses.keys(), "grad_norm_actor", *value_losses.keys(), "grad_norm_value"]
        self._metric_keys = [*keys, "nonfinite_skipped"]

    def _complete(self, metrics: dict[str, torch.Tensor]) -> TensorDictBase:
        """The metrics under the fixed key set; those an update did not reach (skipped early) are NaN."""
        nan = torch.tensor(math.nan)
        return TensorDict({k: metrics.get(k, nan).float().reshape(()) for k in self._metric_keys}, [])


def parameters_of(*modules: nn.Module | None) -> Sequence[nn.Parameter]:
    """The unique parameters of ``modules`` (``None`` entries skipped), in order."""
    seen: dict[int, nn.Parameter] = {}
    for module in modules:
        if module is not None:
            for p in module.parameters():
                seen.setdefault(id(p), p)
    return list(seen.values())


class ZeroStateStepper(IsoDreamOptimizationStepper):
    """An :class:`IsoDreamOptimizationStepper` whose :meth:`step` updates on :meth:`prepare`'s output: the loss's
    input (:meth:`loss_inputs`) of the flat ``[B * T]`` replay sample, moved to the model's device first, with zero
    root ``"state"`` ``[N, S]`` / ``"belief"`` ``[N, D]`` (a rollout reads each window's first step, as TorchRL's
    examples set them).

    Args:
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        **stepper_kwargs: the arguments of :class:`IsoDreamOptimizationStepper`.
    """

    def __init__(self, *, state_dim: int, belief_dim: int, **stepper_kwargs) -> None:
        super().__init__(**stepper_kwargs)
        self.state_dim, self.belief_dim = state_dim, belief_dim

    def loss_inputs(self, sub_batch: TensorDictBase) -> TensorDictBase:
        """The entries of a flat ``[N]`` replay sample the loss reads, as it reads them (a new tensordict)."""
        raise NotImplementedError(f"{type(self).__name__} must define loss_inputs(): what its loss reads")

    def prepare(self, sample: TensorDictBase) -> TensorDictBase:
        """:meth:`loss_inputs` of a flat ``[N]`` replay sample on the model's device, zero ``"state"``/``"belief"``
        added on the same device."""
        n = sample.numel()
        batch = self.loss_inputs(sample)
        batch.set("state", torch.zeros(n, self.state_dim, device=sample.device))
        batch.set("belief", torch.zeros(n, self.belief_dim, device=sample.device))
        return batch
