"""Pictures and mask scores of a world model's per-branch decomposition (paper Figs. 3-5)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw
from tensordict import TensorDictBase

#: Rows of :func:`branch_grid`: (label, key under "next" or root, kind).
_ROWS = (
    ("ground truth", ("next", "pixels"), "uint8"),
    ("composite", ("next", "reco_pixels"), "image"),
    ("controllable", ("next", "reco_control"), "image"),
    ("mask s", ("next", "mask_control"), "mask"),
    ("noncontrollable", ("next", "reco_free"), "image"),
    ("mask z", ("next", "mask_free"), "mask"),
    ("background", "background", "image"),
    ("mask b", ("next", "mask_static"), "mask"),
)


def _to_uint8(x: torch.Tensor, kind: str) -> np.ndarray:
    """``[3 or 1, H, W]`` -> ``[H, W, 3]`` uint8."""
    x = x.detach().float().cpu()
    if kind == "uint8":
        x = x / 255.0
    elif kind == "image":
        x = x + 0.5
    x = x.clamp(0, 1)
    if x.shape[0] == 1:
        x = x.expand(3, -1, -1)
    return (x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def branch_grid(output: TensorDictBase, *, sample: int = 0, steps: int = 10, scale: int = 2) -> Image.Image:
    """A grid image: one row per quantity (ground truth, composite, each component and its mask), one column
    per time step of window ``sample`` of a world-model output.

    Args:
        output: the ``[B, T]`` output tensordict of :class:`~isodream_rl.modules.IsoDreamWorldModel`.
        sample: which window of the batch.
        steps: how many time steps (columns), evenly spread over the window.
        scale: pixel upscaling factor.
    """
    time = output.shape[1]
    columns = np.unique(np.linspace(0, time - 1, min(steps, time)).round().astype(int))
    keys = output.keys(True)
    rows = [(label, key, kind) for label, key, kind in _ROWS if key in keys]
    tile, label_width = 64 * scale, 110
    grid = Image.new("RGB", (label_width + tile * len(columns), tile * len(rows)), "white")
    draw = ImageDraw.Draw(grid)
    for r, (label, key, kind) in enumerate(rows):
        draw.text((4, r * tile + tile // 2 - 6), label, fill="black")
        for c, t in enumerate(columns):
            value = output.get(key)[sample, t]
            image = Image.fromarray(_to_uint8(value, kind)).resize((tile, tile), Image.NEAREST)
            grid.paste(image, (label_width + c * tile, r * tile))
    return grid


def save_png(image: Image.Image, path: str | Path) -> Path:
    """Write ``image`` atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    image.save(tmp)
    tmp.replace(path)
    return path


def mask_iou(predicted: torch.Tensor, truth: torch.Tensor, *, threshold: float = 0.5) -> float:
    """Intersection over union of ``predicted > threshold`` and the boolean ``truth`` over all pixels given.

    ``predicted``: ``[*N, 1, H, W]`` or ``[*N, H, W]`` soft masks; ``truth``: ``[*N, H, W]`` bool.
    """
    pred = predicted.detach().reshape(truth.shape) > threshold
    truth = truth.bool()
    union = (pred | truth).sum().item()
    return float((pred & truth).sum().item() / union) if union else float("nan")
