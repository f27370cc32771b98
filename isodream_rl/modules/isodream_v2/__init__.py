"""The DreamerV2-style learner's modules (``algo=isodream_v2``, ``isodream_paper`` and the single-branch
``dreamerv2``; ``mode=world_model`` trains its world model): the paper's world model with Gaussian latents
(encoder, RSSM cells, decoders, heads, :class:`IsoDreamV2WorldModel`, its configuration :class:`IsoDreamV2Config`
and CPU fast paths), the actor, the value and the acting policy.
"""

from isodream_rl.modules.isodream_v2.actor import IsoDreamV2Actor
from isodream_rl.modules.isodream_v2.config import IsoDreamV2Config
from isodream_rl.modules.isodream_v2.decoder import ConvDecoder
from isodream_rl.modules.isodream_v2.encoder import BranchedEncoder
from isodream_rl.modules.isodream_v2.heads import make_discount_head, make_reward_head
from isodream_rl.modules.isodream_v2.policy import IsoDreamV2Policy
from isodream_rl.modules.isodream_v2.rssm import (
    ActionConditionedRSSM,
    ActionFreeRSSM,
    LayerNormGRUCell,
    RSSMCell,
)
from isodream_rl.modules.isodream_v2.value import IsoDreamV2Value
from isodream_rl.modules.isodream_v2.world_model import IsoDreamV2WorldModel

__all__ = [
    "ActionConditionedRSSM",
    "ActionFreeRSSM",
    "BranchedEncoder",
    "ConvDecoder",
    "IsoDreamV2Actor",
    "IsoDreamV2Config",
    "IsoDreamV2Policy",
    "IsoDreamV2Value",
    "IsoDreamV2WorldModel",
    "LayerNormGRUCell",
    "RSSMCell",
    "make_discount_head",
    "make_reward_head",
]
