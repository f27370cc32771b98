"""Per-frame PSNR and SSIM for video prediction, averaged over samples for each predicted frame, then
over frames (the protocol behind Iso-Dream's Tables 2-3).

Two flavours:

* ``"float"``: on ``[0, 1]`` images (data range 1; torchmetrics' SSIM, Gaussian 11x11 window);
* ``"uint8"``: the authors' evaluation, for comparability: predictions clipped to ``[0, 1]``, both images
  converted with ``uint8(x * 255)`` (which truncates), PSNR from the per-sample MSE with peak 255, and
  scikit-image's SSIM (7x7 uniform window, sample covariance, data range 255, channel average).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "mse_per_sample",
    "psnr_per_sample",
    "ssim_per_sample",
    "uint8_psnr_per_sample",
    "uint8_ssim_per_sample",
    "FrameMetrics",
]


def _check(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape or pred.ndim != 4:
        raise ValueError(
            f"expected pred and target [N, C, H, W] of equal shape, got {pred.shape}, {target.shape}"
        )


def mse_per_sample(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error per sample of ``[N, C, H, W]`` float frames in ``[0, 1]``, as ``[N]``."""
    _check(pred, target)
    return (pred.float() - target.float()).pow(2).flatten(1).mean(1)


def psnr_per_sample(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """PSNR (dB) of each image pair, data range 1, prediction clipped to ``[0, 1]``.

    Args:
        pred: ``[N, C, H, W]``.
        target: ``[N, C, H, W]``.

    Returns:
        ``[N]``.
    """
    _check(pred, target)
    # one line rather than torchmetrics' PSNR with a per-sample ``dim``, much slower on CPU.
    mse = (pred.clamp(0, 1).float() - target.float()).pow(2).flatten(1).mean(1)
    return -10 * torch.log10(mse)


def ssim_per_sample(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """SSIM of each image pair (torchmetrics defaults: Gaussian window 11, sigma 1.5), data range 1."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    _check(pred, target)
    return structural_similarity_index_measure(
        pred.clamp(0, 1).float(), target.float(), data_range=1.0, reduction="none"
    )


def _to_uint8(x: torch.Tensor) -> torch.Tensor:
    return (x.clamp(0, 1) * 255).to(torch.uint8).float()  # the cast truncates, as numpy's astype does


def uint8_psnr_per_sample(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The authors' PSNR: truncated uint8 images, ``20 log10 255 - 10 log10 MSE`` per sample."""
    _check(pred, target)
    mse = (_to_uint8(pred) - _to_uint8(target)).pow(2).flatten(1).mean(1)
    return 20 * torch.log10(torch.tensor(255.0)) - 10 * torch.log10(mse)


def uint8_ssim_per_sample(pred: torch.Tensor, target: torch.Tensor, *, window: int = 7) -> torch.Tensor:
    """The authors' SSIM: scikit-image's ``structural_similarity`` on truncated uint8 images.

    A uniform ``window x window`` filter, sample (``n - 1``) covariance, ``K1 = 0.01``, ``K2 = 0.03``,
    data range 255; the SSIM map is averaged over the interior (valid) region and over channels.
    """
    _check(pred, target)
    x, y = _to_uint8(pred), _to_uint8(target)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    n = window * window
    cov_norm = n / (n - 1)

    def mean(z):
        return F.avg_pool2d(z, window, stride=1)

    mx, my = mean(x), mean(y)
    vx = cov_norm * (mean(x * x) - mx * mx)
    vy = cov_norm * (mean(y * y) - my * my)
    vxy = cov_norm * (mean(x * y) - mx * my)
    ssim_map = ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return ssim_map.flatten(1).mean(1)


class FrameMetrics:
    """Accumulates PSNR / SSIM per predicted frame over an evaluation set.

    Examples:
        >>> metrics = FrameMetrics()
        >>> metrics.update(torch.rand(2, 3, 3, 16, 16), torch.rand(2, 3, 3, 16, 16))
        >>> sorted(metrics.compute())
        ['mse', 'psnr', 'psnr_uint8', 'ssim', 'ssim_uint8']
    """

    _FUNCTIONS = {
        "mse": mse_per_sample,
        "psnr": psnr_per_sample,
        "ssim": ssim_per_sample,
        "psnr_uint8": uint8_psnr_per_sample,
        "ssim_uint8": uint8_ssim_per_sample,
    }

    def __init__(self) -> None:
        self._sums: dict[str, torch.Tensor] = {}
        self._count = 0

    def update(self, pred: torch.Tensor, target: torch.Tensor) -> None:
        """Add a batch of predicted clips ``[B, T, C, H, W]`` and their targets."""
        if pred.shape != target.shape or pred.ndim != 5:
            raise ValueError(f"expected pred and target [B, T, C, H, W], got {pred.shape}, {target.shape}")
        batch, steps = pred.shape[:2]
        p, t = pred.detach().flatten(0, 1).cpu(), target.detach().flatten(0, 1).cpu()
        for name, fn in self._FUNCTIONS.items():
            per_frame = fn(p, t).view(batch, steps).sum(0).double()
            if name in self._sums and self._sums[name].shape != per_frame.shape:
                raise ValueError(f"every batch must predict {self._sums[name].shape[0]} frames, got {steps}")
            self._sums[name] = self._sums.get(name, 0) + per_frame
        self._count += batch

    def compute(self) -> dict[str, torch.Tensor]:
        """Per-frame averages over all samples, ``{metric: [T]}``."""
        if not self._count:
            raise ValueError("FrameMetrics.compute() called before any update()")
        return {k: (v / self._count).float() for k, v in self._sums.items()}

    @staticmethod
    def summarize(per_frame: dict[str, torch.Tensor], horizons: tuple[int, ...]) -> dict[str, float]:
        """Mean over the first ``h`` predicted frames of each per-frame curve, as ``{"psnr_10": ..}``."""
        out = {}
        for h in horizons:
            for name, curve in per_frame.items():
                if h > curve.shape[0]:
                    raise ValueError(f"horizon {h} exceeds the {curve.shape[0]} predicted frames")
                out[f"{name}_{h}"] = float(curve[:h].mean())
        return out
