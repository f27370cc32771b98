"""Mask composition of the branch components into one image (paper eq. 4).

``o^_t = M^s_t * o^s_t + M^z_t * o^z_t + (1 - M^s_t - M^z_t) * o^b``.

Two ways to produce the masks:

* ``"softmax"`` (default): one logit map per branch (the static branch has its own), softmax over the
  branches, so every mask is non-negative and the three sum to one at every pixel.
* ``"sigmoid"``: the authors' code: independent sigmoids ``M^s = sigmoid(l^s)``, ``M^z = sigmoid(l^z)`` and
  ``M^b = 1 - M^s - M^z``, which is unclamped and can be negative.

Components are clamped to the pixel range ``[-0.5, 0.5]`` before they are mixed (``clamp_components``, as
in the authors' code; the gradient is zero outside the range). Unbounded components let a faint mask
times an out-of-range colour reproduce an object, and the masks then stay soft and never separate the
scene: on the sprites scene every mask stayed below 0.5 for 4000 updates without the clamp.

A softmax saturates: a branch whose mask went to ~0 on a region gets ~0 gradient there, for its colour and
its logit. The logits' gradients are always the exact ones: lifting them towards a shut-out branch made
training diverge on the sprites scene (docs/results/world_model_demo.md).

:meth:`MaskComposition.compose_decoded` composes straight from the decoders' ``RGB + logit`` outputs, the
operations one by one (:meth:`MaskComposition.bound`, then :meth:`MaskComposition.forward`): the reference
form. The world models build :class:`~isodream_rl.modules.fast_paths.FusedMaskComposition` instead when
``IsoDreamConfig.fast_paths`` / ``IsoDreamV2Config.fast_paths`` is set (the same function, one autograd node in
softmax mode).
"""

from __future__ import annotations

import torch
from torch import nn

MASK_MODES = ("softmax", "sigmoid")
BRANCHES = ("control", "free", "static")
#: What a dynamic branch's decoder may draw at each step: its posterior, or its one-step prior (both learners).
DECODER_STATES = ("posterior", "prior")
#: The preprocessed pixel range (``isodream_rl.modules.pixels.preprocess_pixels``).
PIXEL_RANGE = (-0.5, 0.5)
CLAMP_GRADIENTS = ("zero", "inward")


def outward(grad: torch.Tensor, value: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """Where ``"inward"`` mode stops the gradient of ``clamp(x, low, high)`` (bool): on or beyond a bound where a
    descent step would push ``x`` further out (``grad <= 0`` at the top, ``grad >= 0`` at the bottom); the
    complement of :func:`inward_pass`."""
    return ((value >= high) & (grad <= 0)) | ((value <= low) & (grad >= 0))


def inward_pass(grad: torch.Tensor, value: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """Where the gradient of ``clamp(x, low, high)`` passes in ``"inward"`` mode, as 0/1 of ``grad``'s dtype:
    inside the range, and on or beyond a bound where a descent step (``x -= lr * grad``) moves ``x`` back
    towards the range (``grad > 0`` at the top, ``grad < 0`` at the bottom). ``value`` may be ``x`` or the
    clamped ``x`` (the same answer)."""
    return (~outward(grad, value, low, high)).to(grad.dtype)


def inward_grad(grad: torch.Tensor, value: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """``grad * inward_pass(grad, value, low, high)``: the gradient ``"inward"`` mode passes.

    The same values (a stopped entry is ``+0.0`` where the product gives ``-0.0`` for a negative ``grad``) in
    fewer passes over the tensor: four comparisons and three logical ops on bytes, then one masked fill, where
    the product form makes six comparisons, five logical ops, a cast and a multiplication (about 3x slower on a
    ``[512, 3, 64, 64]`` gradient on one CPU core). A NaN ``value`` passes its gradient here, where the product
    form stops it (the loss is NaN then, and the update skipped).
    """
    return grad.masked_fill(outward(grad, value, low, high), 0.0)


class _InwardClamp(torch.autograd.Function):
    """``x.clamp(low, high)`` whose backward passes the gradients that point back into the range."""

    @staticmethod
    def forward(ctx, x, low, high):
        out = x.clamp(low, high)
        ctx.save_for_backward(out)
        ctx.bounds = (low, high)
        return out

    @staticmethod
    def backward(ctx, grad):
        (out,) = ctx.saved_tensors
        return inward_grad(grad, out, *ctx.bounds), None, None


class MaskComposition(nn.Module):
    """Compose per-branch RGB components with their masks (eq. 4).

    Args:
        mask_mode: ``"softmax"`` or ``"sigmoid"`` (see the module docstring).
        clamp_components: clamp each component to ``pixel_range`` when two or more branches are composed
            (:meth:`bound`); a single branch (the DreamerV2 ablation) is left as decoded, like TorchRL's.
        clamp_gradient: backward of the clamp (no effect without it): ``"inward"`` (the forward unchanged; a
            colour outside the range gets the gradients that move it back towards the range, so a branch whose
            colours all overshoot where its mask is shut can come back) or ``"zero"`` (a plain clamp: no
            gradient to a colour outside the range, in either direction).
        pixel_range: the units of the components and of the composite: ``PIXEL_RANGE`` (``[-0.5, 0.5]``, the
            preprocessed pixels) or, e.g., ``(0.0, 1.0)`` for components in ``pixels / 255`` units (TorchRL's
            DreamerV3 decoders). Eq. 4 commutes with a shift of every component (the masks sum to one), so
            composing in the decoders' own units equals shifting them into ``PIXEL_RANGE``, composing and
            shifting back, without three image-sized passes each way.

    Forward:
        ``colors`` and ``logits`` map branch names (``"control"``, ``"free"``, ``"static"``; any subset
        with ``"control"``) to ``[*N, 3, H, W]`` components and ``[*N, 1, H, W]`` mask logits; tensors
        broadcast against each other (a per-window background ``[B, 1, 3, H, W]`` against ``[B, T, ...]``
        components). In sigmoid mode the static branch needs no logit. ``bounded=True``: ``colors`` already
        went through :meth:`bound` (callers that also keep the components).

    Returns:
        ``(composite [*N, 3, H, W], masks)`` with ``masks[name]`` of shape ``[*N, 1, H, W]``.
    """

    def __init__(
        self,
        *,
        mask_mode: str = "softmax",
        clamp_components: bool = True,
        clamp_gradient: str = "inward",
        pixel_range: tuple[float, float] = PIXEL_RANGE,
    ):
        super().__init__()
        if mask_mode not in MASK_MODES:
            raise ValueError(f"unknown mask_mode {mask_mode!r}; valid: {MASK_MODES}")
        if clamp_gradient not in CLAMP_GRADIENTS:
            raise ValueError(f"unknown clamp_gradient {clamp_gradient!r}; valid: {CLAMP_GRADIENTS}")
        self.mask_mode = mask_mode
        self.clamp_components = clamp_components
        self.clamp_gradient = clamp_gradient
        self.pixel_range = tuple(pixel_range)

    def bound(self, colors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The components as :meth:`forward` mixes them: clamped to ``pixel_range`` (see ``clamp_components``)."""
        if not self.clamp_components or len(colors) < 2:
            return dict(colors)
        if self.clamp_gradient == "inward":
            return {name: _InwardClamp.apply(color, *self.pixel_range) for name, color in colors.items()}
        return {name: color.clamp(*self.pixel_range) for name, color in colors.items()}

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
            probs = torch.softmax(stacked, dim=-3)
            masks = dict(zip(names, probs.split(1, dim=-3)))
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

    def compose_decoded(
        self, outputs: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Eq. 4 from the decoders' raw outputs: :meth:`bound`, then :meth:`forward`.

        Args:
            outputs: branch name -> decoder output ``[*lead, C, H, W]`` with ``C = 4`` (RGB + mask logit)
                or ``C = 3`` (no logit: a lone controllable branch, the static branch in sigmoid mode);
                the ``lead`` shapes broadcast (``[B, T]`` dynamic branches, ``[B, 1]`` background). Any
                floating dtype: a bf16/fp16 decoder output is composed in float32 (its gradient is returned
                in its own dtype).

        Returns:
            ``(composite, masks, colors)``: the composite ``[*N, 3, H, W]``, the masks ``[*N, 1, H, W]`` and
            the components as mixed (clamped, see :meth:`bound`) ``[*lead, 3, H, W]``, keyed by branch name.
            Gradients flow from all three.
        """
        names = [name for name in BRANCHES if name in outputs]
        outputs = {n: outputs[n].to(compute_dtype(outputs[n].dtype)) for n in names}
        colors = {n: outputs[n][..., :3, :, :] for n in names}
        logits = {n: outputs[n][..., 3:, :, :] for n in names if outputs[n].shape[-3] == 4}
        colors = self.bound(colors)
        composite, masks = self(colors, logits, bounded=True)
        return composite, masks, colors


def compute_dtype(*dtypes: torch.dtype) -> torch.dtype:
    """float32, or a wider floating dtype among ``dtypes``: the composition and the image loss never run in
    bf16/fp16."""
    out = torch.float32
    for dtype in dtypes:
        out = torch.promote_types(out, dtype)
    return out
