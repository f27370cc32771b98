"""Pictures and mask scores of a world model's per-branch decomposition (paper Figs. 3-5)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw
from tensordict import TensorDictBase
from torch import nn

from isodream_rl.data.sprites_episodes import episode_windows, model_input
from isodream_rl.evaluation.decomposition import branch_assignment, centred_images, score_decomposition
from isodream_rl.modules.pixels import preprocess_pixels

#: Rows of :func:`branch_grid`: (label, key under "next" or root, kind).
_ROWS = (
    ("ground truth", ("next", "pixels"), "uint8"),
    ("true agent", ("next", "mask_agent"), "bool"),
    ("true distractors", ("next", "mask_distractors"), "bool"),
    ("composite", ("next", "reco_pixels"), "image"),
    ("controllable", ("next", "reco_control"), "image"),
    ("mask s", ("next", "mask_control"), "mask"),
    ("noncontrollable", ("next", "reco_free"), "image"),
    ("mask z", ("next", "mask_free"), "mask"),
    ("background", "background", "image"),
    ("mask b", ("next", "mask_static"), "mask"),
)


def _to_uint8(x: torch.Tensor, kind: str) -> np.ndarray:
    """``[3 or 1, H, W]`` (``[H, W]`` for ``kind="bool"``) -> ``[H, W, 3]`` uint8."""
    x = x.detach().float().cpu()
    if kind == "bool":
        x = x[None]
    elif kind == "uint8":
        x = x / 255.0
    elif kind == "image":
        x = x + 0.5
    x = x.clamp(0, 1)
    if x.shape[0] == 1:
        x = x.expand(3, -1, -1)
    return (x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def branch_grid(output: TensorDictBase, *, sample: int = 0, steps: int = 10, scale: int = 2) -> Image.Image:
    """A grid image: one row per quantity (ground truth, the ground-truth masks where the output holds them,
    composite, each component and its mask), one column per time step of window ``sample`` of a world-model
    output.

    Args:
        output: the ``[B, T]`` output tensordict of a world model, its images in ``[-0.5, 0.5]``
            (:class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel`'s, or
            :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel`'s through
            :func:`~isodream_rl.evaluation.decomposition.centred_images`, as :func:`score_branches` returns them).
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


@torch.no_grad()
def score_branches(
    world_model: nn.Module, data: TensorDictBase, *, window: int, device: torch.device | str = "cpu"
) -> tuple[dict[str, float], TensorDictBase]:
    """Scores of a world model on flat episode data cut into windows, and its output (for
    :func:`branch_grid`).

    ``reco_mse``: the composite's mean squared error per pixel and channel (``[-0.5, 0.5]`` range). Where the
    data hold the ground truth (``"mask_agent"`` and ``"mask_distractors"`` under ``"next"``, any env of
    ``make_env(..., return_masks=True)``), the scores of
    :func:`~isodream_rl.evaluation.decomposition_scores` (each branch's pixels: the largest mask). On the
    sprites scene (``"distractor_ids"``, as
    :func:`~isodream_rl.data.sprites_episodes.collect_sprites_episodes` writes them), per disc as well:

    * ``free_covers_distractor_{i}``: the fraction of distractor ``i``'s visible pixels the noncontrollable
      branch holds (which distractors the branch has taken, one by one);
    * ``reco_error_distractor_{i}``: the composite's squared error on those pixels (summed over RGB), which
      tells a disc drawn by the wrong branch (low error) from a disc not drawn at all (the error of the disc
      against the background, ~0.3-0.5); ``reco_error_agent`` the same on the agent's pixels.

    Args:
        world_model: an :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` or an
            :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel` (or a module with their output
            keys).
        data: flat ``[episodes * steps]`` episodes, ``steps`` a multiple of ``window``.
        window: steps per window; each is filtered from zero states.
        device: where the world model runs.

    Returns:
        ``(scores, output)``: the scores, and the world model's ``[N, window]`` output on CPU, its images in
        ``[-0.5, 0.5]`` (:func:`~isodream_rl.evaluation.decomposition.centred_images`; with the ground-truth
        masks, where the data hold them, beside its input frames).
    """
    windows = episode_windows(data, window=window)
    out = centred_images(world_model, world_model(model_input(windows).to(device))).cpu()
    truth = windows["next"]
    if not all(key in truth.keys() for key in ("mask_agent", "mask_distractors")):
        error = (out["next", "reco_pixels"].float() - preprocess_pixels(truth["pixels"])).pow(2)
        return {"reco_mse": float(error.mean())}, out
    scores = score_decomposition(out, windows)
    for key in ("mask_agent", "mask_distractors"):  # beside the frames, for branch_grid
        out["next", key] = truth[key]
    if "distractor_ids" in truth.keys():
        scores.update(_disc_scores(out, windows))
    return scores, out


def _disc_scores(out: TensorDictBase, windows: TensorDictBase) -> dict[str, float]:
    """The sprites scene's per-disc scores of :func:`score_branches`."""
    truth = windows["next"]
    ids = truth["distractor_ids"]
    error = (out["next", "reco_pixels"].float() - preprocess_pixels(truth["pixels"])).pow(2).sum(-3)
    taken = branch_assignment(out)["free"] if "mask_free" in out["next"].keys() else None
    scores = {}
    for i in range(1, int(ids.max()) + 1):
        pixels = ids == i
        count = pixels.sum().clamp(min=1)
        if taken is not None:
            scores[f"free_covers_distractor_{i - 1}"] = float((taken & pixels).sum() / count)
        scores[f"reco_error_distractor_{i - 1}"] = float(error[pixels].sum() / count)
    agent = truth["mask_agent"]
    scores["reco_error_agent"] = float(error[agent].sum() / agent.sum().clamp(min=1))
    return scores
