"""Open-loop predictions of the world model (paper Figs. 3-5): a few context frames, then imagination.

The first ``context`` frames of a replay window are filtered (posteriors); from there both branches roll
forward on their priors, the controllable one with the window's real actions, and every step is decoded
into the composite image, each branch's component and its mask.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw
from tensordict import TensorDict, TensorDictBase

from isodream_rl.modules.isodream.world_model import IsoDreamWorldModel
from isodream_rl.modules.isodream_v2 import IsoDreamV2WorldModel
from isodream_rl.modules.pixels import IMAGE_SHAPE

#: Columns of each GIF frame: (label, key in the prediction tensordict, kind).
_COLUMNS = (
    ("truth", "pixels", "uint8"),
    ("prediction", "reco_pixels", "image"),
    ("controllable", "reco_control", "image"),
    ("mask s", "mask_control", "mask"),
    ("noncontrollable", "reco_free", "image"),
    ("mask z", "mask_free", "mask"),
    ("background", "background", "image"),
    ("mask b", "mask_static", "mask"),
)


@torch.no_grad()
def open_loop_prediction(
    world_model: IsoDreamV2WorldModel | IsoDreamWorldModel, window: TensorDictBase, *, context: int = 5
) -> TensorDictBase:
    """Filter ``context`` steps of ``window``, imagine the rest with its actions, decode every step.

    Args:
        world_model: the trained world model (an ``IsoDreamWorldModel`` predicts with its own
            :meth:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel.open_loop`).
        window: a ``[B, T]`` replay window with ``("next", "pixels")`` uint8 ``[B, T, 3, 64, 64]`` and
            ``"action"`` ``[B, T, A]``, on any device (a replay sample is on the CPU).
        context: observed steps, ``2 <= context < T`` (the world model filters windows of 2 steps or more).

    Returns:
        ``[B, T]`` tensordict on the world model's device: ``pixels`` (truth, uint8), ``reco_pixels``,
        ``reco_control`` (and ``reco_free``, ``background`` when the branches exist) in ``[-0.5, 0.5]``, masks
        ``[B, T, 1, 64, 64]`` and ``imagined`` ``[B, T]`` bool (``False`` on context steps).
    """
    batch, time = window.shape
    if not 2 <= context < time:
        raise ValueError(f"context must be in [2, {time - 1}] for a window of {time} steps, got {context}")
    device = next(world_model.parameters()).device
    window = window.select("action", ("next", "pixels"), "is_init", strict=False).to(device)
    if isinstance(world_model, IsoDreamWorldModel):
        return world_model.open_loop(window, context=context)
    cfg = world_model.config
    was_training = world_model.training
    world_model.eval()
    observed = window[:, :context].clone()
    filtered = world_model(observed).get("next")
    action = window.get("action").float()
    state = {k: filtered.get(k)[:, -1] for k in ("state", "belief")}
    if cfg.free_branch:
        state.update({k: filtered.get(k)[:, -1] for k in ("free_state", "free_belief")})

    control_inputs = [filtered.get("prior_state" if cfg.decoder_input == "paper" else "state")]
    control_beliefs = [filtered.get("belief")]
    free_inputs = [filtered.get("free_state")] if cfg.free_branch else []
    free_beliefs = [filtered.get("free_belief")] if cfg.free_branch else []
    for t in range(context, time):
        _, _, s, h = world_model.control_rssm.imagine_step(state["state"], state["belief"], action[:, t])
        state["state"], state["belief"] = s, h
        control_inputs.append(s[:, None])
        control_beliefs.append(h[:, None])
        if cfg.free_branch:
            _, _, z, hf = world_model.free_rssm.imagine_step(state["free_state"], state["free_belief"])
            state["free_state"], state["free_belief"] = z, hf
            free_inputs.append(z[:, None])
            free_beliefs.append(hf[:, None])

    def decode(decoder, inputs, beliefs) -> torch.Tensor:
        feat = torch.cat([torch.cat(inputs, 1), torch.cat(beliefs, 1)], -1).reshape(batch * time, -1)
        # in the decoder's dtype: the composition composes bf16 outputs in float32
        return decoder(feat).reshape(batch, time, -1, *IMAGE_SHAPE[1:])

    decoded = {"control": decode(world_model.control_decoder, control_inputs, control_beliefs)}
    if cfg.free_branch:
        decoded["free"] = decode(world_model.free_decoder, free_inputs, free_beliefs)
    if cfg.static_branch:
        pixels = window.get(("next", "pixels"))[:, :context]
        trunk = world_model.encoder.trunk_features(
            pixels.reshape(-1, *IMAGE_SHAPE), channels_last=cfg.channels_last
        )
        static = world_model.static_background(trunk.reshape(batch, context, *trunk.shape[1:]))
        decoded["static"] = static[:, None]
    composite, masks, colors = world_model.composition.compose_decoded(decoded)
    world_model.train(was_training)

    out = TensorDict(
        {
            "pixels": window.get(("next", "pixels")),
            "reco_pixels": composite,
            "reco_control": colors["control"],
            "imagined": (torch.arange(time, device=device) >= context).expand(batch, time),
        },
        [batch, time],
    )
    if "free" in colors:
        out["reco_free"] = colors["free"]
    if "static" in colors:
        out["background"] = colors["static"].expand(batch, time, -1, -1, -1)
    for name, mask in masks.items():
        out[f"mask_{name}"] = mask
    return out


def _tile(x: torch.Tensor, kind: str) -> np.ndarray:
    """``[C, H, W]`` -> ``[H, W, 3]`` uint8."""
    x = x.detach().float().cpu()
    x = x / 255.0 if kind == "uint8" else (x + 0.5 if kind == "image" else x)
    x = x.clamp(0, 1)
    if x.shape[0] == 1:
        x = x.expand(3, -1, -1)
    return (x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def prediction_frames(prediction: TensorDictBase, *, sample: int = 0, scale: int = 2) -> list[Image.Image]:
    """One image per time step: truth, prediction, each branch's component and mask side by side.

    Imagined steps get a red frame label; context steps a green one.
    """
    columns = [(label, key, kind) for label, key, kind in _COLUMNS if key in prediction.keys()]
    tile, header = 64 * scale, 14
    frames = []
    for t in range(prediction.shape[1]):
        frame = Image.new("RGB", (tile * len(columns), tile + header), "white")
        draw = ImageDraw.Draw(frame)
        imagined = bool(prediction.get("imagined")[sample, t])
        for c, (label, key, kind) in enumerate(columns):
            draw.text((c * tile + 3, 1), label, fill="black")
            image = Image.fromarray(_tile(prediction.get(key)[sample, t], kind)).resize(
                (tile, tile), Image.NEAREST
            )
            frame.paste(image, (c * tile, header))
        colour = (200, 0, 0) if imagined else (0, 150, 0)
        draw.rectangle([0, header, tile - 1, header + tile - 1], outline=colour, width=2)
        draw.text((tile * len(columns) - 60, 1), f"t={t}{'*' if imagined else ''}", fill=colour)
        frames.append(frame)
    return frames


def save_gif(frames: list[Image.Image], path: str | Path, *, fps: int = 4) -> Path:
    """Write ``frames`` as a looping GIF, atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.gif")
    frames[0].save(tmp, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    tmp.replace(path)
    return path


def prediction_video(prediction: TensorDictBase, *, sample: int = 0) -> torch.Tensor:
    """The frames of :func:`prediction_frames` as a uint8 ``[1, T, 3, H, W]`` tensor for ``Logger.log_video``."""
    frames = [
        torch.from_numpy(np.array(f)).permute(2, 0, 1) for f in prediction_frames(prediction, sample=sample)
    ]
    return torch.stack(frames)[None]
