"""Specification of the future-state attention (paper eq. 6) and the policy input e_t (eq. 7)."""

import math

import pytest
import torch

from isodream_rl.modules import FutureStateAttention, PolicyInput
from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel


class TestFutureStateAttention:
    def test_literal_form_matches_a_hand_computation(self):
        attention = FutureStateAttention(query_dim=2, key_dim=2, projections=False)
        s = torch.tensor([[1.0, 0.0]])
        z = torch.tensor([[[2.0, 0.0], [0.0, 1.0]]])
        # scores s.z = [2, 0]; softmax = [e^2, 1] / (e^2 + 1)
        a0 = math.exp(2) / (math.exp(2) + 1)
        expected = torch.tensor([[a0 * 2.0 + 1.0, (1 - a0) * 1.0]])
        torch.testing.assert_close(attention(s, z), expected)
        assert list(attention.parameters()) == []

    @staticmethod
    def textbook(attention, q, window, key_bias):
        """Attention with every projection applied explicitly (a key bias shifts all scores equally)."""
        queries = q @ attention.query.weight.T + attention.query.bias
        keys = window @ attention.key.weight.T + key_bias
        values = window @ attention.value.weight.T + attention.value.bias
        scores = (keys @ queries[..., None]).squeeze(-1) / math.sqrt(attention.width)
        weights = torch.softmax(scores, dim=-1)
        pooled = (weights[..., None] * values).sum(-2)
        return pooled @ attention.output.weight.T + attention.output.bias + q, weights

    @pytest.mark.parametrize("rows", [1, 7])
    def test_projected_form_equals_standard_attention_with_any_key_bias(self, rows):
        torch.manual_seed(1)
        attention = FutureStateAttention(query_dim=3, key_dim=4, width=5)
        assert attention._fold_pays(rows) == (rows > 1), "both evaluation paths are covered"
        q, window = torch.randn(rows, 3), torch.randn(rows, 6, 4)
        expected, weights = self.textbook(attention, q, window, torch.randn(5))
        torch.testing.assert_close(attention(q, window), expected, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(attention.weights(q, window), weights, rtol=1e-5, atol=1e-6)

    def test_folded_projections_give_the_standard_gradients(self):
        torch.manual_seed(2)
        attention = FutureStateAttention(query_dim=3, key_dim=4, width=5)
        q, window = torch.randn(7, 3, requires_grad=True), torch.randn(7, 6, 4)
        weight = torch.randn(7, 3)
        grads = []
        for out in (
            attention(q, window, folded=attention.fold()),
            self.textbook(attention, q, window, 0.0)[0],
        ):
            grads.append(torch.autograd.grad((out * weight).sum(), [q, *attention.parameters()]))
        for folded, plain in zip(*grads):
            torch.testing.assert_close(folded, plain, rtol=1e-4, atol=1e-5)

    def test_weights_sum_to_one_over_the_window(self):
        attention = FutureStateAttention(query_dim=4, key_dim=4, width=8)
        weights = attention.weights(torch.randn(2, 3, 4), torch.randn(2, 3, 5, 4))
        assert weights.shape == (2, 3, 5)
        torch.testing.assert_close(weights.sum(-1), torch.ones(2, 3))

    def test_residual_keeps_the_query_when_the_output_projection_is_zero(self):
        attention = FutureStateAttention(query_dim=4, key_dim=4, width=8)
        torch.nn.init.zeros_(attention.output.weight)
        torch.nn.init.zeros_(attention.output.bias)
        q = torch.randn(3, 4)
        torch.testing.assert_close(attention(q, torch.randn(3, 2, 4)), q)

    def test_literal_form_needs_equal_widths(self):
        with pytest.raises(ValueError, match="equal query and key widths"):
            FutureStateAttention(query_dim=3, key_dim=4, projections=False)

    def test_mismatched_window_is_rejected(self):
        attention = FutureStateAttention(query_dim=3, key_dim=3, width=4)
        with pytest.raises(ValueError, match="window"):
            attention(torch.randn(2, 3), torch.randn(3, 5, 3))
        with pytest.raises(ValueError, match=r"window \[\*N, tau, 3\]"):
            attention(torch.randn(2, 3), torch.randn(2, 5, 4))


class TestPolicyInput:
    def test_modes_give_the_documented_features(self):
        control, free, window = torch.randn(2, 6), torch.randn(2, 6), torch.randn(2, 3, 6)
        assert torch.equal(PolicyInput(mode="controllable", feature_dim=6)(control, free, window), control)
        concat = PolicyInput(mode="concat", feature_dim=6)
        assert concat.out_features == 12
        assert torch.equal(concat(control, free), torch.cat([control, free], -1))
        attention = PolicyInput(mode="attention", feature_dim=6, window=3, width=8)
        assert attention.out_features == 6
        torch.testing.assert_close(attention(control, free, window), attention.attention(control, window))

    def test_attention_needs_a_window_of_tau(self):
        attention = PolicyInput(mode="attention", feature_dim=6, window=3, width=8)
        with pytest.raises(ValueError, match="window"):
            attention(torch.randn(2, 6), None, torch.randn(2, 4, 6))

    def test_unknown_mode_and_missing_free_branch_are_rejected(self):
        with pytest.raises(ValueError, match="unknown policy_input"):
            PolicyInput(mode="future", feature_dim=6)
        wm = IsoDreamV2WorldModel(IsoDreamV2Config.dreamerv2("tiny", action_dim=2))
        with pytest.raises(ValueError, match="free_branch=False"):
            PolicyInput.for_world_model(wm, mode="attention")
        assert PolicyInput.for_world_model(wm, mode="controllable").out_features == 8 + 16
