"""Iso-Dream objectives: world-model loss (eq. 5), inverse-dynamics loss, KL balancing."""

from isodream_rl.objectives.isodream_v2.actor import IsoDreamV2ActorLoss, lambda_returns
from isodream_rl.objectives.isodream_v2.imagination import IsoDreamV2Imagination
from isodream_rl.objectives.inverse_dynamics import InverseDynamicsLoss
from isodream_rl.objectives.isodream_v2.kl import balanced_kl, gaussian_kl
from isodream_rl.objectives.isodream_v2.value import IsoDreamV2ValueLoss, make_target_updater
from isodream_rl.objectives.isodream_v2.world_model import IsoDreamV2ModelLoss

__all__ = [
    "InverseDynamicsLoss",
    "IsoDreamV2ActorLoss",
    "IsoDreamV2Imagination",
    "IsoDreamV2ModelLoss",
    "IsoDreamV2ValueLoss",
    "balanced_kl",
    "gaussian_kl",
    "lambda_returns",
    "make_target_updater",
]
