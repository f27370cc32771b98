"""Specification of the three-branch world model (paper eqs. 3-5) and its losses."""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from isodream_rl.modules import MaskComposition
from isodream_rl.modules.isodream_v2 import (
    ActionFreeRSSM,
    BranchedEncoder,
    IsoDreamV2Config,
    IsoDreamV2WorldModel,
)
from isodream_rl.modules.isodream_v2.config import DREAMERV2, PAPER_EXACT
from isodream_rl.objectives import InverseDynamicsLoss
from isodream_rl.objectives.isodream_v2 import IsoDreamV2ModelLoss, balanced_kl, gaussian_kl

B, T, A = 2, 6, 2


def make_batch(batch=B, time=T, action_dim=A, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "action": torch.rand(batch, time, action_dim, generator=g) * 2 - 1,
            "is_init": torch.zeros(batch, time, 1, dtype=torch.bool),
            ("next", "pixels"): torch.randint(
                0, 256, (batch, time, 3, 64, 64), dtype=torch.uint8, generator=g
            ),
            ("next", "reward"): torch.randn(batch, time, 1, generator=g),
            ("next", "terminated"): torch.zeros(batch, time, 1, dtype=torch.bool),
        },
        [batch, time],
    )


def tiny(**kw):
    return IsoDreamV2Config.from_preset("tiny", action_dim=A, **kw)


CONFIGS = {
    "isodream": {},
    "sigmoid_masks": {"mask_mode": "sigmoid"},
    "paper_exact": dict(PAPER_EXACT),
    "reward_on_free_discount": {"reward_uses_free": True, "discount_head": True},
    "free_from_prior": {"free_decoder_input": "prior"},
    "no_static": {"static_branch": False},
    "no_inverse": {"inverse_dynamics": False},
    "dreamerv2": dict(DREAMERV2),
    "nchw_gru": {"channels_last": False, "layer_norm_gru": False},
}


class TestRSSM:
    def test_action_free_cell_takes_no_action(self):
        cell = ActionFreeRSSM(state_dim=4, belief_dim=8, hidden_dim=8, embed_dim=16)
        assert cell.transition_in.in_features == 4
        state, belief = cell.initial((3,))
        out = cell.observe_step(state, belief, None, cell.project_embedding(torch.randn(3, 16)))
        assert out["state"].shape == (3, 4) and out["belief"].shape == (3, 8)

    def test_std_is_bounded_below_by_min_std(self):
        cell = ActionFreeRSSM(state_dim=4, belief_dim=8, hidden_dim=8, embed_dim=16, min_std=0.1)
        _, std = cell.prior(torch.randn(100, 8) * 100)
        assert (std >= 0.1).all() and (std <= 2.1).all()

    def test_wrong_embedding_width_is_rejected(self):
        cell = ActionFreeRSSM(state_dim=4, belief_dim=8, hidden_dim=8, embed_dim=16)
        with pytest.raises(ValueError, match="expected 16"):
            cell.project_embedding(torch.randn(3, 15))


class TestEncoder:
    def test_embedding_shapes(self):
        enc = BranchedEncoder(depth=4)
        e_s, e_z = enc(torch.zeros(2, 3, 3, 64, 64, dtype=torch.uint8))
        assert e_s.shape == e_z.shape == (2, 3, 128)

    @pytest.mark.parametrize("shape", [(2, 3, 84, 84), (2, 64, 64, 3), (2, 1, 64, 64)])
    def test_wrong_image_size_is_rejected(self, shape):
        with pytest.raises(ValueError, match=r"\[\*batch, 3, 64, 64\]"):
            BranchedEncoder(depth=4)(torch.zeros(shape, dtype=torch.uint8))


class TestComposition:
    def test_softmax_masks_are_nonnegative_and_sum_to_one(self):
        logits = {n: torch.randn(4, 1, 8, 8) * 5 for n in ("control", "free", "static")}
        colors = {n: torch.rand(4, 3, 8, 8) - 0.5 for n in logits}
        composite, masks = MaskComposition()(colors, logits)
        total = sum(masks.values())
        assert all((m >= 0).all() for m in masks.values())
        torch.testing.assert_close(total, torch.ones_like(total))
        expected = sum(masks[n] * colors[n] for n in colors)
        torch.testing.assert_close(composite, expected)

    def test_sigmoid_mode_is_eq4_with_independent_masks(self):
        logits = {n: torch.randn(4, 1, 8, 8) for n in ("control", "free")}
        colors = {n: torch.rand(4, 3, 8, 8) - 0.5 for n in ("control", "free", "static")}
        composite, masks = MaskComposition(mask_mode="sigmoid")(colors, logits)
        m_s, m_z = torch.sigmoid(logits["control"]), torch.sigmoid(logits["free"])
        expected = m_s * colors["control"] + m_z * colors["free"] + (1 - m_s - m_z) * colors["static"]
        torch.testing.assert_close(composite, expected)
        torch.testing.assert_close(masks["static"], 1 - m_s - m_z)

    def test_components_are_clamped_to_the_pixel_range_before_mixing(self):
        logits = {n: torch.zeros(1, 1, 1, 2) for n in ("control", "free", "static")}
        control = torch.tensor([[[[2.0, 0.25]]]]).expand(1, 3, 1, 2).clone().requires_grad_()
        colors = {"control": control, "free": torch.zeros(1, 3, 1, 2), "static": torch.zeros(1, 3, 1, 2)}
        composite, _ = MaskComposition(clamp_gradient="zero")(colors, logits)
        # out of range: 2.0 counts as 0.5 and, under the plain clamp, gets no gradient; in range: unchanged
        torch.testing.assert_close(composite[0, 0, 0], torch.tensor([0.5, 0.25]) / 3)
        composite.sum().backward()
        assert control.grad[0, 0, 0, 0] == 0 and control.grad[0, 0, 0, 1] > 0
        unclamped, _ = MaskComposition(clamp_components=False)(colors, logits)
        torch.testing.assert_close(unclamped[0, 0, 0], torch.tensor([2.0, 0.25]) / 3)
        # one branch (DreamerV2 ablation): the decoded image as it is
        alone, _ = MaskComposition()({"control": control}, {})
        assert alone[0, 0, 0, 0] == 2.0

    def test_per_window_background_broadcasts_over_time(self):
        colors = {"control": torch.randn(2, 5, 3, 8, 8), "static": torch.randn(2, 1, 3, 8, 8)}
        logits = {"control": torch.randn(2, 5, 1, 8, 8), "static": torch.randn(2, 1, 1, 8, 8)}
        composite, masks = MaskComposition()(colors, logits)
        assert composite.shape == (2, 5, 3, 8, 8) and masks["static"].shape == (2, 5, 1, 8, 8)


class TestWorldModel:
    @pytest.mark.parametrize("name", sorted(CONFIGS))
    def test_output_keys_and_shapes(self, name):
        wm = IsoDreamV2WorldModel(tiny(**CONFIGS[name]))
        out = wm(make_batch())
        cfg = wm.config
        for key in wm.out_keys:
            assert key in out.keys(True), key
        nxt = out["next"]
        assert nxt["state"].shape == nxt["prior_state"].shape == (B, T, cfg.state_dim)
        assert nxt["belief"].shape == (B, T, cfg.belief_dim)
        assert nxt["reco_pixels"].shape == nxt["reco_control"].shape == (B, T, 3, 64, 64)
        assert nxt["mask_control"].shape == (B, T, 1, 64, 64)
        assert nxt["reward_pred"].shape == (B, T, 1)
        if cfg.free_branch:
            assert nxt["free_state"].shape == (B, T, cfg.state_dim)
            assert nxt["reco_free"].shape == (B, T, 3, 64, 64)
        else:
            assert "free_state" not in nxt.keys()
        if cfg.static_branch:
            assert out["background"].shape == (B, T, 3, 64, 64)
            # one background per window
            torch.testing.assert_close(out["background"][:, 0], out["background"][:, -1])
        if cfg.inverse_dynamics:
            assert nxt["action_pred"].shape == (B, T, A)
            assert not nxt["action_pred_valid"][:, 0].any() and nxt["action_pred_valid"][:, 1:].all()

    def test_masks_sum_to_one_in_softmax_mode(self):
        nxt = IsoDreamV2WorldModel(tiny())(make_batch())["next"]
        masks = [nxt["mask_control"], nxt["mask_free"], nxt["mask_static"]]
        assert all((m >= 0).all() for m in masks)
        torch.testing.assert_close(sum(masks), torch.ones_like(masks[0]))

    @pytest.mark.parametrize("free_input", ["posterior", "prior"])
    def test_free_component_reads_the_current_frame_only_from_the_posterior(self, free_input):
        wm = IsoDreamV2WorldModel(tiny(free_decoder_input=free_input))
        td = make_batch()
        changed = td.clone()
        changed["next", "pixels"][:, 4] = 255 - changed["next", "pixels"][:, 4]
        outputs = []
        for batch in (td, changed):
            torch.manual_seed(0)  # the same latent samples
            outputs.append(wm(batch)["next", "reco_free"])
        # steps before the change agree either way; at the changed step only the posterior has seen it
        torch.testing.assert_close(outputs[0][:, :4], outputs[1][:, :4])
        same_at_change = torch.allclose(outputs[0][:, 4], outputs[1][:, 4])
        assert same_at_change == (free_input == "prior")
        assert not torch.allclose(outputs[0][:, 5], outputs[1][:, 5])  # the prior sees it one step later

    def test_is_init_mid_window_resets_both_branches(self):
        wm = IsoDreamV2WorldModel(tiny())
        td = make_batch()
        td["is_init"][:, 0] = True
        td["is_init"][0, 3] = True
        nxt = wm(td)["next"]
        # After a reset the transition sees zero states and a zero action, so the belief is the
        # same constant as at a window start with a zero action; sample 1 carries on instead.
        zero = torch.zeros(1, wm.config.state_dim)
        expected = wm.control_rssm.transition(zero, torch.zeros(1, wm.config.belief_dim), torch.zeros(1, A))
        expected_free = wm.free_rssm.transition(zero, torch.zeros(1, wm.config.belief_dim))
        for t_reset in (0, 3):
            torch.testing.assert_close(nxt["belief"][0, t_reset], expected[0])
            torch.testing.assert_close(nxt["free_belief"][0, t_reset], expected_free[0])
        assert not torch.allclose(nxt["belief"][1, 3], expected[0])
        assert not torch.allclose(nxt["free_belief"][1, 3], expected_free[0])
        assert not nxt["action_pred_valid"][0, 3] and nxt["action_pred_valid"][1, 3]

    def test_missing_key_names_it(self):
        td = make_batch()
        del td["action"]
        with pytest.raises(KeyError, match=r"needs the key .*action"):
            IsoDreamV2WorldModel(tiny())(td)

    def test_wrong_action_dims_are_rejected(self):
        td = make_batch(action_dim=3)
        with pytest.raises(ValueError, match=r"\[B, T, 2\]"):
            IsoDreamV2WorldModel(tiny())(td)

    def test_wrong_image_size_is_rejected(self):
        td = make_batch()
        td["next", "pixels"] = torch.zeros(B, T, 3, 32, 32, dtype=torch.uint8)
        with pytest.raises(ValueError, match="64x64"):
            IsoDreamV2WorldModel(tiny())(td)

    def test_flat_batch_is_rejected(self):
        with pytest.raises(ValueError, match=r"\[B, T\]"):
            IsoDreamV2WorldModel(tiny())(make_batch().reshape(-1))

    def test_impossible_configs_fail_early(self):
        with pytest.raises(ValueError, match="free_branch"):
            tiny(free_branch=False, reward_uses_free=True)
        with pytest.raises(ValueError, match="static branch"):
            tiny(static_branch=False, mask_mode="sigmoid")
        with pytest.raises(ValueError, match="unknown size preset"):
            IsoDreamV2Config.from_preset("huge", action_dim=2)
        with pytest.raises(ValueError, match="free_decoder_input 'state'"):
            tiny(free_decoder_input="state")

    def test_short_windows_reuse_their_last_frame_for_the_background(self):
        wm = IsoDreamV2WorldModel(tiny(static_frames=10))
        out = wm(make_batch(time=3))
        assert out["background"].shape == (B, 3, 3, 64, 64)


class TestKL:
    def test_gaussian_kl_matches_torch_distributions(self):
        mq, sq, mp, sp = torch.randn(5, 3), torch.rand(5, 3) + 0.1, torch.randn(5, 3), torch.rand(5, 3) + 0.1
        ref = torch.distributions.kl_divergence(
            torch.distributions.Normal(mq, sq), torch.distributions.Normal(mp, sp)
        ).sum(-1)
        torch.testing.assert_close(gaussian_kl(mq, sq, mp, sp), ref)

    def test_free_nats_clamp_the_batch_mean(self):
        m, s = torch.zeros(4, 3), torch.ones(4, 3)
        loss, kl = balanced_kl(m, s, m + 0.1, s, free_nats=1.0)
        assert loss.item() == pytest.approx(1.0) and kl.item() < 1.0

    def test_balance_weights_prior_and_posterior_gradients(self):
        mq = torch.zeros(1, 2, requires_grad=True)
        mp = torch.ones(1, 2, requires_grad=True)
        loss, _ = balanced_kl(mq, torch.ones(1, 2), mp, torch.ones(1, 2), balance=0.8, free_nats=0.0)
        loss.backward()
        # d KL / d mean = (mq - mp) for unit stds: the prior gets 0.8 of it, the posterior 0.2.
        torch.testing.assert_close(mp.grad, torch.full((1, 2), 0.8))
        torch.testing.assert_close(mq.grad, torch.full((1, 2), -0.2))


def _grad_norm(params):
    grads = [p.grad for p in params if p.grad is not None]
    return sum(g.abs().sum().item() for g in grads)


class TestInverseDynamicsLoss:
    @pytest.mark.parametrize("inverse_input", ["state", "embedding"])
    def test_gradient_reaches_controllable_branch_not_free_branch(self, inverse_input):
        wm = IsoDreamV2WorldModel(tiny(inverse_input=inverse_input))
        out = wm(make_batch())
        InverseDynamicsLoss()(out)["loss_inverse"].backward()
        assert _grad_norm(wm.encoder.trunk.parameters()) > 0
        assert _grad_norm(wm.encoder.heads["control"].parameters()) > 0
        assert _grad_norm(wm.inverse_cell.parameters()) > 0
        if inverse_input == "state":
            assert _grad_norm(wm.control_rssm.parameters()) > 0
        for module in (
            wm.free_rssm,
            wm.encoder.heads["free"],
            wm.free_decoder,
            wm.static_decoder,
            wm.reward_head,
        ):
            assert _grad_norm(module.parameters()) == 0

    def test_value_is_masked_mean_of_half_squared_error(self):
        action = torch.tensor([[[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]]])
        pred = torch.tensor([[[9.0, 9.0], [0.0, 0.0], [1.0, 0.0]]])
        valid = torch.tensor([[[False], [True], [True]]])
        td = TensorDict(
            {"action": action, ("next", "action_pred"): pred, ("next", "action_pred_valid"): valid}, [1, 3]
        )
        # valid steps: (0 - 0)^2 + (2 - 0)^2 = 4 and 0 + 1 = 1 -> gaussian 0.5 * 5 / 2
        assert InverseDynamicsLoss(lambda_inverse=2.0)(td)["loss_inverse"].item() == pytest.approx(2.5)
        assert InverseDynamicsLoss(loss_type="l2")(td)["loss_inverse"].item() == pytest.approx(2.5)

    def test_set_keys_remaps_inputs(self):
        td = TensorDict(
            {
                "act": torch.ones(1, 2, 2),
                ("next", "a_hat"): torch.zeros(1, 2, 2),
                ("next", "ok"): torch.ones(1, 2, 1),
            },
            [1, 2],
        )
        loss = InverseDynamicsLoss()
        loss.set_keys(action="act", action_pred=("next", "a_hat"), action_pred_valid=("next", "ok"))
        assert loss(td)["loss_inverse"].item() == pytest.approx(1.0)


class TestModelLoss:
    @pytest.mark.parametrize("name", sorted(CONFIGS))
    def test_loss_terms_are_finite_scalars(self, name):
        loss = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(tiny(**CONFIGS[name])))
        losses, out = loss(make_batch())
        cfg = loss.world_model.config
        expected = {"loss_model_reco", "loss_model_reward", "loss_model_kl_control"}
        expected |= {"loss_model_kl_free"} if cfg.free_branch else set()
        expected |= {"loss_model_inverse"} if cfg.inverse_dynamics else set()
        expected |= {"loss_model_discount"} if cfg.discount_head else set()
        assert {k for k in losses.keys() if k.startswith("loss_")} == expected
        assert all(torch.isfinite(v) and v.dim() == 0 for v in losses.values())
        assert ("next", "state") in out.keys(True)

    def test_image_loss_is_half_squared_error_summed_over_pixels(self):
        loss = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(tiny()))
        td = make_batch()
        losses, out = loss(td)
        target = td["next", "pixels"].float() / 255 - 0.5
        expected = 0.5 * (out["next", "reco_pixels"] - target).pow(2).sum((-3, -2, -1)).mean()
        torch.testing.assert_close(losses["loss_model_reco"], expected)

    def test_recon_only_free_branch_gets_no_kl_gradient(self):
        loss = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(tiny()), free_branch_loss="recon_only", free_nats=0.0)
        losses, _ = loss(make_batch())
        assert "loss_model_kl_free" not in losses.keys() and "kl_free" in losses.keys()
        loss.total(losses).backward()
        # the free prior only ever learns through the KL; without it, no gradient reaches it
        assert _grad_norm(loss.world_model.free_rssm.prior_net.parameters()) == 0
        assert _grad_norm(loss.world_model.free_rssm.posterior_out.parameters()) > 0

    def test_set_keys_remapping_gives_the_same_loss(self):
        td = make_batch()
        renamed = TensorDict(
            {
                "act": td["action"],
                "first": td["is_init"],
                ("next", "obs"): td["next", "pixels"],
                ("next", "rew"): td["next", "reward"],
            },
            td.batch_size,
        )
        loss = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(tiny()))
        torch.manual_seed(1)
        reference, _ = loss(td)
        loss.set_keys(action="act", is_init="first", pixels=("next", "obs"), reward=("next", "rew"))
        torch.manual_seed(1)
        remapped, _ = loss(renamed)
        for key in reference.keys():
            torch.testing.assert_close(remapped[key], reference[key])

    def test_set_keys_remaps_the_world_models_output_keys(self):
        class RenamedOutputs(IsoDreamV2WorldModel):
            """Writes every output under ``("next", "out_<key>")``: a world model with other key names."""

            def forward(self, tensordict):
                out = super().forward(tensordict)
                for key in list(out["next"].keys()):
                    if key not in ("pixels", "reward"):
                        out.rename_key_(("next", key), ("next", f"out_{key}"))
                return out

        td = make_batch()
        torch.manual_seed(0)
        reference, _ = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(tiny()))(td.clone())
        with pytest.raises(KeyError, match="reco_pixels"):
            IsoDreamV2ModelLoss(RenamedOutputs(tiny()))(td.clone())
        output_keys = [
            "reco_pixels",
            "reward_pred",
            "prior_mean",
            "prior_std",
            "posterior_mean",
            "posterior_std",
            "free_prior_mean",
            "free_prior_std",
            "free_posterior_mean",
            "free_posterior_std",
            "mask_control",
            "mask_free",
            "mask_static",
            "action_pred",
            "action_pred_valid",
        ]
        torch.manual_seed(0)
        loss = IsoDreamV2ModelLoss(RenamedOutputs(tiny()))
        loss.set_keys(**{key: ("next", f"out_{key}") for key in output_keys})
        remapped, _ = loss(td.clone())
        assert set(remapped.keys()) == set(reference.keys())
        for key in reference.keys():
            torch.testing.assert_close(remapped[key], reference[key])

    def test_paper_exact_loss_uses_eq5s_alpha(self):
        model = IsoDreamV2WorldModel(IsoDreamV2Config.paper_exact("tiny", action_dim=A))
        assert IsoDreamV2ModelLoss(model).inverse_loss.lambda_inverse == 30.0
        assert IsoDreamV2ModelLoss.paper_exact(model).inverse_loss.lambda_inverse == 1.0
        config = model.config
        assert (config.inverse_input, config.decoder_input, config.clamp_gradient) == (
            "state",
            "paper",
            "zero",
        )
        assert config.static_mask_bias == 0.0

    def test_missing_reward_key_is_named(self):
        td = make_batch()
        del td["next", "reward"]
        with pytest.raises(KeyError, match="reward"):
            IsoDreamV2ModelLoss(IsoDreamV2WorldModel(tiny()))(td)


def structured_batch(batch=2, time=8, seed=0):
    """Squares on a gradient background: one moved by the action, one drifting on its own."""
    rng = np.random.default_rng(seed)
    frames = np.zeros((batch, time, 64, 64, 3), np.uint8)
    actions = rng.uniform(-1, 1, (batch, time, 2)).astype(np.float32)
    ramp = np.linspace(40, 120, 64, dtype=np.float32)
    for b in range(batch):
        agent = rng.uniform(16, 48, 2)
        other, velocity = rng.uniform(8, 56, 2), rng.uniform(-3, 3, 2)
        for t in range(time):
            agent = np.clip(agent + 4 * actions[b, t], 4, 60)
            other = other + velocity
            velocity = np.where((other < 4) | (other > 60), -velocity, velocity)
            frame = np.stack(
                [ramp[None, :].repeat(64, 0), ramp[:, None].repeat(64, 1), np.full((64, 64), 60.0)], -1
            )
            for (y, x), color in ((agent, (250, 40, 40)), (other, (40, 40, 250))):
                y, x = int(y), int(x)
                frame[max(y - 4, 0) : y + 4, max(x - 4, 0) : x + 4] = color
            frames[b, t] = frame
    return TensorDict(
        {
            "action": torch.from_numpy(actions),
            "is_init": torch.zeros(batch, time, 1, dtype=torch.bool),
            ("next", "pixels"): torch.from_numpy(frames).permute(0, 1, 4, 2, 3).contiguous(),
            ("next", "reward"): torch.from_numpy(actions[..., :1].copy()),
        },
        [batch, time],
    )


@pytest.mark.parametrize(("precision", "steps", "lr"), [("fp32", 120, 5e-3), ("bf16", 60, 1e-2)])
def test_total_loss_falls_when_overfitting_one_batch(precision, steps, lr):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread is faster and immune to a loaded machine
    try:
        torch.manual_seed(0)
        loss = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(tiny(precision=precision)))
        optimizer = torch.optim.Adam(loss.parameters(), lr=lr)
        td = structured_batch(time=6)
        history = []
        for _ in range(steps):
            losses, _ = loss(td.clone())
            total = loss.total(losses)
            optimizer.zero_grad()
            total.backward()
            optimizer.step()
            history.append(total.item())
    finally:
        torch.set_num_threads(threads)
    assert all(math.isfinite(h) for h in history)
    first, last = np.mean(history[:5]), np.mean(history[-5:])
    assert last < 0.3 * first, (first, last)


def test_decoder_matmul_first_layer_equals_the_transposed_convolution():
    from isodream_rl.modules.isodream_v2.fast_paths import FastConvDecoder

    decoder = FastConvDecoder(in_features=20, out_channels=4, depth=4)
    latent = torch.randn(3, 20)
    reference = decoder.deconv(decoder.linear(latent)[:, :, None, None])
    torch.testing.assert_close(decoder(latent), reference, rtol=1e-5, atol=1e-5)
