"""Reward and discount heads (paper eq. 5): ``p(r_t | s_t)`` or ``p(r_t | s_t, z_t)``, and ``p(gamma_t | .)``.

Both are TorchRL ``MLP``s with ELU (2 x 400 in the paper's setting). The reward head outputs the mean of
a unit-variance Normal; the discount head outputs the logit of a Bernoulli "episode continues".
"""

from __future__ import annotations

from torch import nn
from torchrl.modules import MLP


def make_reward_head(*, in_features: int, num_cells: int = 400, depth: int = 2, device=None) -> MLP:
    """``[*N, in_features] -> [*N, 1]`` reward mean."""
    return MLP(
        in_features=in_features,
        out_features=1,
        depth=depth,
        num_cells=num_cells,
        activation_class=nn.ELU,
        device=device,
    )


def make_discount_head(*, in_features: int, num_cells: int = 400, depth: int = 2, device=None) -> MLP:
    """``[*N, in_features] -> [*N, 1]`` logit of ``P(not terminated)``."""
    return MLP(
        in_features=in_features,
        out_features=1,
        depth=depth,
        num_cells=num_cells,
        activation_class=nn.ELU,
        device=device,
    )
