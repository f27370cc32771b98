"""Training objective of the video predictor: image reconstruction + alpha * action reconstruction +
beta * PredRNN-v2 decoupling (Iso-Dream Sec. 4.4, Table 5)."""

from __future__ import annotations

from dataclasses import dataclass

import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from isodream_rl.video_prediction.predictor import ThreeBranchPredictor

__all__ = ["VideoPredictionLoss"]


class VideoPredictionLoss(LossModule):
    """Loss of :class:`~isodream_rl.video_prediction.predictor.ThreeBranchPredictor`.

    * ``loss_image``: mean squared error of frames ``1 .. T-1`` (all pixels, all steps);
    * ``loss_action``: ``lambda_action * sum_t ||a_t - a~_t||^2 / B`` from the inverse-dynamics cell
      (0 when the variant has none);
    * ``loss_decouple``: ``lambda_decouple *`` mean ``|cos(delta_c, delta_m)|`` summed over branches.

    Reference: https://arxiv.org/abs/2205.13817 (Iso-Dream), https://arxiv.org/abs/2103.09504 (PredRNN-v2).

    Args:
        predictor: the model.
        lambda_action: weight of the action reconstruction (paper, Table 5: 1e-4).
        lambda_decouple: weight of the decoupling term (authors' script: 0.1).
        context: observed frames per clip.

    Examples:
        >>> from isodream_rl.video_prediction.config import variant_config
        >>> model = ThreeBranchPredictor(config=variant_config("isodream", hidden_channels=8,
        ...     encoder_channels=(8, 8), kernel_size=3))
        >>> loss = VideoPredictionLoss(model)
        >>> td = TensorDict({"frames": torch.rand(2, 4, 3, 16, 16), "actions": torch.rand(2, 4, 4)}, [2])
        >>> sorted(loss(td).keys())
        ['loss_action', 'loss_decouple', 'loss_image']
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss.

        Attributes:
            frames (NestedKey): clips ``[B, T, C, H, W]`` in ``[0, 1]``. Defaults to ``"frames"``.
            actions (NestedKey): actions ``[B, T, A]``. Defaults to ``"actions"``.
        """

        frames: NestedKey = "frames"
        actions: NestedKey = "actions"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        predictor: ThreeBranchPredictor,
        *,
        lambda_action: float = 1e-4,
        lambda_decouple: float = 0.1,
        context: int = 2,
    ) -> None:
        super().__init__()
        self.predictor = predictor
        self.lambda_action = lambda_action
        self.lambda_decouple = lambda_decouple
        self.context = context

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        frames = tensordict.get(self.tensor_keys.frames)
        actions = tensordict.get(self.tensor_keys.actions)
        out = self.predictor(frames, actions, context=self.context)
        loss_image = F.mse_loss(out["frames"].float(), frames[:, 1:].float())
        if "action_pred" in out:
            target = actions[:, : out["action_pred"].shape[1]]
            loss_action = (out["action_pred"].float() - target).pow(2).sum() / frames.shape[0]
        else:
            loss_action = loss_image.new_zeros(())
        return TensorDict(
            {
                "loss_image": loss_image,
                "loss_action": self.lambda_action * loss_action,
                "loss_decouple": self.lambda_decouple * out["decouple"].float(),
            },
            batch_size=[],
        )
