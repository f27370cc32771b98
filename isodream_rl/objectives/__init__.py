"""Iso-Dream objectives: world-model loss (eq. 5), inverse-dynamics loss, KL balancing."""

from isodream_rl.objectives.isodream_v2.actor import IsoDreamActorLoss, lambda_returns
from isodream_rl.objectives.isodream_v2.imagination import IsoDreamImagination
from isodream_rl.objectives.inverse_dynamics import InverseDynamicsLoss
from isodream_rl.objectives.isodream_v2.kl import balanced_kl, gaussian_kl
from isodream_rl.objectives.isodream_v2.value import IsoDreamValueLoss, make_target_updater
from isodream_rl.objectives.isodream_v2.world_model import IsoDreamModelLoss

__all__ = [
    "InverseDynamicsLoss",
    "IsoDreamActorLoss",
    "IsoDreamImagination",
    "IsoDreamModelLoss",
    "IsoDreamValueLoss",
    "balanced_kl",
    "gaussian_kl",
    "lambda_returns",
    "make_target_updater",
]
