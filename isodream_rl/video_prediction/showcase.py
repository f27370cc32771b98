"""Figures: a showcase like the paper's Figure 6 (ground truth, prediction, each branch and its mask)
and per-frame metric curves."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from PIL import Image, ImageDraw

from isodream_rl.video_prediction.predictor import ThreeBranchPredictor

__all__ = ["showcase_rows", "save_showcase", "save_metric_curves"]

_ROWS = (
    ("ground truth", "truth"),
    ("prediction", "frames"),
    ("action branch", "reco_control"),
    ("action mask", "mask_control"),
    ("action-free branch", "reco_free"),
    ("action-free mask", "mask_free"),
    ("static mask", "mask_static"),
)


@torch.no_grad()
def showcase_rows(
    model: ThreeBranchPredictor,
    frames: torch.Tensor,
    actions: torch.Tensor,
    *,
    context: int = 2,
    every: int = 3,
) -> list[tuple[str, np.ndarray]]:
    """Rows of the showcase for one clip, every ``every``-th predicted frame.

    Args:
        model: the predictor.
        frames: ``[T, C, H, W]`` in ``[0, 1]``, on any device (a data set's clip is on the CPU).
        actions: ``[T, A]``, on any device.
        context: observed frames.
        every: stride over the predicted frames.

    Returns:
        ``[(label, uint8 [K, H, W, 3])]`` for the rows the variant has (masks shown in grey).
    """
    device = next(model.parameters()).device
    frames, actions = frames.to(device), actions.to(device)
    was_training = model.training
    model.eval()
    out = model(frames[None], actions[None], context=context, return_components=True)
    model.train(was_training)
    index = torch.arange(context - 1, frames.shape[0] - 1, every, device=device)
    out["truth"] = frames[None, 1:]
    rows = []
    for label, key in _ROWS:
        if key not in out:
            continue
        images = out[key][0, index].clamp(0, 1)
        if images.shape[1] == 1:
            images = images.expand(-1, 3, -1, -1)
        rows.append((label, (images.permute(0, 2, 3, 1).cpu().numpy() * 255).astype(np.uint8)))
    return rows


def save_showcase(
    path: str | os.PathLike, rows: Sequence[tuple[str, np.ndarray]], *, scale: int = 2, label_width: int = 120
) -> None:
    """Write rows of images as one labelled PNG grid (``rows`` from :func:`showcase_rows`)."""
    if not rows:
        raise ValueError("nothing to draw: rows is empty")
    count, height, width = rows[0][1].shape[:3]
    pad = 2
    canvas = Image.new(
        "RGB", (label_width + count * (width * scale + pad), len(rows) * (height * scale + pad)), "white"
    )
    draw = ImageDraw.Draw(canvas)
    for r, (label, images) in enumerate(rows):
        y = r * (height * scale + pad)
        draw.text((4, y + height * scale // 2 - 6), label, fill="black")
        for k, image in enumerate(images):
            tile = Image.fromarray(image).resize((width * scale, height * scale), Image.Resampling.NEAREST)
            canvas.paste(tile, (label_width + k * (width * scale + pad), y))
    canvas.save(path)


def save_metric_curves(path: str | os.PathLike, curves: Mapping[str, Mapping[str, Sequence[float]]]) -> None:
    """Plot PSNR and SSIM against the predicted-frame index for several runs.

    Args:
        path: output PNG.
        curves: ``{run_name: {"psnr": [...], "ssim": [...]}}``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    for name, curve in curves.items():
        for ax, metric in zip(axes, ("psnr", "ssim")):
            values = curve[metric]
            ax.plot(np.arange(1, len(values) + 1), values, label=name)
    for ax, metric in zip(axes, ("PSNR (dB)", "SSIM")):
        ax.set_xlabel("predicted frame")
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
