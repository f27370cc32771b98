"""Shared encoder ``Enc_theta`` and the three branch heads ``Enc_phi1..3`` (paper §3.2, Table 5).

The layer pattern is TorchRL's ``ObsEncoder`` (k4 s2 convolutions, ReLU, widths doubling from
``depth``) cut in two: the first two convolutions are the shared trunk, the last two are repeated with
separate weights for the controllable, noncontrollable and static heads. TorchRL's ``ObsEncoder``
always starts from pixels and flattens its output, so it cannot serve as a trunk; the heads would fit
but are two lines with the trunk's helper.
"""

from __future__ import annotations

import torch
from torch import nn

from isodream_rl.modules.pixels import IMAGE_SHAPE, check_pixels, preprocess_pixels


def _conv_stack(widths: list[int], *, device=None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for cin, cout in zip(widths[:-1], widths[1:]):
        # In-place ReLU: a convolution's backward needs its input, not its output.
        layers += [nn.Conv2d(cin, cout, 4, stride=2, device=device), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class BranchedEncoder(nn.Module):
    """``Enc_theta`` then ``Enc_phi1`` (controllable), ``Enc_phi2`` (noncontrollable), ``Enc_phi3`` (static).

    Args:
        depth: channels of the first convolution (32 in the paper's setting; TorchRL's ``channels``).
        heads: which heads to build, a subset of ``("control", "free", "static")``.
        device: where to create the parameters.

    Shapes:
        ``trunk(x)``: ``[N, 3, 64, 64]`` (preprocessed) -> ``[N, 2*depth, 14, 14]``;
        ``head(name, f)``: ``[N, 2*depth, 14, 14]`` -> ``[N, 32*depth]`` (1024 at depth 32).
    """

    def __init__(
        self,
        *,
        depth: int = 32,
        heads: tuple[str, ...] = ("control", "free", "static"),
        device=None,
    ):
        super().__init__()
        unknown = set(heads) - {"control", "free", "static"}
        if unknown:
            raise ValueError(f"unknown encoder heads {sorted(unknown)}; valid: control, free, static")
        self.depth = depth
        self.trunk = _conv_stack([3, depth, 2 * depth], device=device)
        self.heads = nn.ModuleDict(
            {name: _conv_stack([2 * depth, 4 * depth, 8 * depth], device=device) for name in heads}
        )

    @property
    def embed_dim(self) -> int:
        return 32 * self.depth

    def head(self, name: str, features: torch.Tensor) -> torch.Tensor:
        return self.heads[name](features).flatten(1)

    def trunk_features(self, pixels: torch.Tensor, *, channels_last: bool = False) -> torch.Tensor:
        """Shared trunk ``Enc_theta``: ``[N, 3, 64, 64]`` raw pixels -> ``[N, 2*depth, 14, 14]``."""
        check_pixels(pixels)
        if channels_last:
            # The layout is changed on the uint8 frames, before they are converted to float.
            pixels = pixels.contiguous(memory_format=torch.channels_last)
        return self.trunk(preprocess_pixels(pixels))

    def forward(self, pixels: torch.Tensor, *, channels_last: bool = False) -> tuple[torch.Tensor, ...]:
        """Encode ``[*batch, 3, 64, 64]`` pixels into one embedding ``[*batch, 32*depth]`` per dynamic head.

        Returns the embeddings of the ``"control"`` and ``"free"`` heads that exist, in that order.
        """
        check_pixels(pixels)
        lead = pixels.shape[:-3]
        pixels = pixels.reshape(-1, *IMAGE_SHAPE)
        features = self.trunk_features(pixels, channels_last=channels_last)
        embeddings = []
        if "control" in self.heads:
            embeddings.append(self.head("control", features).reshape(*lead, self.embed_dim))
        if "free" in self.heads:
            embeddings.append(self.head("free", features).reshape(*lead, self.embed_dim))
        return tuple(embeddings)
