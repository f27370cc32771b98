"""The CPU fast paths (``isodream_rl.modules.fast_paths``) compute the same functions as the reference forms they
replace, and a whole world model gives the same losses and gradients with ``fast_paths`` on and off."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from isodream_rl.modules.composition import MaskComposition
from isodream_rl.modules.fast_paths import FusedMaskComposition, fused_compose_decoded
from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel
from isodream_rl.modules.isodream_v2.decoder import ConvDecoder
from isodream_rl.modules.isodream_v2.fast_paths import (
    FastConvDecoder,
    fast_filter_window,
    paired_filter_window,
)
from isodream_rl.modules.isodream_v2.rssm import filter_window


def reference_decoder(decoder: ConvDecoder, latent: torch.Tensor) -> torch.Tensor:
    """The decoder as plain ``nn`` layers: linear, ReLU, then ConvTranspose2d/ReLU (bias inside)."""
    x = torch.relu(decoder.linear(latent))[:, :, None, None]
    for layer in decoder.deconv[1:]:
        x = torch.relu(x) if isinstance(layer, nn.ReLU) else layer(x)
    return x


def grads(module: nn.Module, latent: torch.Tensor, out: torch.Tensor, upstream: torch.Tensor):
    params = [latent, *module.parameters()]
    return torch.autograd.grad(out, params, upstream)


@pytest.mark.parametrize("channels_last", [False, True])
def test_decoder_matches_plain_transposed_convolutions_in_values_and_gradients(channels_last):
    torch.manual_seed(0)
    decoder = FastConvDecoder(in_features=12, out_channels=4, depth=4).double()
    if channels_last:
        decoder.to(memory_format=torch.channels_last)
    latent = torch.randn(5, 12, dtype=torch.float64, requires_grad=True)
    fast, ref = decoder(latent), reference_decoder(decoder, latent)
    # the reference form is the plain layers
    torch.testing.assert_close(ConvDecoder.forward(decoder, latent), ref)
    assert fast.shape == (5, 4, 64, 64)
    torch.testing.assert_close(fast, ref)
    upstream = torch.randn_like(ref)
    for g_fast, g_ref in zip(grads(decoder, latent, fast, upstream), grads(decoder, latent, ref, upstream)):
        torch.testing.assert_close(g_fast, g_ref)


@pytest.mark.parametrize("channels_last", [False, True])
def test_decoder_under_bf16_autocast_matches_the_plain_layers(channels_last):
    """bf16 outputs (the biases, added outside the convolutions, in the output's dtype; the 4-channel layer's
    bias as a repeated pattern when channels-last): values and gradients as the plain layers under the same
    autocast, within bf16 rounding."""
    torch.manual_seed(0)
    decoder = FastConvDecoder(in_features=12, out_channels=4, depth=4)
    with torch.no_grad():  # biases large enough that adding one in the wrong place shows
        for module in decoder.modules():
            if isinstance(module, nn.ConvTranspose2d):
                module.bias.uniform_(-1.0, 1.0)
    if channels_last:
        decoder.to(memory_format=torch.channels_last)
    latent = torch.randn(3, 12, requires_grad=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        fast, ref = decoder(latent), reference_decoder(decoder, latent)
    assert fast.dtype == ref.dtype == torch.bfloat16 and fast.shape == (3, 4, 64, 64)
    torch.testing.assert_close(fast.float(), ref.float(), atol=0.05, rtol=0.02)
    upstream = torch.randn_like(ref)
    for g_fast, g_ref in zip(grads(decoder, latent, fast, upstream), grads(decoder, latent, ref, upstream)):
        assert g_fast.dtype == g_ref.dtype
        assert (g_fast - g_ref).norm() <= 0.1 * g_ref.norm()


def test_decoder_state_dict_keeps_the_layer_names_and_shapes():
    decoder = FastConvDecoder(in_features=12, out_channels=4, depth=4)
    shapes = {k: tuple(v.shape) for k, v in decoder.state_dict().items()}
    assert shapes["deconv.1.weight"] == (128, 16, 5, 5)
    assert shapes["deconv.7.weight"] == (4, 4, 6, 6) and shapes["deconv.7.bias"] == (4,)
    ConvDecoder(in_features=12, out_channels=4, depth=4).load_state_dict(decoder.state_dict())
    FastConvDecoder(in_features=12, out_channels=4, depth=4).load_state_dict(decoder.state_dict())


def test_single_threaded_rollout_has_the_loops_values_and_gradients_and_restores_the_thread_count():
    wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
    rssm_params = [*wm.control_rssm.parameters(), *wm.free_rssm.parameters()]
    control = torch.randn(2, 6, wm.config.hidden_dim, requires_grad=True)
    free = torch.randn(2, 6, wm.config.hidden_dim, requires_grad=True)
    action = torch.randn(2, 6, 2)
    is_init = torch.zeros(2, 6, 1, dtype=torch.bool)
    is_init[1, 3] = True

    def run(rollout):
        torch.manual_seed(0)
        out = rollout(wm.control_rssm, wm.free_rssm, control, free, action, is_init)
        loss = sum((v * torch.linspace(-1, 1, v.shape[-1], dtype=v.dtype)).sum() for v in out.values())
        return out, torch.autograd.grad(loss, [control, free, *rssm_params], allow_unused=True)

    previous = torch.get_num_threads()
    torch.set_num_threads(2)  # the wrapper is a no-op on one thread
    try:
        fast_out, fast_grads = run(fast_filter_window)
        assert torch.get_num_threads() == 2
        ref_out, ref_grads = run(paired_filter_window)
    finally:
        torch.set_num_threads(previous)
    assert fast_out.keys() == ref_out.keys()
    for key in ref_out:
        torch.testing.assert_close(fast_out[key], ref_out[key])
    assert [g is None for g in fast_grads] == [g is None for g in ref_grads]
    assert fast_grads[0] is not None and fast_grads[1] is not None
    for fast, ref in zip(fast_grads, ref_grads):
        if ref is not None:
            torch.testing.assert_close(fast, ref)


def test_paired_rollout_equals_the_branchwise_loop_in_values_and_gradients():
    """paired_filter_window (RSSMPair: both branches in one batched step) against the reference filter_window
    (filter_step: one observe_step per branch and step): same outputs, same random draws, same gradients for
    every RSSM parameter and both embedding projections."""
    wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=3))
    params = [*wm.control_rssm.parameters(), *wm.free_rssm.parameters()]
    with torch.no_grad():  # non-trivial layer-norm affine parameters, different per branch
        for p in params:
            p.add_(0.1 * torch.randn_like(p))
    control = torch.randn(3, 7, wm.config.hidden_dim, requires_grad=True)
    free = torch.randn(3, 7, wm.config.hidden_dim, requires_grad=True)
    action = torch.randn(3, 7, 3)
    is_init = torch.zeros(3, 7, 1, dtype=torch.bool)
    is_init[0, 4] = is_init[2, 1] = True

    def run(paired):
        torch.manual_seed(3)
        rollout = paired_filter_window if paired else filter_window
        out = rollout(wm.control_rssm, wm.free_rssm, control, free, action, is_init)
        loss = sum((v * torch.linspace(-1, 1, v.shape[-1])).sum() for v in out.values())
        # posterior_embed_in is applied outside the loop (project_embedding): no gradient here
        return out, torch.autograd.grad(loss, [control, free, *params], allow_unused=True)

    paired, paired_grads = run(True)
    plain, plain_grads = run(False)
    assert paired.keys() == plain.keys() and len(plain) == 14
    for key in plain:
        torch.testing.assert_close(paired[key], plain[key], msg=key)
    assert [g is None for g in paired_grads] == [g is None for g in plain_grads]
    assert sum(g is not None for g in plain_grads) == 2 + len(params) - 2
    for got, want in zip(paired_grads, plain_grads):
        if want is not None:
            torch.testing.assert_close(got, want)
    # the model's filter (fast_paths=True by default) is the pair, on one thread
    assert wm.filter_window is fast_filter_window
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(3)
        want = paired_filter_window(wm.control_rssm, wm.free_rssm, control, free, action, is_init)["state"]
        torch.manual_seed(3)
        got = wm.filter_window(wm.control_rssm, wm.free_rssm, control, free, action, is_init)["state"]
    finally:
        torch.set_num_threads(previous)
    assert got.equal(want)
    # the pair asked for where it cannot run: an error, not a silent fallback
    with pytest.raises(ValueError, match="paired_filter_window"):
        paired_filter_window(wm.control_rssm, wm.free_rssm, control, None, action, is_init)
    # the model's fast filter falls back to the reference there (a lone branch)
    torch.manual_seed(3)
    alone = fast_filter_window(wm.control_rssm, None, control, None, action, is_init)
    torch.manual_seed(3)
    reference = filter_window(wm.control_rssm, None, control, None, action, is_init)
    assert alone.keys() == reference.keys() and len(alone) == 7
    for key in reference:
        torch.testing.assert_close(alone[key], reference[key], msg=key)


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("clamp", [True, False])
@pytest.mark.parametrize("names", [("control", "free", "static"), ("control", "free"), ("control", "static")])
@pytest.mark.parametrize("clamp_gradient", ["inward", "zero"])
def test_fused_composition_matches_the_plain_operations(channels_last, clamp, names, clamp_gradient):
    """fused_compose_decoded (one autograd node) against the reference compose_decoded (split + clamp + softmax +
    products), values and gradients from every output (composite, masks, components), in the decoders' memory
    format."""
    torch.manual_seed(0)
    batch, time = 2, 3
    leads = {name: (batch, 1) if name == "static" else (batch, time) for name in names}
    raw = {}
    for name, lead in leads.items():
        x = torch.randn(lead[0] * lead[1], 4, 8, 8, dtype=torch.float64)
        if channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        raw[name] = x.requires_grad_()
    composition = MaskComposition(clamp_components=clamp, clamp_gradient=clamp_gradient)
    weights = torch.randn(batch, time, 3, 8, 8, dtype=torch.float64)
    mask_weights = torch.randn(batch, time, 1, 8, 8, dtype=torch.float64)

    def run(fused):
        outputs = {n: raw[n].reshape(*leads[n], 4, 8, 8) for n in names}
        if fused:
            composite, masks, colors = fused_compose_decoded(composition, outputs)
        else:
            composite, masks, colors = composition.compose_decoded(outputs)
        loss = (composite * weights).sum()
        loss = loss + sum((m * mask_weights * (k + 1)).sum() for k, m in enumerate(masks.values()))
        loss = loss + sum(c.pow(2).sum() for c in colors.values())
        return composite, masks, colors, torch.autograd.grad(loss, [raw[n] for n in names])

    fused, plain = run(True), run(False)
    torch.testing.assert_close(fused[0], plain[0])
    for name in names:
        torch.testing.assert_close(fused[1][name], plain[1][name])
        torch.testing.assert_close(fused[2][name], plain[2][name])
    for name, got, want in zip(names, fused[3], plain[3]):
        torch.testing.assert_close(got, want)
        assert got.stride() == raw[name].stride()
    masks = torch.cat(list(fused[1].values()), dim=-3)
    assert masks.min() >= 0
    torch.testing.assert_close(masks.sum(-3), torch.ones_like(masks[..., 0, :, :]))


def test_fused_composition_is_refused_where_it_does_not_apply():
    outputs = {n: torch.randn(2, 3, 4, 8, 8) for n in ("control", "free")}
    outputs["static"] = torch.randn(2, 1, 3, 8, 8)  # sigmoid mode: the background has no logit
    with pytest.raises(ValueError, match="fused_compose_decoded"):
        fused_compose_decoded(MaskComposition(mask_mode="sigmoid"), outputs)
    composition = FusedMaskComposition(mask_mode="sigmoid")
    composite, _, _ = composition.compose_decoded(outputs)  # the reference, chosen here
    assert composite.shape == (2, 3, 3, 8, 8)


def test_fused_composition_passes_only_the_gradients_asked_for():
    """Gradient from the composite alone, and from one mask alone, still matches the plain path."""
    torch.manual_seed(1)
    raw = {n: torch.randn(4, 4, 8, 8, requires_grad=True) for n in ("control", "free")}
    composition = FusedMaskComposition()
    outputs = {n: x.reshape(2, 2, 4, 8, 8) for n, x in raw.items()}
    _, masks, _ = composition.compose_decoded(outputs)
    got = torch.autograd.grad(masks["free"].sum() * 2 + masks["free"].pow(2).sum(), list(raw.values()))
    colors = composition.bound({n: o[..., :3, :, :] for n, o in outputs.items()})
    _, plain_masks = composition(colors, {n: o[..., 3:, :, :] for n, o in outputs.items()}, bounded=True)
    want = torch.autograd.grad(
        plain_masks["free"].sum() * 2 + plain_masks["free"].pow(2).sum(), list(raw.values())
    )
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w)
        torch.testing.assert_close(g[:, :3], torch.zeros_like(g[:, :3]))


@pytest.mark.parametrize("channels_last", [False, True])
def test_fused_composition_reads_bf16_decoder_outputs_and_composes_in_float32(channels_last):
    """bf16 dynamic outputs with a float32 background (the model under bf16 autocast): the same values as
    composing their float32 copies, float32 results, gradients in each output's dtype and layout."""
    torch.manual_seed(2)
    leads = {"control": (2, 3), "free": (2, 3), "static": (2, 1)}
    raw = {}
    for name, lead in leads.items():
        x = torch.randn(
            lead[0] * lead[1], 4, 8, 8, dtype=torch.float32 if name == "static" else torch.bfloat16
        )
        raw[name] = (x.contiguous(memory_format=torch.channels_last) if channels_last else x).requires_grad_()
    composition = FusedMaskComposition(clamp_gradient="inward")
    weights = torch.randn(2, 3, 3, 8, 8)

    def run(inputs):
        composite, masks, colors = composition.compose_decoded(
            {n: x.reshape(*leads[n], 4, 8, 8) for n, x in inputs.items()}
        )
        loss = (composite * weights).sum() + masks["free"].pow(2).sum() + colors["control"].sum()
        return composite, masks, colors, torch.autograd.grad(loss, list(inputs.values()))

    widened = {n: x.detach().float().requires_grad_() for n, x in raw.items()}
    got, want = run(raw), run(widened)
    assert got[0].dtype == torch.float32 and all(m.dtype == torch.float32 for m in got[1].values())
    torch.testing.assert_close(got[0], want[0])
    for name in leads:
        torch.testing.assert_close(got[1][name], want[1][name])
        torch.testing.assert_close(got[2][name], want[2][name])
    for x, g, w in zip(raw.values(), got[3], want[3]):
        assert g.dtype == x.dtype and g.stride() == x.stride()
        torch.testing.assert_close(g, w.to(x.dtype))


def test_inward_clamp_passes_only_the_gradients_that_point_back_into_the_range():
    from isodream_rl.modules.composition import inward_pass

    value = torch.tensor([-0.9, -0.5, -0.5, 0.0, 0.5, 0.5, 0.9, 0.9])
    grad = torch.tensor([-1.0, -1.0, 1.0, 1.0, 1.0, -1.0, 1.0, -1.0])
    # below the range: a negative gradient (descent raises x) passes; above it: a positive one
    assert inward_pass(grad, value, -0.5, 0.5).tolist() == [1, 1, 0, 1, 1, 0, 1, 0]

    torch.manual_seed(2)
    names = ("control", "free", "static")
    leads = {"control": (2, 3), "free": (2, 3), "static": (2, 1)}
    raw = {
        n: (torch.randn(lead[0] * lead[1], 4, 8, 8, dtype=torch.float64) * 1.5) for n, lead in leads.items()
    }
    for x in raw.values():
        x.requires_grad_()
    target = torch.rand(2, 3, 3, 8, 8, dtype=torch.float64) - 0.5

    def grads(mode, fused=True):
        composition = MaskComposition(clamp_gradient="zero" if mode == "straight_through" else mode)
        outputs = {n: raw[n].reshape(*leads[n], 4, 8, 8) for n in names}
        if fused:
            composite, _, _ = fused_compose_decoded(composition, outputs)
        else:
            colors = {n: o[..., :3, :, :] for n, o in outputs.items()}
            if mode == "straight_through":  # clamped forward, identity backward: the gradient before gating
                colors = {n: c + (c.clamp(-0.5, 0.5) - c).detach() for n, c in colors.items()}
            else:
                colors = composition.bound(colors)
            logits = {n: o[..., 3:, :, :] for n, o in outputs.items()}
            composite, _ = composition(colors, logits, bounded=True)
        return torch.autograd.grad((composite - target).pow(2).sum(), [raw[n] for n in names])

    inward, plain, zero = grads("inward"), grads("inward", fused=False), grads("zero")
    full = grads("straight_through", fused=False)
    for name, got, want, closed, ungated in zip(names, inward, plain, zero, full):
        torch.testing.assert_close(got, want)  # the fused node and the plain operations agree
        rgb = raw[name][:, :3].detach()
        expected = ungated[:, :3] * inward_pass(ungated[:, :3], rgb, -0.5, 0.5)
        torch.testing.assert_close(got[:, :3], expected)
        torch.testing.assert_close(got[:, 3:], closed[:, 3:])  # the logits' gradients are unchanged
        outside = rgb.abs() > 0.5
        assert (closed[:, :3][outside] == 0).all()  # a plain clamp passes nothing beyond the range
        assert (got[:, :3][outside] != 0).any()  # the inward one passes some
    with pytest.raises(ValueError, match="clamp_gradient"):
        MaskComposition(clamp_gradient="straight")


@pytest.mark.parametrize("bounds", [(0.0, 1.0), (-0.5, 0.5)])
def test_inward_clamp_gradient_by_float_operations_matches_the_boolean_form(bounds):
    """fast_paths._inward_clamp_grad (the fused composition's ``"inward"`` gate, float passes only) against the
    reference composition.inward_grad (comparisons and a masked fill), on colours on both bounds and inside and
    gradients of either sign and zero: the same values."""
    from isodream_rl.modules.composition import inward_grad
    from isodream_rl.modules.fast_paths import _inward_clamp_grad

    torch.manual_seed(4)
    low, high = bounds
    color = (torch.rand(2, 3, 3, 64) * 1.6 - 0.3) * (high - low) + low
    color = color.clamp(low, high)  # the node gates the clamped colour: a third of it on a bound
    grad = torch.randn(2, 3, 3, 64)
    grad[..., ::7] = 0.0
    assert (color == low).any() and (color == high).any()
    expected = inward_grad(grad, color, low, high)
    got = _inward_clamp_grad(grad.clone(), color, low, high)
    torch.testing.assert_close(got, expected, rtol=0, atol=0)
    on_top, on_bottom = color == high, color == low
    assert (got[on_top] >= 0).all() and (got[on_bottom] <= 0).all()
    inside = ~(on_top | on_bottom)
    assert torch.equal(got[inside], grad[inside])


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"mask_mode": "sigmoid"},  # the composition falls back to the reference
        {"free_branch": False, "static_branch": False, "inverse_dynamics": False},  # DreamerV2: one branch
        {"channels_last": False, "layer_norm_gru": False},  # planar decoders, cells that do not pair
    ],
    ids=["isodream", "sigmoid_masks", "dreamerv2", "nchw_gru"],
)
def test_a_world_model_gives_the_same_losses_and_gradients_with_and_without_fast_paths(overrides):
    """Two world models with the same weights, fast_paths=True (the default) and False (the reference forms):
    the same modules and state dict, and the same losses and gradients for every parameter on one batch with
    a reset inside the window, under the same seed."""
    from isodream_rl.objectives.isodream_v2 import IsoDreamV2ModelLoss

    torch.manual_seed(0)
    fast = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2, **overrides))
    reference = IsoDreamV2WorldModel(
        IsoDreamV2Config.from_preset("tiny", action_dim=2, fast_paths=False, **overrides)
    )
    assert fast.state_dict().keys() == reference.state_dict().keys()
    reference.load_state_dict(fast.state_dict())
    assert type(fast.control_decoder) is FastConvDecoder and type(reference.control_decoder) is ConvDecoder
    assert type(fast.composition) is FusedMaskComposition and type(reference.composition) is MaskComposition
    assert fast.filter_window is fast_filter_window and reference.filter_window is filter_window
    g = torch.Generator().manual_seed(1)
    batch, time = 2, 6
    is_init = torch.zeros(batch, time, 1, dtype=torch.bool)
    is_init[1, 3] = True
    td = TensorDict(
        {
            "action": torch.rand(batch, time, 2, generator=g) * 2 - 1,
            "is_init": is_init,
            ("next", "pixels"): torch.randint(
                0, 256, (batch, time, 3, 64, 64), dtype=torch.uint8, generator=g
            ),
            ("next", "reward"): torch.randn(batch, time, 1, generator=g),
            ("next", "terminated"): torch.zeros(batch, time, 1, dtype=torch.bool),
        },
        [batch, time],
    )

    def run(model):
        loss = IsoDreamV2ModelLoss(model)
        torch.manual_seed(2)
        losses, _ = loss(td.clone())
        params = list(model.parameters())
        grads = torch.autograd.grad(loss.total(losses), params, allow_unused=True)
        return {k: v.detach() for k, v in losses.items() if k.startswith("loss_")}, grads

    fast_losses, fast_grads = run(fast)
    ref_losses, ref_grads = run(reference)
    assert fast_losses.keys() == ref_losses.keys() and fast_losses
    for key in ref_losses:
        torch.testing.assert_close(fast_losses[key], ref_losses[key], rtol=1e-5, atol=1e-5, msg=key)
    names = [name for name, _ in reference.named_parameters()]
    assert [g is None for g in fast_grads] == [g is None for g in ref_grads]
    for name, got, want in zip(names, fast_grads, ref_grads):
        if want is not None:
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * float(want.abs().max()), msg=name)


@pytest.mark.parametrize("channels_first", [False, True])
def test_fast_rms_norms_match_torchrl(channels_first):
    """FastRMSNorm / FastChannelRMSNorm: TorchRL's DreamerV3 RMS norms' values and gradients, same parameter."""
    from torchrl.modules.models.model_based import _DreamerV3ChannelRMSNorm, _DreamerV3RMSNorm

    from isodream_rl.modules.fast_paths import use_fast_rms_norms

    torch.manual_seed(0)
    reference = (_DreamerV3ChannelRMSNorm if channels_first else _DreamerV3RMSNorm)(6)
    with torch.no_grad():
        reference.weight.uniform_(0.5, 1.5)
    holder = use_fast_rms_norms(torch.nn.Sequential(reference))
    fast = holder[0]
    assert type(fast).__name__ == ("FastChannelRMSNorm" if channels_first else "FastRMSNorm")
    assert fast.weight is reference.weight and list(holder.state_dict()) == ["0.weight"]
    shape = (3, 6, 5, 4) if channels_first else (3, 5, 6)
    x = torch.randn(shape, requires_grad=True)
    grad = torch.randn(shape)
    results = []
    for module in (reference, fast):
        out = module(x)
        gx, gw = torch.autograd.grad(out, [x, reference.weight], grad)
        results.append((out, gx, gw))
    for expected, got in zip(*results):
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
