"""The value model ``v_xi(e_t)`` of eq. 7: an MLP regressing lambda-returns (Normal with unit variance)."""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import MLP


class IsoDreamV2Value(nn.Module):
    """MLP ``[*N, in_features] -> [*N, 1]``, 3 x 400 ELU by default (the authors' critic).

    Args:
        in_features: width of ``e_t`` (``PolicyInput.out_features``).
        num_cells: hidden width (400).
        depth: number of hidden layers (3).
        device: where to create the parameters.

    Examples:
        >>> import torch
        >>> IsoDreamV2Value(in_features=6, num_cells=8)(torch.randn(3, 6)).shape
        torch.Size([3, 1])
    """

    def __init__(
        self,
        *,
        in_features: int,
        num_cells: int = 400,
        depth: int = 3,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        self.in_features = in_features
        self.net = MLP(
            in_features=in_features,
            out_features=1,
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.ELU,
            device=device,
        )

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        if features.shape[-1] != self.in_features:
            raise ValueError(
                f"the value model expects [*N, {self.in_features}] features, got {tuple(features.shape)}"
            )
        return self.net(features).float()
