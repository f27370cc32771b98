"""The CPU fast paths of the world model: the same functions as the reference modules, computed another way.

The paper's equations live in their plain form in :mod:`~isodream_rl.modules.isodream_v2.rssm` (eq. 3),
:mod:`~isodream_rl.modules.isodream_v2.composition` (eq. 4) and :mod:`~isodream_rl.modules.isodream_v2.decoder`. Each class or
function here reproduces one of them, named in its docstring, with the same values within float tolerance,
the same random draws and the same gradients (tests/test_fast_layers.py compares each pair):

* :func:`fast_filter_window` for :func:`~isodream_rl.modules.isodream_v2.rssm.filter_window` (eq. 3): both branches'
  filtering step as one batched computation (:class:`RSSMPair`, :func:`paired_filter_window`), the window's
  loop forward and backward on one thread (:func:`single_threaded`);
* :class:`FusedMaskComposition` for :meth:`~isodream_rl.modules.isodream_v2.composition.MaskComposition.compose_decoded`
  (eq. 4): the softmax-mode composition as one autograd node with a hand-written backward
  (:class:`_SoftmaxComposition`);
* :class:`FastConvDecoder` for :class:`~isodream_rl.modules.isodream_v2.decoder.ConvDecoder`: the first transposed
  convolution (on a 1x1 map) as one matrix product, the other transposed convolutions with their bias added
  outside the convolution;
* :class:`FastRMSNorm` / :class:`FastChannelRMSNorm` for TorchRL's DreamerV3 RMS norms (the DreamerV3 learner's
  MLPs, RSSM heads, image encoder and decoders; :func:`use_fast_rms_norms`): one fused forward kernel and a
  hand-written backward (:class:`_FusedRMSNorm`).

One switch chooses: :class:`~isodream_rl.modules.isodream_v2.world_model.IsoDreamV2WorldModel` builds these when
``IsoDreamV2Config.fast_paths`` is true (the default) and the reference forms when it is false. Where a fast
path does not apply (sigmoid masks, a lone branch, a plain ``nn.GRUCell``) it runs the reference. Measured
gains: docs/architecture.md, "Speed" (``bench/world_model_speed.py``). Iso-Dream's DreamerV3 learner
(:mod:`~isodream_rl.modules.isodream.world_model`, :mod:`~isodream_rl.modules.isodream.behavior`) always builds
:class:`FusedMaskComposition` and the fast RMS norms (``bench/update_speed.py``).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable, Iterator

import torch
from torch import nn
from torch.nn import functional as F

from isodream_rl.modules.isodream_v2.composition import BRANCHES, MaskComposition, compute_dtype, outward
from isodream_rl.modules.isodream_v2.decoder import ConvDecoder
from isodream_rl.modules.isodream_v2.rssm import LayerNormGRUCell, RSSMCell, filter_window, gru_gates, sigmoid2_std

# ---------------------------------------------------------------------------------------------------------------
# eq. 3: the filter over a window (reference: rssm.filter_window)


@contextlib.contextmanager
def _num_threads(count: int) -> Iterator[None]:
    previous = torch.get_num_threads()
    if previous == count:
        yield
        return
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class _SingleThreaded(torch.autograd.Function):
    """Runs ``fn`` forward and its graph backward with one intra-op thread (see :func:`single_threaded`)."""

    @staticmethod
    def forward(ctx, fn, keys: list, num_args: int, *tensors: torch.Tensor):
        args = [t.detach().requires_grad_() if t.requires_grad else t for t in tensors[:num_args]]
        with torch.enable_grad(), _num_threads(1):
            outputs = fn(*args)
        keys.extend(outputs)
        ctx.set_materialize_grads(False)
        ctx.inner = (args + list(tensors[num_args:]), [outputs[k] for k in keys])
        return tuple(outputs[k].detach() for k in keys)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor | None):
        inputs, outputs = ctx.inner
        del ctx.inner
        pairs = [(o, g) for o, g in zip(outputs, grads) if g is not None and o.requires_grad]
        wanted = [i for i, t in enumerate(inputs) if t.requires_grad]
        result: list[torch.Tensor | None] = [None] * len(inputs)
        if pairs and wanted:
            with _num_threads(1):
                got = torch.autograd.grad(
                    [o for o, _ in pairs],
                    [inputs[i] for i in wanted],
                    [g for _, g in pairs],
                    allow_unused=True,
                )
            for i, g in zip(wanted, got):
                result[i] = g
        return (None, None, None, *result)


def single_threaded(
    fn: Callable[..., dict[str, torch.Tensor]],
    args: Iterable[torch.Tensor],
    parameters: Iterable[torch.Tensor],
) -> dict[str, torch.Tensor]:
    """``fn(*args)`` (a recurrent rollout returning a dict of tensors), forward and backward on one thread.

    A time loop over a ``[B, .]`` state runs thousands of tiny operations (``16 x 200`` matrices at paper
    size) that gain nothing from several threads; each one that does go parallel (MKL products,
    layer norm, reductions) waits for every thread of the pool, and on a machine whose cores are shared
    with other processes that wait is a scheduler time slice per operation. This runs the loop's forward
    and, through a custom autograd function, its backward with ``torch.set_num_threads(1)``, restoring the
    previous count afterwards; the convolutions outside keep all threads. The result is the same function
    with the same gradients. Limitation: the inner graph is freed by the first backward, so a second
    backward through it (``retain_graph=True``) is not supported.

    Args:
        fn: the rollout; it reads ``parameters`` through its closure.
        args: its tensor arguments (gradients flow back to those that require them).
        parameters: the parameters ``fn`` uses, so that their gradients are produced.
    """
    args, parameters = list(args), [p for p in parameters if p.requires_grad]
    needs_graph = torch.is_grad_enabled() and any(t.requires_grad for t in args + parameters)
    if torch.get_num_threads() == 1 or not needs_graph:
        with _num_threads(1):
            return fn(*args)
    keys: list[str] = []
    outputs = _SingleThreaded.apply(fn, keys, len(args), *args, *parameters)
    return dict(zip(keys, outputs))


#: The outputs of :meth:`~isodream_rl.modules.isodream_v2.rssm.RSSMCell.observe_step`.
OUT_KEYS = (
    "belief",
    "prior_mean",
    "prior_std",
    "prior_state",
    "posterior_mean",
    "posterior_std",
    "state",
)


def can_pair(control: RSSMCell, free: RSSMCell | None) -> bool:
    """Whether :class:`RSSMPair` applies: two layer-norm-GRU cells of equal sizes, the second action-free."""
    return (
        free is not None
        and isinstance(control.gru, LayerNormGRUCell)
        and isinstance(free.gru, LayerNormGRUCell)
        and free.action_dim == 0
        and (control.state_dim, control.belief_dim, control.min_std)
        == (free.state_dim, free.belief_dim, free.min_std)
        and control.transition_in.out_features == free.transition_in.out_features
        and control.gru.norm.eps == free.gru.norm.eps
    )


class RSSMPair:
    """One filtering step of the controllable and the action-free branch, batched over the two.

    Reproduces :meth:`~isodream_rl.modules.isodream_v2.rssm.RSSMCell.observe_step` (eq. 3) of both cells, in the order
    :func:`~isodream_rl.modules.isodream_v2.rssm.filter_step` calls them. The controllable cell ``GRU_s(h, s, a)`` and
    the action-free cell ``GRU_z(h', z)`` have the same layer shapes except for the action input, so one
    filtering step of both is the same sequence of matrix products on a leading branch dimension of size 2:
    ``bmm`` over stacked weights instead of two calls per layer (the action-free cell's transition input is
    padded with zero columns where the action would be). At paper size this halves the ~30 small operations
    per time step of the window's loop. The pair stacks the cells' own parameters when it is built
    (``torch.stack`` is differentiable), so modules, parameter names and checkpoints are unchanged.

    Args:
        control: the :class:`~isodream_rl.modules.isodream_v2.rssm.ActionConditionedRSSM`.
        free: the :class:`~isodream_rl.modules.isodream_v2.rssm.ActionFreeRSSM` (:func:`can_pair` must hold).

    Build one per rollout (it stacks the current weights); tensors carry a leading branch dimension
    ``[2, B, .]``, index 0 the controllable branch and 1 the noncontrollable one.
    """

    def __init__(self, control: RSSMCell, free: RSSMCell):
        if not can_pair(control, free):
            raise ValueError("RSSMPair needs two layer-norm-GRU cells of equal sizes, the second action-free")
        self.action_dim = control.action_dim
        self.state_dim = control.state_dim
        self.min_std = control.min_std
        self.eps = control.gru.norm.eps
        cells = (control, free)
        free_in = F.pad(free.transition_in.weight, (0, self.action_dim))
        self.transition_weight = torch.stack([control.transition_in.weight, free_in]).transpose(1, 2)
        self.transition_bias = torch.stack([c.transition_in.bias for c in cells])[:, None]
        self.gru_weight = torch.stack([c.gru.linear.weight for c in cells]).transpose(1, 2)
        self.norm_weight = torch.stack([c.gru.norm.weight for c in cells])[:, None]
        self.norm_bias = torch.stack([c.gru.norm.bias for c in cells])[:, None]
        # prior_net[0] and posterior_belief_in both read h_t: one product for the two
        self.belief_weight = torch.stack(
            [torch.cat([c.prior_net[0].weight, c.posterior_belief_in.weight]) for c in cells]
        ).transpose(1, 2)
        self.belief_bias = torch.stack(
            [torch.cat([c.prior_net[0].bias, c.posterior_belief_in.bias]) for c in cells]
        )[:, None]
        self.hidden = control.prior_net[0].out_features
        # prior_net[2] (control, free) and posterior_out (control, free): one product over four
        self.out_weight = torch.stack(
            [control.prior_net[2].weight, free.prior_net[2].weight]
            + [control.posterior_out.weight, free.posterior_out.weight]
        ).transpose(1, 2)
        self.out_bias = torch.stack(
            [control.prior_net[2].bias, free.prior_net[2].bias]
            + [control.posterior_out.bias, free.posterior_out.bias]
        )[:, None]

    def observe_step(
        self,
        state: torch.Tensor,
        belief: torch.Tensor,
        action: torch.Tensor,
        projected_embedding: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """``[2, B, S]`` states, ``[2, B, D]`` beliefs, ``[B, A]`` action, ``[2, B, hidden]`` projected embeddings.

        Returns the keys of :meth:`~isodream_rl.modules.isodream_v2.rssm.RSSMCell.observe_step`, each ``[2, B, .]``.
        """
        batch = state.shape[1]
        padded = torch.cat([action[None], torch.zeros_like(action)[None]]).to(state.dtype)
        x = F.elu(torch.baddbmm(self.transition_bias, torch.cat([state, padded], -1), self.transition_weight))
        # layer-norm GRU (LayerNormGRUCell) with per-branch affine parameters
        parts = torch.bmm(torch.cat([x, belief], -1), self.gru_weight)
        parts = F.layer_norm(parts, parts.shape[-1:], eps=self.eps)
        belief = gru_gates(torch.addcmul(self.norm_bias, parts, self.norm_weight), belief)
        hidden = torch.baddbmm(self.belief_bias, belief, self.belief_weight)
        prior_hidden = F.elu(hidden[..., : self.hidden])
        post_hidden = F.elu(hidden[..., self.hidden :] + projected_embedding)
        raw = torch.baddbmm(self.out_bias, torch.cat([prior_hidden, post_hidden]), self.out_weight)
        mean, std = raw.chunk(2, dim=-1)
        std = sigmoid2_std(std, self.min_std)
        # the draws of RSSMCell.observe_step, branch after branch: control prior, control posterior, ...
        noise = [torch.randn(batch, self.state_dim, dtype=std.dtype, device=std.device) for _ in range(4)]
        eps = torch.stack([noise[0], noise[2], noise[1], noise[3]])
        sample = torch.addcmul(mean, std, eps)
        return {
            "belief": belief,
            "prior_mean": mean[:2],
            "prior_std": std[:2],
            "prior_state": sample[:2],
            "posterior_mean": mean[2:],
            "posterior_std": std[2:],
            "state": sample[2:],
        }


def paired_filter_window(
    control: RSSMCell,
    free: RSSMCell | None,
    control_proj: torch.Tensor,
    free_proj: torch.Tensor | None,
    action: torch.Tensor,
    is_init: torch.Tensor | None,
) -> dict[str, torch.Tensor]:
    """:func:`~isodream_rl.modules.isodream_v2.rssm.filter_window` (eq. 3) with :class:`RSSMPair` steps.

    Same arguments and outputs as the reference, with the same values, random draws and gradients.

    Raises:
        ValueError: ``free`` or ``free_proj`` is missing, or the cells cannot be paired (:func:`can_pair`).
    """
    if free_proj is None or not can_pair(control, free):
        raise ValueError(
            "paired_filter_window needs two pairable cells (see can_pair) and the free branch's embeddings"
        )
    batch, time = action.shape[:2]
    # unbind, not [:, t]: its backward is one stack, where indexing writes a zero-filled window per step
    actions = action.unbind(1)
    resets = [None] * time if is_init is None else is_init.bool().unbind(1)
    state, belief = control.initial((batch,), device=action.device)
    pair = RSSMPair(control, free)
    free_state, free_belief = free.initial((batch,), device=action.device)
    state, belief = torch.stack([state, free_state]), torch.stack([belief, free_belief])
    projections = torch.stack([control_proj, free_proj]).unbind(2)
    steps = []
    for t in range(time):
        act = actions[t]
        if resets[t] is not None:
            keep = (~resets[t]).to(action.dtype)
            state, belief, act = state * keep, belief * keep, act * keep
        out = pair.observe_step(state, belief, act, projections[t])
        steps.append(out)
        state, belief = out["state"], out["belief"]
    result = {}
    for key in OUT_KEYS:
        result[key], result[f"free_{key}"] = torch.stack([s[key] for s in steps], dim=2).unbind(0)
    return result


def fast_filter_window(
    control: RSSMCell,
    free: RSSMCell | None,
    control_proj: torch.Tensor,
    free_proj: torch.Tensor | None,
    action: torch.Tensor,
    is_init: torch.Tensor | None,
) -> dict[str, torch.Tensor]:
    """:func:`~isodream_rl.modules.isodream_v2.rssm.filter_window` (eq. 3) on one thread (:func:`single_threaded`), with
    :func:`paired_filter_window` where the cells pair (:func:`can_pair`) and the reference elsewhere.

    Same arguments and outputs as the reference, with the same values, random draws and gradients.
    """
    given = {"control_proj": control_proj, "free_proj": free_proj, "action": action, "is_init": is_init}
    names = [k for k, v in given.items() if v is not None]
    cells = [c for c in (control, free) if c is not None]
    rollout = paired_filter_window if free_proj is not None and can_pair(control, free) else filter_window

    def run(*tensors: torch.Tensor) -> dict[str, torch.Tensor]:
        return rollout(control, free, **{**dict.fromkeys(given), **dict(zip(names, tensors))})

    return single_threaded(run, [given[k] for k in names], [p for c in cells for p in c.parameters()])


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
    """:class:`~isodream_rl.modules.isodream_v2.composition.MaskComposition` whose
    :meth:`~isodream_rl.modules.isodream_v2.composition.MaskComposition.compose_decoded` (eq. 4) runs
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

    Reproduces :meth:`~isodream_rl.modules.isodream_v2.composition.MaskComposition.bound` then
    :meth:`~isodream_rl.modules.isodream_v2.composition.MaskComposition.forward` in softmax mode.
    Forward, per pixel: ``c_i = clamp(rgb_i)``, ``m = softmax(l)`` over branches, ``y = sum_i m_i c_i``.
    Backward, with ``g = dL/dy`` and ``q_i = <g, c_i> + dL/dm_i`` (sum over RGB):
    ``dL/drgb_i = (g m_i + dL/dc_i) * [rgb_i in range]`` and ``dL/dl_i = m_i (q_i - sum_j m_j q_j)``.

    Autograd through the separate operations makes ~25 passes over ``[N, 3, 64, 64]`` tensors, many of
    them broadcasting a mask over the innermost channel of a channels-last decoder output (a 3-wide inner
    loop). Here each decoder output is made planar once and its gradient is returned in the output's own
    memory format, so the transposed convolutions get the layout they were run in.

    Inputs: ``bounds`` (clamp range or ``None``), the ``lead`` shape of each branch, then each branch's
    output flattened to ``[prod(lead), 4, H, W]``.
    """

    @staticmethod
    def forward(ctx, bounds, inward, leads, *raw):
        shape = torch.broadcast_shapes(*leads)
        ctx.inward = inward
        size = raw[0].shape[-2:]
        ctx.formats = [memory_format_of(r) for r in raw]
        ctx.dtypes = [r.dtype for r in raw]
        ctx.leads, ctx.bounds = leads, bounds
        dtype = compute_dtype(*ctx.dtypes)
        colors = []
        for r, lead in zip(raw, leads):
            # written planar (and in float32) whatever the decoder's layout and dtype, in one pass: the
            # products below then run over whole planes
            color = r.new_empty(r.shape[0], 3, *size, dtype=dtype).copy_(r[:, :3])
            if bounds is not None:
                color.clamp_(*bounds)
            colors.append(color.view(*lead, 3, *size))
        logits = raw[0].new_empty(*shape, len(raw), *size, dtype=dtype)
        for i, (r, lead) in enumerate(zip(raw, leads)):
            logits[..., i : i + 1, :, :].copy_(r[:, 3:].reshape(*lead, 1, *size).expand(*shape, 1, *size))
        masks = torch.softmax(logits, dim=-3)
        composite = colors[0] * masks[..., 0:1, :, :]
        for i in range(1, len(colors)):
            composite.addcmul_(colors[i], masks[..., i : i + 1, :, :])
        ctx.save_for_backward(masks, *colors)
        ctx.set_materialize_grads(False)
        return (composite, masks, *colors)

    @staticmethod
    def backward(ctx, grad_composite, grad_masks, *grad_colors):
        masks, *colors = ctx.saved_tensors
        size = masks.shape[-2:]
        grads = []
        q = []
        for i, color in enumerate(colors):
            m_i = masks[..., i : i + 1, :, :]
            g = None
            if grad_composite is not None:
                g = (grad_composite * m_i).sum_to_size(color.shape)
            if grad_colors[i] is not None:
                g = grad_colors[i].clone() if g is None else g.add_(grad_colors[i])
            if g is not None and ctx.bounds is not None:
                if ctx.inward:
                    g = g.masked_fill_(outward(g, color, *ctx.bounds), 0.0)
                else:
                    # zero outside the range; a clamped colour sits exactly on a bound, an unclamped one inside
                    g = torch.ops.aten.hardtanh_backward.grad_input(g, color, *ctx.bounds, grad_input=g)
            grads.append(g)
            q_i = None
            if grad_composite is not None:
                q_i = grad_composite[..., 0:1, :, :] * color[..., 0:1, :, :]
                for c in (1, 2):
                    q_i = q_i.addcmul_(grad_composite[..., c : c + 1, :, :], color[..., c : c + 1, :, :])
            if grad_masks is not None:
                g_m = grad_masks[..., i : i + 1, :, :]
                q_i = g_m.clone() if q_i is None else q_i.add_(g_m)
            q.append(q_i)
        logits = [None] * len(colors)
        if any(q_i is not None for q_i in q):
            q = [torch.zeros_like(masks[..., :1, :, :]) if q_i is None else q_i for q_i in q]
            # dL/dl_i = m_i (q_i - sum_j m_j q_j), the softmax's Jacobian
            mean = q[0] * masks[..., 0:1, :, :]
            for i in range(1, len(q)):
                mean.addcmul_(q[i], masks[..., i : i + 1, :, :])
            logits = [
                (q[i] - mean).mul_(masks[..., i : i + 1, :, :]).sum_to_size(*lead, 1, *size)
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


# ---------------------------------------------------------------------------------------------------------------
# the branch decoders (reference: decoder.ConvDecoder)


class FastConvDecoder(ConvDecoder):
    """:class:`~isodream_rl.modules.isodream_v2.decoder.ConvDecoder` (the decoders ``Dec_phi1..3`` of eq. 4) with the same
    layers, parameters and state dict, computed another way; same values and gradients.

    * The first transposed convolution sees a 1x1 map: it is an outer product, computed as one matrix
      product (``addmm``) instead of a oneDNN convolution. With channels-last weights (stored
      ``[Cin, kh, kw, Cout]``) the product is already the channels-last ``[N, Cout, kh, kw]`` map, with no
      copy of the weight or of the output.
    * The other transposed convolutions add their bias outside the convolution (:func:`_transposed_conv`).
    """

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        hidden = torch.relu(self.linear(latent))
        first = self.deconv[1]
        weight, (cin, cout, kh, kw) = first.weight, first.weight.shape
        if weight.is_contiguous(memory_format=torch.channels_last):
            flat = weight.permute(0, 2, 3, 1).reshape(cin, -1)
            x = torch.addmm(first.bias.repeat(kh * kw), hidden, flat)
            x = x.view(-1, kh, kw, cout).permute(0, 3, 1, 2)
        else:
            x = torch.addmm(first.bias.repeat_interleave(kh * kw), hidden, weight.reshape(cin, -1))
            x = x.view(-1, cout, kh, kw)
        for layer in self.deconv[2:]:
            x = _transposed_conv(layer, x) if isinstance(layer, nn.ConvTranspose2d) else layer(x)
        return x


def _transposed_conv(layer: nn.ConvTranspose2d, x: torch.Tensor) -> torch.Tensor:
    """``layer(x)`` with the bias added outside the convolution.

    The same function; PyTorch's CPU (oneDNN) transposed convolution computes its bias gradient by a slower
    route than a plain sum over ``grad``. The in-place add is safe: the convolution's backward needs its
    input and weight, not its output. The bias is cast to the output's dtype first (as autocast casts a
    convolution's bias): a float32 bias added in place to a bfloat16 output takes a mixed-dtype path.
    """
    out = F.conv_transpose2d(
        x,
        layer.weight,
        None,
        stride=layer.stride,
        padding=layer.padding,
        output_padding=layer.output_padding,
        groups=layer.groups,
        dilation=layer.dilation,
    )
    return out if layer.bias is None else _add_channel_bias_(out, layer.bias.to(out.dtype))


_FEW_CHANNELS = 8
_REDUCED = (torch.bfloat16, torch.float16)


def _add_channel_bias_(out: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``out += bias[:, None, None]`` in place, ``out`` ``[N, C, H, W]``, ``bias`` ``[C]`` of ``out``'s dtype.

    A channels-last bf16/fp16 map with few channels (the RGB + logit layer) gets the bias as a ``[H * W * C]``
    pattern added to its ``[N, H * W * C]`` rows, instead of broadcasting ``[C, 1, 1]`` there (an inner loop
    of C elements). Everywhere else (float32 included) the plain broadcast.
    """
    n, c, h, w = out.shape
    if c <= _FEW_CHANNELS and out.dtype in _REDUCED and memory_format_of(out) == torch.channels_last:
        out.permute(0, 2, 3, 1).reshape(n, h * w * c).add_(bias.repeat(h * w))
        return out
    return out.add_(bias[:, None, None])


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
