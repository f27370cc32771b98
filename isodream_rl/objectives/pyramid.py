"""A coarse-to-fine image term: the composite's squared error on the levels of a Gaussian pyramid.

Not in the paper (its image term, eq. 5, is the per-pixel log-likelihood only). At full resolution a small
object that the model draws a few pixels off its true place, or as a faint haze over the frame, gets a
gradient only where the two overlap. Level ``l`` of a Gaussian pyramid (Burt and Adelson: blur with the
binomial kernel ``[1, 4, 6, 4, 1] / 16`` per axis, keep every second pixel, ``l`` times) has the frame blurred
over ~``2^l`` pixels, so there the two blobs overlap and the error pulls the component towards where the
object is before its fine shape is learned (the usual reason for multi-scale reconstruction losses). Level
``l`` has ``4^-l`` of the pixels and is weighted by ``4^l``, so an error spread evenly over the frame weighs the
same at every level as at full resolution. (Average pooling in disjoint cells would not do: two blobs in
different cells stay apart at every level.)
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

_BINOMIAL = (1.0, 4.0, 6.0, 4.0, 1.0)


def pyramid_down(images: torch.Tensor) -> torch.Tensor:
    """One Gaussian-pyramid step: ``[N, C, H, W]`` -> ``[N, C, H / 2, W / 2]`` (binomial blur, edge pixels
    repeated, every second pixel kept)."""
    channels = images.shape[1]
    kernel = images.new_tensor(_BINOMIAL) / 16.0
    padded = F.pad(images, (2, 2, 2, 2), mode="replicate")
    rows = F.conv2d(padded, kernel.view(1, 1, 5, 1).expand(channels, 1, 5, 1), stride=(2, 1), groups=channels)
    return F.conv2d(rows, kernel.view(1, 1, 1, 5).expand(channels, 1, 1, 5), stride=(1, 2), groups=channels)


def pyramid_squared_error(reco: torch.Tensor, target: torch.Tensor, *, levels: int) -> torch.Tensor:
    """``sum_{l=1..levels} 4^l * ||G_l(reco) - G_l(target)||^2`` over every frame (``G_l``: pyramid level ``l``).

    Args:
        reco: composed frames ``[*batch, C, H, W]``.
        target: true frames, same shape; ``H`` and ``W`` divisible by ``2^levels``.
        levels: number of pyramid levels (>= 1).

    Returns:
        A scalar: the weighted squared errors summed over pixels, channels, levels and frames (divide by the
        frame count for the per-frame value).
    """
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    if reco.shape != target.shape:
        raise ValueError(f"reco and target differ in shape: {tuple(reco.shape)} vs {tuple(target.shape)}")
    height, width = reco.shape[-2:]
    if height % 2**levels or width % 2**levels:
        raise ValueError(f"{levels} levels need H and W divisible by {2**levels}, got {height}x{width}")
    reco = reco.reshape(-1, *reco.shape[-3:])
    target = target.reshape(-1, *target.shape[-3:])
    total = reco.new_zeros(())
    for level in range(1, levels + 1):
        reco, target = pyramid_down(reco), pyramid_down(target)
        total = total + 4**level * F.mse_loss(reco, target, reduction="sum")
    return total


class PyramidImageTerm(nn.Module):
    """The coarse-to-fine image term as an extra term of :class:`~isodream_rl.objectives.IsoDreamModelLoss`.

    ``loss_model_reco_pyramid = lambda_reco_pyramid * 0.5 * pyramid_squared_error(o^, o) / frames``: the
    frames' mean like the image log-loss. Used as
    ``IsoDreamModelLoss(world_model, extra_terms=[PyramidImageTerm(levels=4)])``.

    Args:
        levels: pyramid levels (3: 32x32, 16x16 and 8x8 for 64x64 frames), in ``[1, 6]``.
        lambda_reco_pyramid: the term's weight (1). A plain attribute, so a training loop can ramp it.

    Examples:
        >>> import torch
        >>> term = PyramidImageTerm(levels=2)
        >>> sorted(term(torch.zeros(2, 5, 3, 64, 64), torch.zeros(2, 5, 3, 64, 64)))
        ['loss_model_reco_pyramid']
    """

    def __init__(self, *, levels: int = 3, lambda_reco_pyramid: float = 1.0):
        super().__init__()
        if lambda_reco_pyramid < 0 or not 1 <= levels <= 6:
            raise ValueError(
                f"lambda_reco_pyramid must be >= 0 and levels in [1, 6] (64x64 frames), got "
                f"{lambda_reco_pyramid} and {levels}"
            )
        self.levels = levels
        self.lambda_reco_pyramid = lambda_reco_pyramid

    def forward(self, reco: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
        frames = reco.numel() // reco.shape[-3:].numel()
        coarse = pyramid_squared_error(reco, target, levels=self.levels)
        return {"loss_model_reco_pyramid": self.lambda_reco_pyramid * 0.5 * coarse / frames}

    def extra_repr(self) -> str:
        return f"levels={self.levels}, lambda_reco_pyramid={self.lambda_reco_pyramid}"
