"""The DreamerV2-style world model's CPU fast paths: the same functions as its reference modules, computed another way.

Each class or function here reproduces one of the plain forms, named in its docstring, with the same values within
float tolerance, the same random draws and the same gradients (tests/test_fast_layers.py compares each pair):

* :func:`fast_filter_window` for :func:`~isodream_rl.modules.isodream_v2.rssm.filter_window` (eq. 3): both branches'
  filtering step as one batched computation (:class:`RSSMPair`, :func:`paired_filter_window`), the window's
  loop forward and backward on one thread (:func:`single_threaded`);
* :class:`FastConvDecoder` for :class:`~isodream_rl.modules.isodream_v2.decoder.ConvDecoder`: the first transposed
  convolution (on a 1x1 map) as one matrix product, the other transposed convolutions with their bias added
  outside the convolution.

One switch chooses: :class:`~isodream_rl.modules.isodream_v2.world_model.IsoDreamV2WorldModel` builds these (and
:class:`~isodream_rl.modules.fast_paths.FusedMaskComposition`) when ``IsoDreamV2Config.fast_paths`` is true (the
default) and the reference forms when it is false. Where a fast path does not apply (a lone branch, a plain
``nn.GRUCell``) it runs the reference. Measured gains: docs/architecture.md, "Speed" (``bench/world_model_speed.py``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator

import torch
from torch import nn
from torch.nn import functional as F

from isodream_rl.modules.fast_paths import memory_format_of
from isodream_rl.modules.isodream_v2.decoder import ConvDecoder
from isodream_rl.modules.isodream_v2.rssm import (
    LayerNormGRUCell,
    RSSMCell,
    filter_window,
    gru_gates,
    sigmoid2_std,
)

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
