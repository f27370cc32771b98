"""Iso-Dream modules: encoder, decoupled RSSM, masked decoders, inverse dynamics, heads, world model."""

from isodream_rl.modules.isodream_v2.actor import IsoDreamV2Actor
from isodream_rl.modules.attention import POLICY_INPUTS, FutureStateAttention, PolicyInput
from isodream_rl.modules.isodream_v2.composition import MaskComposition
from isodream_rl.modules.isodream_v2.config import SIZE_PRESETS, IsoDreamV2Config
from isodream_rl.modules.isodream_v2.decoder import ConvDecoder
from isodream_rl.modules.isodream_v2.encoder import BranchedEncoder
from isodream_rl.modules.isodream_v2.heads import make_discount_head, make_reward_head
from isodream_rl.modules.inverse_dynamics import InverseDynamicsCell
from isodream_rl.modules.isodream_v2.policy import IsoDreamV2Policy
from isodream_rl.modules.isodream_v2.rssm import ActionConditionedRSSM, ActionFreeRSSM, LayerNormGRUCell, RSSMCell
from isodream_rl.modules.isodream_v2.value import IsoDreamV2Value
from isodream_rl.modules.isodream_v2.world_model import IsoDreamV2WorldModel

__all__ = [
    "ActionConditionedRSSM",
    "ActionFreeRSSM",
    "BranchedEncoder",
    "ConvDecoder",
    "FutureStateAttention",
    "InverseDynamicsCell",
    "IsoDreamV2Actor",
    "IsoDreamV2Policy",
    "IsoDreamV2Value",
    "IsoDreamV2WorldModel",
    "LayerNormGRUCell",
    "MaskComposition",
    "POLICY_INPUTS",
    "PolicyInput",
    "RSSMCell",
    "SIZE_PRESETS",
    "IsoDreamV2Config",
    "make_discount_head",
    "make_reward_head",
]
