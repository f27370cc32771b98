"""Branch decoders ``Dec_phi1``, ``Dec_phi2`` (RGB + mask logit) and ``Dec_phi3`` (background) (§3.2).

Same layer pattern and widths as TorchRL's ``ObsDecoder`` (a linear layer to ``32*depth`` on a 1x1 map,
then transposed convolutions with kernels 5, 5, 6, 6 and stride 2 to 64x64, ReLU). It is written here
rather than reused because the static branch decodes a stack of frame embeddings, not ``(state,
belief)``, and because every call site wants the flat ``[N, C, 64, 64]`` form (channels-last friendly).

:class:`ConvDecoder` is the reference form, plain ``nn`` layers; the world model builds
:class:`~isodream_rl.modules.isodream_v2.fast_paths.FastConvDecoder` instead when ``IsoDreamV2Config.fast_paths`` is set (the
same layers and parameters, the first layer computed as a matrix product).
"""

from __future__ import annotations

import torch
from torch import nn


class ConvDecoder(nn.Module):
    """Latent vector -> image-sized map.

    Args:
        in_features: width of the input vector.
        out_channels: output channels (4 = RGB + mask logit for the dynamic branches).
        depth: channels of the last hidden layer (32 in the paper's setting).
        device: where to create the parameters.

    Shapes:
        ``[N, in_features]`` -> ``[N, out_channels, 64, 64]``.
    """

    def __init__(self, *, in_features: int, out_channels: int, depth: int = 32, device=None):
        super().__init__()
        self.in_features = in_features
        self.linear = nn.Linear(in_features, 32 * depth, device=device)
        # In-place ReLUs: a transposed convolution's backward needs its input, not its output, so the
        # activation can overwrite it and save one activation-sized allocation per layer.
        self.deconv = nn.Sequential(
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(32 * depth, 4 * depth, 5, stride=2, device=device),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(4 * depth, 2 * depth, 5, stride=2, device=device),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(2 * depth, depth, 6, stride=2, device=device),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(depth, out_channels, 6, stride=2, device=device),
        )

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        # the linear layer's output as a 1x1 map; deconv starts with its ReLU
        return self.deconv(self.linear(latent)[:, :, None, None])
