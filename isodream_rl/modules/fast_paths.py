"""The CPU fast paths both Iso-Dream learners use: the same functions as the reference forms, computed another way.

Each class or function here reproduces one plain form, named in its docstring, with the same values within float
tolerance and the same gradients (tests/test_fast_layers.py compares each pair):

* :class:`FusedMaskComposition` for :meth:`~isodream_rl.modules.composition.MaskComposition.compose_decoded`
  (eq. 4): the softmax-mode composition as one autograd node with a hand-written backward
  (:class:`_SoftmaxComposition`);
* :class:`FastRMSNorm` / :class:`FastChannelRMSNorm` for TorchRL's DreamerV3 RMS norms (the default learner's
  MLPs, RSSM heads, image encoder and decoders; :func:`use_fast_rms_norms`): one fused forward kernel and a
  hand-written backward (:class:`_FusedRMSNorm`).

The default learner (:mod:`~isodream_rl.modules.isodream.world_model`, :mod:`~isodream_rl.modules.isodream.behavior`)
builds them when ``IsoDreamConfig.fast_paths`` is true (tests/test_isodream.py compares a whole update of it both
ways); the DreamerV2-style world model builds :class:`FusedMaskComposition` with its own fast paths
(:mod:`isodream_rl.modules.isodream_v2.fast_paths`) when ``IsoDreamV2Config.fast_paths`` is true. Both are on by
default and set by a run's ``model.fast_paths``; ``bench/update_speed.py --fast-paths both`` times each learner
both ways. Measured gains: docs/architecture.md, "Speed".
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from isodream_rl.modules.composition import BRANCHES, MaskComposition, compute_dtype

# ---------------------------------------------------------------------------------------------------------------
# eq. 4: the composition (reference: MaskComposition.compose_decoded)


def memory_format_of(x: torch.Tensor) -> torch.memory_format:
    """``torch.channels_last`` for a 4-d tensor stored channels-last (and not also contiguous), else contiguous."""
    if x.dim() == 4 and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
        return torch.channels_last
    return torch.contiguous_format


def can_fuse(composition: MaskComposition, outputs: dict[str, torch.Tensor]) -> bool:
    """Whether :func:`fused_compose_decoded` applies: softmax masks and a mask logit for each of two or more
    branches."""
    names = [name for name in BRANCHES if name in outputs]
    return (
        composition.mask_mode == "softmax"
        and len(names) >= 2
        and all(outputs[n].shape[-3] == 4 for n in names)
    )


def fused_compose_decoded(
    composition: MaskComposition, outputs: dict[str, torch.Tensor]
) -> tuple[torch.Tensor, dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """:meth:`MaskComposition.compose_decoded` (eq. 4) of ``composition`` as one autograd node
    (:class:`_SoftmaxComposition`): same arguments, outputs, values and gradients.

    Raises:
        ValueError: where :func:`can_fuse` does not hold.
    """
    if not can_fuse(composition, outputs):
        raise ValueError(
            "fused_compose_decoded needs softmax masks and a mask logit for each of two or more branches"
        )
    names = [name for name in BRANCHES if name in outputs]
    bounds = composition.pixel_range if composition.clamp_components else None
    leads = [tuple(outputs[n].shape[:-3]) for n in names]
    flat = [outputs[n].reshape(-1, *outputs[n].shape[-3:]) for n in names]
    composite, stacked, *colors = _SoftmaxComposition.apply(
        bounds, composition.clamp_gradient == "inward", leads, *flat
    )
    return composite, dict(zip(names, stacked.split(1, dim=-3))), dict(zip(names, colors))


class FusedMaskComposition(MaskComposition):
    """:class:`~isodream_rl.modules.composition.MaskComposition` whose
    :meth:`~isodream_rl.modules.composition.MaskComposition.compose_decoded` (eq. 4) runs
    :func:`fused_compose_decoded` where it applies (:func:`can_fuse`) and the reference elsewhere. Same
    arguments, outputs, values and gradients; :meth:`bound` and :meth:`forward` are the reference's."""

    def compose_decoded(
        self, outputs: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        if can_fuse(self, outputs):
            return fused_compose_decoded(self, outputs)
        return super().compose_decoded(outputs)


class _SoftmaxComposition(torch.autograd.Function):
    """Softmax-mode eq. 4 as one autograd node, forward and backward on planar (NCHW) tensors.

    Reproduces :meth:`~isodream_rl.modules.composition.MaskComposition.bound` then
    :meth:`~isodream_rl.modules.composition.MaskComposition.forward` in softmax mode.
    Forward, per pixel: ``c_i = clamp(rgb_i)``, ``m = softmax(l)`` over branches, ``y = sum_i m_i c_i``.
    Backward, with ``g = dL/dy`` and ``q_i = <g, c_i> + dL/dm_i`` (sum over RGB):
    ``dL/drgb_i = (g m_i + dL/dc_i) * [rgb_i in range]`` and ``dL/dl_i = m_i (q_i - sum_j m_j q_j)``;
    ``"inward"`` mode passes ``dL/drgb_i`` on a bound where it points back into the range
    (:func:`_inward_clamp_grad`).

    Autograd through the separate operations makes ~25 passes over ``[N, 3, 64, 64]`` tensors, many of
    them broadcasting a mask over the innermost channel of a channels-last decoder output (a 3-wide inner
    loop). Here each decoder output is made planar once and its gradient is returned in the output's own
    memory format, so the transposed convolutions get the layout they were run in. In between, every tensor is
    viewed ``[*lead, C, H * W]``: a mask ``[*lead, 1, H * W]`` (a slice of the branches' stacked masks)
    broadcast over the colours then runs as one vectorised row per colour, where the ``[*lead, C, H, W]`` form
    of the same product is ~6x slower on one core (64-wide rows).

    Inputs: ``bounds`` (clamp range or ``None``), the ``lead`` shape of each branch, then each branch's
    output flattened to ``[prod(lead), 4, H, W]``.
    """

    @staticmethod
    def forward(ctx, bounds, inward, leads, *raw):
        shape = torch.broadcast_shapes(*leads)
        ctx.inward = inward
        size = raw[0].shape[-2:]
        pixels = size[0] * size[1]
        ctx.formats = [memory_format_of(r) for r in raw]
        ctx.dtypes = [r.dtype for r in raw]
        ctx.leads, ctx.bounds, ctx.shape, ctx.size = leads, bounds, shape, size
        dtype = compute_dtype(*ctx.dtypes)
        colors = []
        for r, lead in zip(raw, leads):
            # written planar (and in float32) whatever the decoder's layout and dtype, in one pass: the
            # products below then run over whole planes
            color = r.new_empty(r.shape[0], 3, *size, dtype=dtype).copy_(r[:, :3])
            if bounds is not None:
                color.clamp_(*bounds)
            colors.append(color.view(*lead, 3, pixels))
        logits = raw[0].new_empty(*shape, len(raw), pixels, dtype=dtype)
        for i, (r, lead) in enumerate(zip(raw, leads)):
            logits[..., i : i + 1, :].copy_(r[:, 3:].reshape(*lead, 1, pixels).expand(*shape, 1, pixels))
        masks = torch.softmax(logits, dim=-2)
        composite = colors[0] * masks[..., 0:1, :]
        for i in range(1, len(colors)):
            composite.addcmul_(colors[i], masks[..., i : i + 1, :])
        ctx.save_for_backward(masks, *colors)
        ctx.set_materialize_grads(False)
        return (
            composite.view(*shape, 3, *size),
            masks.view(*shape, len(raw), *size),
            *(color.view(*lead, 3, *size) for color, lead in zip(colors, leads)),
        )

    @staticmethod
    def backward(ctx, grad_composite, grad_masks, *grad_colors):
        masks, *colors = ctx.saved_tensors
        shape, size, pixels = ctx.shape, ctx.size, masks.shape[-1]
        if grad_composite is not None:
            grad_composite = grad_composite.reshape(*shape, 3, pixels)
        if grad_masks is not None:
            grad_masks = grad_masks.reshape(*shape, -1, pixels)
        grads = []
        q = []
        for i, (color, lead) in enumerate(zip(colors, ctx.leads)):
            m_i = masks[..., i : i + 1, :]
            g = None
            if grad_composite is not None:
                g = (grad_composite * m_i).sum_to_size(color.shape)
            if grad_colors[i] is not None:
                grad_color = grad_colors[i].reshape(*lead, 3, pixels)
                g = grad_color.clone() if g is None else g.add_(grad_color)
            if g is not None and ctx.bounds is not None:
                if ctx.inward:
                    g = _inward_clamp_grad(g, color, *ctx.bounds)
                else:
                    # zero outside the range; a clamped colour sits exactly on a bound, an unclamped one inside
                    g = torch.ops.aten.hardtanh_backward.grad_input(g, color, *ctx.bounds, grad_input=g)
            grads.append(g)
            q_i = None
            if grad_composite is not None:
                q_i = grad_composite[..., 0:1, :] * color[..., 0:1, :]
                for c in (1, 2):
                    q_i = q_i.addcmul_(grad_composite[..., c : c + 1, :], color[..., c : c + 1, :])
            if grad_masks is not None:
                g_m = grad_masks[..., i : i + 1, :]
                q_i = g_m.clone() if q_i is None else q_i.add_(g_m)
            q.append(q_i)
        logits = [None] * len(colors)
        if any(q_i is not None for q_i in q):
            q = [torch.zeros_like(masks[..., :1, :]) if q_i is None else q_i for q_i in q]
            # dL/dl_i = m_i (q_i - sum_j m_j q_j), the softmax's Jacobian
            mean = q[0] * masks[..., 0:1, :]
            for i in range(1, len(q)):
                mean.addcmul_(q[i], masks[..., i : i + 1, :])
            logits = [
                (q[i] - mean).mul_(masks[..., i : i + 1, :]).sum_to_size(*lead, 1, pixels)
                for i, lead in enumerate(ctx.leads)
            ]
        out = []
        for rgb, logit, lead, memory_format, dtype in zip(grads, logits, ctx.leads, ctx.formats, ctx.dtypes):
            if rgb is None and logit is None:
                out.append(None)
                continue
            count = math.prod(lead)
            # allocated in the decoder output's layout and dtype, filled with two strided copies
            grad = torch.empty(count, 4, *size, dtype=dtype, device=masks.device, memory_format=memory_format)
            for part, value in ((grad[:, :3], rgb), (grad[:, 3:], logit)):
                if value is None:
                    part.zero_()
                else:
                    part.copy_(value.reshape(count, -1, *size))
            out.append(grad)
        return (None, None, None, *out)


def _inward_clamp_grad(grad: torch.Tensor, color: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """``grad`` of the clamped ``color`` (both ``[*N]``, ``color`` in ``[low, high]``) gated as ``"inward"`` mode
    gates it, in place: :func:`~isodream_rl.modules.composition.inward_grad`'s values by float operations only.

    On the top bound only a positive gradient passes (``max(g, 0)``), on the bottom one only a negative one
    (``min(g, 0)``), inside all: ``clamp(g, floor, ceiling)`` with ``floor = 0`` on the top bound and ``-inf``
    elsewhere, ``ceiling = 0`` on the bottom bound and ``+inf`` elsewhere, each made as
    ``nan_to_num((color - bound) * inf, nan=0)`` (``0 * inf`` is NaN exactly on the bound). The comparisons and
    boolean masks of the reference form run ~1 ns per element on one core (not vectorised), these float passes
    ~0.15 ns. A NaN colour stops its gradient here where the reference passes it (its loss is NaN then, and the
    update skipped).

    Returns:
        ``grad``, gated.
    """
    floor = torch.sub(color, high).mul_(math.inf).nan_to_num_(nan=0.0, posinf=math.inf, neginf=-math.inf)
    ceiling = torch.sub(color, low).mul_(math.inf).nan_to_num_(nan=0.0, posinf=math.inf, neginf=-math.inf)
    return grad.clamp_(floor, ceiling)


# ---------------------------------------------------------------------------------------------------------------
# DreamerV3's RMS norms (reference: TorchRL's _DreamerV3RMSNorm / _DreamerV3ChannelRMSNorm, i.e. F.rms_norm)


class _FusedRMSNorm(torch.autograd.Function):
    """``F.rms_norm(x, (C,), weight, eps)`` over the last dim of a float32 ``x`` ``[*N, C]``: the forward as one
    fused kernel (``aten::_fused_rms_norm``, which also returns ``rstd = 1 / sqrt(mean(x^2) + eps)`` ``[*N, 1]``)
    and a hand-written backward, ``x^ = x rstd``, ``dL/dweight = sum_N g x^``,
    ``dL/dx = rstd (g w - x^ mean_C(g w x^))``.

    Why: on CPU, autograd records ``F.rms_norm`` as its decomposition (pow, mean, add, rsqrt, two products and a
    copy), whose backward makes about ten passes over ``x``; this one makes five in the forward and backward
    together, about 1.5x faster on the decoders' ``[512, 32, 32, 16]`` maps on one core (and fewer autograd nodes
    per RSSM step). PyTorch has no CPU kernel for ``aten::_fused_rms_norm_backward``.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, eps: float) -> torch.Tensor:
        out, rstd = torch.ops.aten._fused_rms_norm(x, [x.shape[-1]], weight, eps)
        ctx.save_for_backward(x, rstd, weight)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        x, rstd, weight = ctx.saved_tensors
        channels = x.shape[-1]
        normed = x * rstd
        grad_weight = (grad * normed).reshape(-1, channels).sum(0) if ctx.needs_input_grad[1] else None
        grad_x = None
        if ctx.needs_input_grad[0]:
            scaled = grad * weight
            mean = (scaled * normed).sum(-1, keepdim=True).div_(channels)
            grad_x = torch.addcmul(scaled, normed, mean, value=-1.0).mul_(rstd)
        return grad_x, grad_weight, None


_HAS_FUSED_RMS_NORM = hasattr(torch.ops.aten, "_fused_rms_norm")


def fast_rms_norm(x: torch.Tensor, weight: torch.Tensor, eps: float) -> torch.Tensor:
    """TorchRL's DreamerV3 RMS norm of ``x`` ``[*N, C]`` over its last dim (``F.rms_norm`` in float32, cast back
    to ``x``'s dtype), by :class:`_FusedRMSNorm` for float32 ``x`` and ``weight``; the reference otherwise."""
    if _HAS_FUSED_RMS_NORM and x.dtype == torch.float32 and weight.dtype == torch.float32:
        return _FusedRMSNorm.apply(x, weight, eps)
    return F.rms_norm(x.float(), (weight.shape[0],), weight.float(), eps).to(x.dtype)


class FastRMSNorm(nn.Module):
    """TorchRL's ``_DreamerV3RMSNorm`` (RMS norm over the last dim, a learned scale ``weight``) by
    :func:`fast_rms_norm`; the same parameter and state dict. Build with :meth:`like`."""

    def __init__(self, weight: nn.Parameter, eps: float) -> None:
        super().__init__()
        self.weight, self.eps = weight, eps

    @classmethod
    def like(cls, norm: nn.Module) -> FastRMSNorm:
        """The fast form of ``norm``, sharing its ``weight`` parameter."""
        return cls(norm.weight, norm.eps)

    def forward(self, value: torch.Tensor) -> torch.Tensor:
        return fast_rms_norm(value, self.weight, self.eps)


class FastChannelRMSNorm(FastRMSNorm):
    """TorchRL's ``_DreamerV3ChannelRMSNorm`` (RMS norm over the channels of ``[*N, C, H, W]`` maps) by
    :func:`fast_rms_norm` on the channels-last view; the same parameter and state dict."""

    def forward(self, value: torch.Tensor) -> torch.Tensor:
        return fast_rms_norm(value.movedim(-3, -1), self.weight, self.eps).movedim(-1, -3)


def use_fast_rms_norms(module: nn.Module) -> nn.Module:
    """Replace, in place, every TorchRL DreamerV3 RMS norm module inside ``module`` (``DreamerV3MLP``, the RSSM's
    prior and posterior heads, the image encoder and decoders) by :class:`FastRMSNorm` /
    :class:`FastChannelRMSNorm` sharing its parameter: the same function, parameters and state-dict keys. The
    block GRU's norms, which TorchRL calls as a function, stay as they are. Returns ``module``."""
    try:
        from torchrl.modules.models.model_based import _DreamerV3ChannelRMSNorm, _DreamerV3RMSNorm
    except ImportError:  # another TorchRL: its own norms, unchanged
        return module
    kinds = {_DreamerV3RMSNorm: FastRMSNorm, _DreamerV3ChannelRMSNorm: FastChannelRMSNorm}
    for parent in list(module.modules()):
        for name, child in list(parent.named_children()):
            fast = kinds.get(type(child))
            if fast is not None:
                setattr(parent, name, fast.like(child))
    return module
