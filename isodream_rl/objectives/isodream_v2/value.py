"""The value loss of eq. 7 (DreamerV2 critic) and its slow target network."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.utils import NestedKey
from torchrl.objectives import HardUpdate, LossModule, SoftUpdate
from torchrl.objectives.utils import TargetNetUpdater

from isodream_rl.modules.isodream_v2.value import IsoDreamV2Value
from isodream_rl.objectives.isodream_v2.imagination import IsoDreamV2Imagination, policy_features


class IsoDreamV2ValueLoss(LossModule):
    """Regresses ``v_xi(e_j)`` on the detached lambda-returns of an imagined rollout (eq. 7).

    ``L_value = mean_{N, j} w_j * 0.5 * (v_xi(e_j) - sg(G^lambda_j))^2``, i.e. ``-log N(G; v, 1)`` up to a
    constant, with ``w_j`` the detached ``cumprod(gamma * continuation)`` weights. ``G^lambda_j`` and ``w_j``
    come from :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ActorLoss`, which writes them into the imagined rollout,
    and are aligned with the state they value: ``G_j`` is the return from ``s~_j`` (TorchRL's convention; the
    authors' code regresses on time-reversed targets).

    ``e_j`` is recomputed here from the detached ``[s, h]`` (and window), so the policy input's parameters
    (the future-state attention) learn from this loss, as in the authors' code: ``value_loss.parameters()``
    is the "value + attention" parameter group.

    The loss also owns the slow value target (TorchRL ``target_value_network_params``) that the actor loss
    uses for its returns; refresh it with :func:`make_target_updater` (a hard copy every 100 updates by
    default).

    Args:
        value_network: an :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2Value`.
        imagination: the :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2Imagination` whose rollouts are regressed;
            its policy input is registered here (trained by this loss), its world model is not.
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read and written by the loss; remap with :meth:`set_keys`.

        Attributes:
            lambda_target: the lambda-returns ``[N, L, 1]``. Defaults to ``"lambda_target"``.
            discount_weight: the weights ``w_j`` ``[N, L, 1]``. Defaults to ``"discount_weight"``.
            value: where the predicted values are written. Defaults to ``"state_value"``.
        """

        lambda_target: NestedKey = "lambda_target"
        discount_weight: NestedKey = "discount_weight"
        value: NestedKey = "state_value"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    value_network: IsoDreamV2Value
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(self, value_network: IsoDreamV2Value, imagination: IsoDreamV2Imagination):
        super().__init__()
        policy_input = imagination.policy_input
        if value_network.in_features != policy_input.out_features:
            raise ValueError(
                f"the value network reads {value_network.in_features} features, the policy input gives "
                f"{policy_input.out_features}"
            )
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        self.policy_input = policy_input
        # Not a submodule: the world model's parameters are no part of this loss.
        self.__dict__["imagination"] = imagination

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def target_value(self, features: torch.Tensor) -> torch.Tensor:
        """The slow value target ``[*N, 1]`` at ``features``; no gradient reaches its parameters (buffers)."""
        with self.target_value_network_params.to_module(self.value_network, preserve_module_state=False):
            return self.value_network(features)

    def forward(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        keys = self.tensor_keys
        target = tensordict.get(keys.lambda_target, None)
        weight = tensordict.get(keys.discount_weight, None)
        if target is None or weight is None:
            raise KeyError(
                f"IsoDreamV2ValueLoss reads {keys.lambda_target!r} and {keys.discount_weight!r}, written by "
                "IsoDreamV2ActorLoss into the imagined rollout it returns; pass that rollout"
            )
        with self.imagination.autocast(target.device.type):
            value = self.value_network(policy_features(self.policy_input, tensordict, detach_control=True))
        loss = (weight.detach() * 0.5 * (value - target.detach()).pow(2)).mean()
        tensordict.set(keys.value, value.detach())
        losses = TensorDict({"loss_value": loss, "value_mean": value.detach().mean()}, [])
        return losses, tensordict


def make_target_updater(
    value_loss: IsoDreamV2ValueLoss, *, period: int = 100, tau: float | None = None
) -> TargetNetUpdater:
    """TorchRL target updater for the slow value network of ``value_loss``.

    Args:
        value_loss: the loss owning the target parameters.
        period: with ``tau=None``, a hard copy every ``period`` calls of ``updater.step()`` (the authors' 100).
            TorchRL's ``HardUpdate`` copies on the ``(interval + 1)``-th call, hence ``interval = period - 1``.
        tau: if given, a ``SoftUpdate`` ``target <- (1 - tau) target + tau source`` at every call instead.

    Call ``updater.step()`` once per value update.
    """
    if tau is not None:
        if not 0.0 < tau <= 1.0:
            raise ValueError(f"tau must be in (0, 1], got {tau}")
        return SoftUpdate(value_loss, tau=tau)
    if period < 1:
        raise ValueError(f"period must be >= 1, got {period}")
    return HardUpdate(value_loss, value_network_update_interval=period - 1)
