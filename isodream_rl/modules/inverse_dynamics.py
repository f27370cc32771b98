"""Inverse-dynamics cell (paper §3.2, "Inverse dynamics": ``a~_{t-1} = MLP(s_{t-1}, s_t)``)."""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import MLP

INVERSE_INPUTS = ("state", "embedding")


class InverseDynamicsCell(nn.Module):
    """Predict the action between two consecutive controllable steps.

    Args:
        in_features: width of one step's input: the posterior state ``s`` (``inverse_input="state"``, the
            paper) or the controllable embedding ``e^s`` (``"embedding"``, the authors' code).
        action_dim: width of the action.
        inverse_input: ``"state"`` feeds ``[s_{t-1}, s_t]``; ``"embedding"`` feeds ``e^s_t - e^s_{t-1}``.
        num_cells: width of the two hidden layers (400 in the paper's setting).
        device: where to create the parameters.

    Shapes:
        ``previous``, ``current``: ``[*N, in_features]`` -> ``[*N, action_dim]``.
    """

    def __init__(
        self,
        *,
        in_features: int,
        action_dim: int,
        inverse_input: str = "state",
        num_cells: int = 400,
        device=None,
    ):
        super().__init__()
        if inverse_input not in INVERSE_INPUTS:
            raise ValueError(f"unknown inverse_input {inverse_input!r}; valid: {INVERSE_INPUTS}")
        self.inverse_input = inverse_input
        width = 2 * in_features if inverse_input == "state" else in_features
        self.mlp = MLP(
            in_features=width,
            out_features=action_dim,
            depth=2,
            num_cells=num_cells,
            activation_class=nn.ELU,
            device=device,
        )

    def forward(self, previous: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
        if self.inverse_input == "state":
            x = torch.cat([previous, current], dim=-1)
        else:
            x = current - previous
        return self.mlp(x)
