"""The inverse-dynamics cell of the video predictor (Iso-Dream, eq. "Inverse dynamics", Appendix D)."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["ActionInverseCell"]


class ActionInverseCell(nn.Module):
    """Regresses the action ``a_t`` from the change of action-branch encoder features ``E(x_{t+1}) - E(x_t)``.

    Training it through the encoder pushes the action-conditioned branch's features to carry what the
    action explains. As in the authors' video model it reads encoder-feature differences rather than
    latent states: two strided ``conv + BatchNorm + tanh`` blocks, a global max pool and two linear
    layers.

    Args:
        in_channels: channels of the feature maps.
        action_dim: size of the action.
        channels: widths of the two convolution blocks.

    Examples:
        >>> cell = ActionInverseCell(in_channels=16, action_dim=4)
        >>> cell(torch.zeros(3, 16, 16, 16)).shape
        torch.Size([3, 4])
    """

    def __init__(self, *, in_channels: int, action_dim: int, channels: tuple[int, int] = (64, 128)) -> None:
        super().__init__()
        c1, c2 = channels
        self.net = nn.Sequential(
            nn.Conv2d(in_channels, c1, 3, stride=2, padding=1),
            nn.BatchNorm2d(c1),
            nn.Tanh(),
            nn.Conv2d(c1, c2, 3, stride=2, padding=1),
            nn.BatchNorm2d(c2),
            nn.Tanh(),
            nn.AdaptiveMaxPool2d(1),
            nn.Flatten(),
            nn.Linear(c2, 64),
            nn.Linear(64, action_dim),
        )

    def forward(self, feature_delta: torch.Tensor) -> torch.Tensor:
        """Args:
            feature_delta: ``[B, C, H, W]`` difference of encoder features of consecutive frames.

        Returns:
            The predicted action ``[B, action_dim]``.
        """
        return self.net(feature_delta)
