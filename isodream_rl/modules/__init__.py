"""Iso-Dream modules: encoder, decoupled RSSM, masked decoders, inverse dynamics, heads, world model."""

from isodream_rl.modules.actor import IsoDreamActor
from isodream_rl.modules.attention import POLICY_INPUTS, FutureStateAttention, PolicyInput
from isodream_rl.modules.composition import MaskComposition
from isodream_rl.modules.config import SIZE_PRESETS, WorldModelConfig
from isodream_rl.modules.decoder import ConvDecoder
from isodream_rl.modules.encoder import BranchedEncoder
from isodream_rl.modules.heads import make_discount_head, make_reward_head
from isodream_rl.modules.inverse_dynamics import InverseDynamicsCell
from isodream_rl.modules.policy import IsoDreamPolicy
from isodream_rl.modules.rssm import ActionConditionedRSSM, ActionFreeRSSM, LayerNormGRUCell, RSSMCell
from isodream_rl.modules.value import IsoDreamValue
from isodream_rl.modules.world_model import IsoDreamWorldModel

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
