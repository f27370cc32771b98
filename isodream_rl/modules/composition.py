"""Mask composition of the branch components into one image (paper eq. 4).

``o^_t = M^s_t * o^s_t + M^z_t * o^z_t + (1 - M^s_t - M^z_t) * o^b``.

Two ways to produce the masks:

* ``"softmax"`` (default): one logit map per branch (the static branch has its own), softmax over the
  branches, so every mask is non-negative and the three sum to one at every pixel.
* ``"sigmoid"``: the authors' code: independent sigmoids ``M^s = sigmoid(l^s)``, ``M^z = sigmoid(l^z)`` and
  ``M^b = 1 - M^s - M^z``, which is unclamped and can be negative (isodream_reference.md §14.2).

Components are clamped to the pixel range ``[-0.5, 0.5]`` before they are mixed (``clamp_components``, as
in the authors' code; the gradient is zero outside the range). Unbounded components let a faint mask
times an out-of-range colour reproduce an object, and the masks then stay soft and never separate the
scene: on the sprites scene every mask stayed below 0.5 for 4000 updates without the clamp.
"""

from __future__ import annotations

import torch
from torch import nn

MASK_MODES = ("softmax", "sigmoid")
BRANCHES = ("control", "free", "static")
#: The preprocessed pixel range (``isodream_rl.modules.encoder.preprocess_pixels``).
PIXEL_RANGE = (-0.5, 0.5)


class MaskComposition(nn.Module):
    """Compose per-branch RGB components with their masks (eq. 4).

    Args:
        mask_mode: ``"softmax"`` or ``"sigmoid"`` (see the module docstring).
        clamp_components: clamp each component to ``PIXEL_RANGE`` when two or more branches are composed
            (:meth:`bound`); a single branch (the DreamerV2 ablation) is left as decoded, like TorchRL's.

    Forward:
        ``colors`` and ``logits`` map branch names (``"control"``, ``"free"``, ``"static"``; any subset
        with ``"control"``) to ``[*N, 3, H, W]`` components and ``[*N, 1, H, W]`` mask logits; tensors
        broadcast against each other (a per-window background ``[B, 1, 3, H, W]`` against ``[B, T, ...]``
        components). In sigmoid mode the static branch needs no logit. ``bounded=True``: ``colors`` already
        went through :meth:`bound` (callers that also keep the components).

    Returns:
        ``(composite [*N, 3, H, W], masks)`` with ``masks[name]`` of shape ``[*N, 1, H, W]``.
    """

    def __init__(self, *, mask_mode: str = "softmax", clamp_components: bool = True):
        super().__init__()
        if mask_mode not in MASK_MODES:
            raise ValueError(f"unknown mask_mode {mask_mode!r}; valid: {MASK_MODES}")
        self.mask_mode = mask_mode
        self.clamp_components = clamp_components

    def bound(self, colors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The components as :meth:`forward` mixes them: clamped to ``PIXEL_RANGE`` (see ``clamp_components``)."""
        if not self.clamp_components or len(colors) < 2:
            return dict(colors)
        return {name: color.clamp(*PIXEL_RANGE) for name, color in colors.items()}

    def forward(
        self, colors: dict[str, torch.Tensor], logits: dict[str, torch.Tensor], *, bounded: bool = False
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        if not bounded:
            colors = self.bound(colors)
        names = [name for name in BRANCHES if name in colors]
        if "control" not in names:
            raise KeyError("the controllable component is required for the composition")
        if len(names) == 1:
            color = colors["control"]
            return color, {"control": torch.ones_like(color[..., :1, :, :])}
        shape = torch.broadcast_shapes(
            *(colors[n].shape[:-3] for n in names), *(logits[n].shape[:-3] for n in logits)
        )
        if self.mask_mode == "softmax":
            # One [*N, branches, H, W] tensor and one softmax; the masks are channel views of it.
            stacked = torch.cat([logits[n].expand(*shape, *logits[n].shape[-3:]) for n in names], dim=-3)
            masks = dict(zip(names, torch.softmax(stacked, dim=-3).split(1, dim=-3)))
        else:
            if names[-1] != "static":
                raise ValueError(
                    "mask_mode='sigmoid' composes against the static background branch; enable it"
                )
            masks = {n: torch.sigmoid(logits[n]).expand(*shape, *logits[n].shape[-3:]) for n in names[:-1]}
            masks["static"] = 1.0 - sum(masks.values())
        # colors first: the products take the colors' memory layout (channels-last from the decoders),
        # so the gradients reach the convolutions without a layout copy
        composite = colors[names[0]] * masks[names[0]]
        for name in names[1:]:
            composite = composite + colors[name] * masks[name]
        return composite, masks
