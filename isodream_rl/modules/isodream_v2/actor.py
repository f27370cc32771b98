"""The action model ``pi(a_t | e_t)`` of eq. 7: a tanh-squashed Gaussian (TorchRL ``TanhNormal``).

The authors use a "truncated normal" whose samples are in fact unclipped Normal draws clipped at the
environment; a tanh-squashed Gaussian keeps actions in ``(-1, 1)`` with an exact
log-density, which the entropy bonus and the REINFORCE option need. The mean is ``5 tanh(mu / 5)``
(TorchRL's ``tanh_loc``, as in DreamerV1/V2) and the std ``2 sigmoid(x / 2) + min_std`` (the authors'
actor std).
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import MLP, TanhNormal

from isodream_rl.modules.isodream_v2.rssm import sigmoid2_std


class IsoDreamV2Actor(nn.Module):
    """MLP from ``e_t`` to a ``TanhNormal`` over actions in ``(-1, 1)``.

    Args:
        in_features: width of ``e_t`` (``PolicyInput.out_features``).
        action_dim: width of the action.
        num_cells: hidden width (400).
        depth: number of hidden layers (4).
        min_std: lower bound of the pre-tanh std (0.1).
        upscale: bound of the pre-tanh mean, ``upscale * tanh(mu / upscale)`` (5).
        device: where to create the parameters.

    Shapes:
        ``forward(e)``: ``[*N, in_features]`` -> ``(loc, scale)`` each ``[*N, action_dim]``;
        ``distribution(e)``: a ``TanhNormal`` with batch shape ``[*N]`` and event shape ``[action_dim]``;
        ``mode(e)``: ``[*N, action_dim]``, the evaluation action ``tanh(loc)``.

    Examples:
        >>> import torch
        >>> actor = IsoDreamV2Actor(in_features=6, action_dim=2, num_cells=8, depth=2)
        >>> action, log_prob = actor.distribution(torch.randn(3, 6)).rsample_and_log_prob()
        >>> action.shape, log_prob.shape
        (torch.Size([3, 2]), torch.Size([3]))
    """

    def __init__(
        self,
        *,
        in_features: int,
        action_dim: int,
        num_cells: int = 400,
        depth: int = 4,
        min_std: float = 0.1,
        upscale: float = 5.0,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        if action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {action_dim}")
        self.in_features, self.action_dim = in_features, action_dim
        self.min_std, self.upscale = min_std, upscale
        self.net = MLP(
            in_features=in_features,
            out_features=2 * action_dim,
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.ELU,
            device=device,
        )

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if features.shape[-1] != self.in_features:
            raise ValueError(
                f"the actor expects [*N, {self.in_features}] features, got {tuple(features.shape)}"
            )
        raw = self.net(features).float()
        loc, scale = raw.chunk(2, dim=-1)
        return loc, sigmoid2_std(scale, self.min_std)

    def distribution(self, features: torch.Tensor) -> TanhNormal:
        loc, scale = self(features)
        return TanhNormal(loc, scale, upscale=self.upscale, tanh_loc=True)

    def mode(self, features: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``tanh(upscale * tanh(loc / upscale))`` used for evaluation."""
        loc, _ = self(features)
        return torch.tanh(self.upscale * torch.tanh(loc / self.upscale))
