"""Iso-Dream modules: encoder, decoupled RSSM, masked decoders, inverse dynamics, heads, world model."""

from isodream_rl.modules.isodream_v2.actor import IsoDreamActor
from isodream_rl.modules.attention import POLICY_INPUTS, FutureStateAttention, PolicyInput
from isodream_rl.modules.isodream_v2.composition import MaskComposition
from isodream_rl.modules.isodream_v2.config import SIZE_PRESETS, WorldModelConfig
from isodream_rl.modules.isodream_v2.decoder import ConvDecoder
from isodream_rl.modules.isodream_v2.encoder import BranchedEncoder
from isodream_rl.modules.isodream_v2.heads import make_discount_head, make_reward_head
from isodream_rl.modules.inverse_dynamics import InverseDynamicsCell
from isodream_rl.modules.isodream_v2.policy import IsoDreamPolicy
from isodream_rl.modules.isodream_v2.rssm import ActionConditionedRSSM, ActionFreeRSSM, LayerNormGRUCell, RSSMCell
from isodream_rl.modules.isodream_v2.value import IsoDreamValue
from isodream_rl.modules.isodream_v2.world_model import IsoDreamWorldModel

__all__ = [
    "ActionConditionedRSSM",
    "ActionFreeRSSM",
    "BranchedEncoder",
    "ConvDecoder",
    "FutureStateAttention",
    "InverseDynamicsCell",
    "IsoDreamActor",
    "IsoDreamPolicy",
    "IsoDreamValue",
    "IsoDreamWorldModel",
    "LayerNormGRUCell",
    "MaskComposition",
    "POLICY_INPUTS",
    "PolicyInput",
    "RSSMCell",
    "SIZE_PRESETS",
    "WorldModelConfig",
    "make_discount_head",
    "make_reward_head",
]
