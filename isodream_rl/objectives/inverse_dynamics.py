"""Inverse-dynamics loss: the action term ``alpha * l2(a_t, a~_t)`` of the world-model loss (paper eq. 5)."""

from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

INVERSE_LOSSES = ("gaussian", "l2")


class InverseDynamicsLoss(LossModule):
    """Regress the true action ``a_t`` from the inverse-dynamics cell's prediction ``a~_t``.

    The prediction is made by :class:`~isodream_rl.modules.InverseDynamicsCell` inside the world model
    from consecutive controllable posteriors (or embeddings), so this loss's gradient reaches the
    controllable branch and the shared encoder and nothing of the noncontrollable branch.

    Args:
        lambda_inverse: a scale on the term; the default 1 gives the plain log-loss. It is not eq. 5's
            weight: ``alpha`` belongs to the weighted sum, :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ModelLoss`,
            whose ``lambda_inverse`` (default in ``LOSS_WEIGHTS``, ``objectives/isodream_v2/world_model.py``) it passes here.
        loss_type: ``"gaussian"``: ``-log N(a; a~, I)`` up to a constant, ``0.5 * sum_dims (a - a~)^2``
            (the authors' code); ``"l2"``: ``sum_dims (a - a~)^2`` (the paper's notation).

    Reads:
        ``action`` ``[*B, T, A]``, ``action_pred`` ``[*B, T, A]`` and ``action_pred_valid`` ``[*B, T, 1]``
        (steps without a previous state in the window are masked out).

    Returns:
        ``TensorDict(loss_inverse=[])``, the mean over valid steps times ``lambda_inverse``.
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss; remap with :meth:`set_keys`.

        Attributes:
            action: the true action ``a_t``. Defaults to ``"action"``.
            action_pred: the predicted action. Defaults to ``("next", "action_pred")``.
            action_pred_valid: where a prediction exists. Defaults to ``("next", "action_pred_valid")``.
        """

        action: NestedKey = "action"
        action_pred: NestedKey = ("next", "action_pred")
        action_pred_valid: NestedKey = ("next", "action_pred_valid")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(self, *, lambda_inverse: float = 1.0, loss_type: str = "gaussian"):
        super().__init__()
        if loss_type not in INVERSE_LOSSES:
            raise ValueError(f"unknown loss_type {loss_type!r}; valid: {INVERSE_LOSSES}")
        self.lambda_inverse = lambda_inverse
        self.loss_type = loss_type

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        missing = [
            k
            for k in (keys.action, keys.action_pred, keys.action_pred_valid)
            if k not in tensordict.keys(True)
        ]
        if missing:
            raise KeyError(f"InverseDynamicsLoss: missing keys {missing} (remap them with set_keys)")
        action = tensordict.get(keys.action).float()
        predicted = tensordict.get(keys.action_pred)
        if predicted.shape != action.shape:
            raise ValueError(
                f"predicted actions {tuple(predicted.shape)} and true actions {tuple(action.shape)} differ in shape"
            )
        valid = tensordict.get(keys.action_pred_valid).to(predicted.dtype)
        squared = (action - predicted).pow(2).sum(-1, keepdim=True)
        if self.loss_type == "gaussian":
            squared = 0.5 * squared
        loss = (squared * valid).sum() / valid.sum().clamp_min(1.0)
        return TensorDict({"loss_inverse": self.lambda_inverse * loss}, [])
