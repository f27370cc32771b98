"""Iso-Dream's modules. The default learner's (``algo=isodream``, :mod:`isodream_rl.modules.isodream`): the
decoupled world model on TorchRL's DreamerV3 parts, its configuration, actor, critic and acting policy; and the
pieces both learners build on: the future-state attention (eq. 6), the inverse-dynamics cell, the mask
composition (eq. 4), the size presets.

The DreamerV2-style learner's modules (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``) are exported by
:mod:`isodream_rl.modules.isodream_v2`.
"""

from isodream_rl.modules.attention import POLICY_INPUTS, FutureStateAttention, PolicyInput
from isodream_rl.modules.composition import MaskComposition
from isodream_rl.modules.inverse_dynamics import InverseDynamicsCell
from isodream_rl.modules.isodream.behavior import IsoDreamPolicy, PolicyFeatures, make_actor, make_value
from isodream_rl.modules.isodream.world_model import IsoDreamConfig, IsoDreamWorldModel
from isodream_rl.modules.sizes import SIZE_PRESETS

__all__ = [
    "POLICY_INPUTS",
    "SIZE_PRESETS",
    "FutureStateAttention",
    "InverseDynamicsCell",
    "IsoDreamConfig",
    "IsoDreamPolicy",
    "IsoDreamWorldModel",
    "MaskComposition",
    "PolicyFeatures",
    "PolicyInput",
    "make_actor",
    "make_value",
]
