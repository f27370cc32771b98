"""The DreamerV2-style learner's objectives (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``): the world-model
loss (eq. 5, :class:`IsoDreamV2ModelLoss`, its weights :data:`LOSS_WEIGHTS`), KL balancing, imagination with the
attention window (:class:`IsoDreamV2Imagination`), the actor and value losses."""

from isodream_rl.objectives.isodream_v2.actor import IsoDreamV2ActorLoss, lambda_returns
from isodream_rl.objectives.isodream_v2.imagination import IsoDreamV2Imagination
from isodream_rl.objectives.isodream_v2.kl import balanced_kl, gaussian_kl
from isodream_rl.objectives.isodream_v2.value import IsoDreamV2ValueLoss, make_target_updater
from isodream_rl.objectives.isodream_v2.world_model import LOSS_WEIGHTS, PAPER_WEIGHTS, IsoDreamV2ModelLoss

__all__ = [
    "LOSS_WEIGHTS",
    "PAPER_WEIGHTS",
    "IsoDreamV2ActorLoss",
    "IsoDreamV2Imagination",
    "IsoDreamV2ModelLoss",
    "IsoDreamV2ValueLoss",
    "balanced_kl",
    "gaussian_kl",
    "lambda_returns",
    "make_target_updater",
]
