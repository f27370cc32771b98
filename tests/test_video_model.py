"""ST-LSTM cells, the three-branch predictor, its variants and the training objective."""

import pytest
import torch
from tensordict import TensorDict

from isodream_rl.video_prediction.config import VARIANTS, variant_config
from isodream_rl.video_prediction.objective import VideoPredictionLoss
from isodream_rl.video_prediction.predictor import ThreeBranchPredictor
from isodream_rl.video_prediction.st_lstm import ActionConditionedSTLSTMCell, SpatioTemporalLSTMCell


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # Recurrent rollouts are hundreds of tiny ops; with 2 threads on a busy machine the OpenMP
    # hand-offs dominate, so these tests use one.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


TINY = dict(hidden_channels=8, encoder_channels=(8, 8), kernel_size=3, action_embedding=8)


def _model(variant="isodream", **kw):
    return ThreeBranchPredictor(config=variant_config(variant, **{**TINY, **kw}))


def _clip(batch=2, steps=6, size=16, action_dim=4):
    return torch.rand(batch, steps, 3, size, size), torch.randn(batch, steps, action_dim)


class TestCells:
    def test_st_lstm_shapes_and_zero_state(self):
        cell = SpatioTemporalLSTMCell(in_channels=5, hidden_channels=7, kernel_size=3)
        x = torch.randn(2, 5, 8, 8)
        h, c = cell.initial_state(x)
        assert h.shape == c.shape == (2, 7, 8, 8) and not h.any()
        out = cell(x, (h, c), torch.zeros(2, 7, 8, 8))
        assert [t.shape for t in out] == [torch.Size([2, 7, 8, 8])] * 5

    def test_memory_increments_are_the_gated_updates(self):
        cell = SpatioTemporalLSTMCell(in_channels=3, hidden_channels=4, kernel_size=3)
        x = torch.randn(1, 3, 5, 5)
        h, c, m, delta_c, delta_m = cell(x, cell.initial_state(x), torch.zeros(1, 4, 5, 5))
        # From zero memories, the new memories are exactly the increments.
        torch.testing.assert_close(c, delta_c)
        torch.testing.assert_close(m, delta_m)

    def test_action_changes_the_action_conditioned_cell_only_through_the_hidden_term(self):
        torch.manual_seed(0)
        cell = ActionConditionedSTLSTMCell(in_channels=3, hidden_channels=4, action_channels=2, kernel_size=3)
        x = torch.randn(1, 3, 5, 5)
        zero_h = cell.initial_state(x)
        m = torch.zeros(1, 4, 5, 5)
        a1, a2 = torch.randn(1, 2), torch.randn(1, 2)
        # With h = 0 the hidden term is the conv bias times the gain: the action matters.
        assert not torch.allclose(cell(x, zero_h, m, a1)[0], cell(x, zero_h, m, a2)[0])
        with pytest.raises(ValueError, match="action"):
            cell(x, zero_h, m)

    def test_even_kernel_is_rejected(self):
        with pytest.raises(ValueError, match="odd"):
            SpatioTemporalLSTMCell(in_channels=1, hidden_channels=1, kernel_size=4)


class TestPredictor:
    @pytest.mark.parametrize("variant", sorted(VARIANTS))
    def test_output_shapes(self, variant):
        frames, actions = _clip()
        out = _model(variant)(frames, actions, context=2, return_components=True)
        assert out["frames"].shape == (2, 5, 3, 16, 16)
        assert out["decouple"].shape == ()
        assert ("action_pred" in out) == variant_config(variant).inverse_dynamics
        assert ("mask_free" in out) == variant_config(variant).action_free_branch
        if "action_pred" in out:
            assert out["action_pred"].shape == (2, 5, 4)

    @pytest.mark.parametrize("variant", ["isodream", "no_action_free"])
    def test_masks_sum_to_one(self, variant):
        out = _model(variant)(*_clip(), return_components=True)
        total = out["mask_control"] + out["mask_static"] + out.get("mask_free", 0)
        torch.testing.assert_close(total, torch.ones_like(total))
        assert (out["mask_static"] >= 0).all()

    def test_frames_after_context_do_not_leak_into_predictions(self):
        model = _model().eval()
        frames, actions = _clip()
        changed = frames.clone()
        changed[:, 2:] = torch.rand_like(changed[:, 2:])
        torch.testing.assert_close(model(frames, actions)["frames"], model(changed, actions)["frames"])

    def test_predictions_depend_on_actions(self):
        model = _model().eval()
        frames, actions = _clip()
        assert not torch.allclose(model(frames, actions)["frames"], model(frames, actions + 1)["frames"])

    def test_variant_without_action_free_branch_has_no_free_parameters(self):
        names = [n for n, _ in _model("no_action_free").named_parameters()]
        assert names and not any(n.startswith("free.") for n in names)
        assert not any(
            n.startswith("inverse.") for n in (n for n, _ in _model("no_inverse").named_parameters())
        )

    def test_free_branch_ignores_actions_during_the_rollout(self):
        model = _model().eval()
        frames, actions = _clip()
        out_a = model(frames, actions, return_components=True)
        out_b = model(frames, actions + 1, return_components=True)
        # The free branch reads its own masked output, never the action or the composite frame.
        torch.testing.assert_close(out_a["reco_free"], out_b["reco_free"])

    def test_bad_inputs_are_rejected(self):
        model = _model()
        frames, actions = _clip()
        with pytest.raises(ValueError, match="action_dim"):
            model(frames, actions[..., :3])
        with pytest.raises(ValueError, match="context"):
            model(frames, actions, context=6)
        with pytest.raises(KeyError, match="unknown variant"):
            variant_config("nope")


class TestObjective:
    def test_inverse_loss_trains_the_encoder_but_not_the_free_branch_on_observed_frames(self):
        model = _model()
        frames, actions = _clip()
        # All inputs observed (context = T - 1): the inverse cell only sees true frames.
        loss = VideoPredictionLoss(model, lambda_action=1.0, lambda_decouple=0.0, context=5)
        out = loss(TensorDict({"frames": frames, "actions": actions}, [2]))
        assert set(out.keys()) == {"loss_image", "loss_action", "loss_decouple"}
        out["loss_action"].backward()
        assert model.encoder[0].weight.grad.abs().sum() > 0
        assert all(p.grad is None or not p.grad.any() for p in model.free.parameters())

    def test_variants_without_inverse_have_zero_action_loss(self):
        loss = VideoPredictionLoss(_model("no_inverse"))
        frames, actions = _clip()
        assert loss(TensorDict({"frames": frames, "actions": actions}, [2]))["loss_action"] == 0

    def test_keys_can_be_remapped(self):
        loss = VideoPredictionLoss(_model("predrnn"))
        loss.set_keys(frames="pixels", actions="action")
        frames, actions = _clip()
        out = loss(TensorDict({"pixels": frames, "action": actions}, [2]))
        assert out["loss_image"] > 0

    @pytest.mark.parametrize("precision", ["fp32", "bf16"])
    def test_overfits_a_handful_of_sequences(self, precision):
        torch.manual_seed(0)
        model = _model(num_layers=1, precision=precision)
        # Three clips: a bright square moved by the action (controllable) on a black background.
        frames = torch.zeros(3, 5, 3, 16, 16)
        actions = torch.zeros(3, 5, 4)
        for b in range(3):
            for t in range(5):
                frames[b, t, :, 4:8, 2 * t + b : 2 * t + b + 4] = 1.0
                actions[b, t, 0] = 1.0
        loss = VideoPredictionLoss(model)
        td = TensorDict({"frames": frames, "actions": actions}, [3])
        opt = torch.optim.Adam(model.parameters(), lr=1e-2)
        first = None
        for _ in range(40):
            terms = loss(td)
            first = first if first is not None else terms["loss_image"].item()
            opt.zero_grad()
            sum(terms.values()).backward()
            opt.step()
        assert loss(td)["loss_image"].item() < 0.3 * first


class TestFastPath:
    """The channels-last path equals the plain (contiguous, fp32) reference; bf16 stays close."""

    @staticmethod
    def _pair(variant, **fast):
        plain = _model(variant, channels_last=False)
        other = _model(variant, **fast)
        other.load_state_dict(plain.state_dict())
        return plain, other

    @staticmethod
    def _run(model, frames, actions):
        model.zero_grad(set_to_none=True)
        td = TensorDict({"frames": frames, "actions": actions}, [frames.shape[0]])
        sum(VideoPredictionLoss(model, lambda_action=1.0)(td).values()).backward()
        out = model(frames, actions, return_components=True)
        grads = {n: p.grad for n, p in model.named_parameters() if p.grad is not None}
        return out, grads

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    @pytest.mark.parametrize("variant", sorted(VARIANTS))
    def test_channels_last_matches_the_plain_path(self, variant, dtype):
        torch.manual_seed(0)
        plain, fast = self._pair(variant, channels_last=True)
        plain.to(dtype), fast.to(dtype)
        frames, actions = (x.to(dtype) for x in _clip())
        out_p, grads_p = self._run(plain, frames, actions)
        out_f, grads_f = self._run(fast, frames, actions)
        assert out_p.keys() == out_f.keys() and grads_p.keys() == grads_f.keys() and grads_p
        tol = 1e-5 if dtype == torch.float32 else 1e-10
        for key in out_p:
            torch.testing.assert_close(out_f[key], out_p[key], atol=tol, rtol=tol)
        # Gradients are sums over the rollout, with a different summation order per layout: the tolerance
        # is relative to the largest gradient (the action loss, weighted 1 here, reaches ~10).
        scale = max(1.0, max(g.abs().max().item() for g in grads_p.values()))
        for name in grads_p:
            torch.testing.assert_close(grads_f[name], grads_p[name], atol=tol * scale, rtol=tol)

    def test_bf16_is_close_and_returns_fp32(self):
        torch.manual_seed(0)
        plain, fast = self._pair("isodream", precision="bf16")
        frames, actions = _clip()
        out_p, _ = self._run(plain, frames, actions)
        out_f, grads_f = self._run(fast, frames, actions)
        assert all(v.dtype == torch.float32 for v in out_f.values())
        assert all(g.isfinite().all() for g in grads_f.values())
        torch.testing.assert_close(out_f["frames"], out_p["frames"], atol=3e-2, rtol=0)

    def test_unknown_precision_is_rejected(self):
        with pytest.raises(ValueError, match="precision"):
            variant_config("isodream", precision="fp16")


@pytest.mark.parametrize("variant", ["isodream", "predrnn"])
def test_sigmoid_outputs_keep_a_long_rollout_in_range_and_linear_ones_do_not(variant):
    """Decoders blown up 50x: with ``rgb_activation="sigmoid"`` (the default) every predicted frame of a 20-step
    closed loop stays in [0, 1]; the authors' linear outputs leave it."""
    frames, actions = torch.rand(2, 20, 3, 16, 16), torch.randn(2, 20, 4)
    ranges = {}
    for activation in ("sigmoid", "linear"):
        torch.manual_seed(0)
        model = ThreeBranchPredictor(config=variant_config(variant, rgb_activation=activation, **TINY))
        with torch.no_grad():
            for branch in (model.control, model.free):
                if branch is not None:
                    branch.decoder[-1].weight.mul_(50.0)
            out = model(frames, actions, context=2)["frames"]
        ranges[activation] = (float(out.min()), float(out.max()))
    assert 0.0 <= ranges["sigmoid"][0] and ranges["sigmoid"][1] <= 1.0
    assert ranges["linear"][0] < 0.0 or ranges["linear"][1] > 1.0


def test_configs_saved_before_rgb_activation_load_as_linear():
    from isodream_rl.video_prediction.config import PredictorConfig

    saved = variant_config("isodream").to_dict()
    del saved["rgb_activation"]
    assert PredictorConfig.from_dict(saved).rgb_activation == "linear"
    assert variant_config("isodream").rgb_activation == "sigmoid"
    with pytest.raises(ValueError, match="rgb_activation"):
        variant_config("isodream", rgb_activation="tanh")
