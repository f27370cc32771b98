"""Iso-Dream objectives: world-model loss (eq. 5), inverse-dynamics loss, KL balancing."""

from isodream_rl.objectives.inverse_dynamics import InverseDynamicsLoss
from isodream_rl.objectives.kl import balanced_kl, gaussian_kl
from isodream_rl.objectives.world_model import IsoDreamModelLoss

__all__ = ["InverseDynamicsLoss", "IsoDreamModelLoss", "balanced_kl", "gaussian_kl"]
