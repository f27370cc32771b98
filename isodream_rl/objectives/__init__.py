"""Iso-Dream's objectives. The default learner's (``algo=isodream``, :mod:`isodream_rl.objectives.isodream`):
eq. 5 as TorchRL's ``DreamerV3ModelLoss`` plus the inverse-dynamics term, imagination with the sliding action-free
window, and the learner that composes them with TorchRL's DreamerV3 behaviour losses; and what both learners use:
the inverse-dynamics loss, imagination as a TorchRL ``DreamerEnv``.

The DreamerV2-style learner's objectives (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``) are exported by
:mod:`isodream_rl.objectives.isodream_v2`.
"""

from isodream_rl.objectives.imagination_env import latent_dreamer_env
from isodream_rl.objectives.inverse_dynamics import InverseDynamicsLoss
from isodream_rl.objectives.isodream import (
    IsoDreamImaginationEnv,
    IsoDreamLearner,
    IsoDreamModelLoss,
    IsoDreamTransition,
    isodream_imagination_env,
    make_isodream,
)

__all__ = [
    "InverseDynamicsLoss",
    "IsoDreamImaginationEnv",
    "IsoDreamLearner",
    "IsoDreamModelLoss",
    "IsoDreamTransition",
    "isodream_imagination_env",
    "latent_dreamer_env",
    "make_isodream",
]
