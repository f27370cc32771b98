"""Specification of the imagination rollout (Algorithm 1, lines 7-12)."""

import pytest
import torch
from tensordict import TensorDict

from isodream_rl.modules import PolicyInput
from isodream_rl.modules.isodream_v2 import IsoDreamV2Actor, IsoDreamV2Config, IsoDreamV2WorldModel
from isodream_rl.objectives.isodream_v2 import IsoDreamV2Imagination, IsoDreamV2ModelLoss

A, L, TAU, N = 2, 4, 3, 5


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny tensors: a second intra-op thread only adds synchronisation, which costs 10x on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def build(mode="attention", attention_window="start", **wm_kwargs):
    wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=A, **wm_kwargs))
    policy_input = PolicyInput.for_world_model(wm, mode=mode, window=TAU, width=8)
    imagination = IsoDreamV2Imagination(wm, policy_input, horizon=L, attention_window=attention_window)
    actor = IsoDreamV2Actor(in_features=policy_input.out_features, action_dim=A, num_cells=8, depth=2)
    return wm, imagination, actor


def random_start(wm, n=N):
    return [torch.randn_like(v) for v in wm.initial_state((n,)).values()]


def features(td, prefix=""):
    return torch.cat([td[f"{prefix}state"], td[f"{prefix}belief"]], dim=-1)


@pytest.mark.parametrize("attention_window", ["start", "per_step"])
def test_rollout_has_torchrl_layout_and_shapes(attention_window):
    wm, imagination, actor = build(attention_window=attention_window, discount_head=True)
    out = imagination(*random_start(wm), actor=actor)
    assert out.batch_size == (N, L)
    assert out["action"].shape == (N, L, A) and out["action"].abs().max() < 1
    assert out["action_log_prob"].shape == (N, L)
    assert out["free_window"].shape == (N, L, TAU, 8 + 16)
    assert out["next", "reward"].shape == (N, L, 1)
    assert ((out["next", "continuation"] > 0) & (out["next", "continuation"] < 1)).all()
    # The "next" entries are the root entries one step later.
    torch.testing.assert_close(out["next", "state"][:, :-1], out["state"][:, 1:])
    torch.testing.assert_close(out["next", "free_window"][:, :-1], out["free_window"][:, 1:])


def test_start_window_at_step_j_covers_z_j_to_z_j_plus_tau_minus_one_of_one_chain():
    wm, imagination, actor = build(attention_window="start")
    start = random_start(wm)
    out = imagination(*start, actor=actor)
    windows = torch.cat([out["free_window"], out["next", "free_window"][:, -1:]], dim=1)  # [N, L + 1, tau, F]
    chain = torch.cat([windows[:, :, 0], windows[:, -1, 1:]], dim=1)  # z_0 .. z_{L + tau - 1}
    assert chain.shape[1] == L + TAU
    for j in range(L + 1):
        torch.testing.assert_close(windows[:, j], chain[:, j : j + TAU])
    # The chain starts at the posterior and is the trajectory's z_j.
    torch.testing.assert_close(chain[:, 0], torch.cat(start[2:], dim=-1))
    torch.testing.assert_close(windows[:, :L, 0], features(out, "free_"))
    # Each element follows the previous one through the action-free transition (beliefs are deterministic).
    state_dim = wm.config.state_dim
    belief = wm.free_rssm.transition(chain[:, :-1, :state_dim], chain[:, :-1, state_dim:])
    torch.testing.assert_close(belief, chain[:, 1:, state_dim:])


def test_per_step_window_is_rerolled_from_each_imagined_z():
    wm, imagination, actor = build(attention_window="per_step")
    out = imagination(*random_start(wm), actor=actor)
    window = out["free_window"]
    torch.testing.assert_close(window[:, :, 0], features(out, "free_"))
    state_dim = wm.config.state_dim
    belief = wm.free_rssm.transition(window[:, :, :-1, :state_dim], window[:, :, :-1, state_dim:])
    torch.testing.assert_close(belief, window[:, :, 1:, state_dim:])
    # Re-rolled, so step j's look-ahead is not step j + 1's trajectory state.
    assert not torch.allclose(window[:, :-1, 1], window[:, 1:, 0])


def test_actions_drive_the_controllable_prior_and_the_actor_reads_the_attended_window():
    wm, imagination, actor = build()
    out = imagination(*random_start(wm), actor=actor)
    belief = wm.control_rssm.transition(out["state"], out["belief"], out["action"])
    torch.testing.assert_close(belief, out["next", "belief"])
    expected = imagination.policy_input(features(out), None, out["free_window"])
    torch.testing.assert_close(out["attended_state"], expected, rtol=1e-5, atol=1e-5)
    # The actor's input is detached (authors' code); actions carry the pathwise gradient.
    assert out["attended_state"].grad_fn is None and out["action"].requires_grad


@pytest.mark.parametrize("reward_uses_free", [False, True])
def test_reward_is_the_reward_head_on_the_state_reached(reward_uses_free):
    wm, imagination, actor = build(mode="concat", reward_uses_free=reward_uses_free)
    out = imagination(*random_start(wm), actor=actor)
    nxt = out["next"]
    head_input = wm.reward_features(nxt["state"], nxt["belief"], nxt["free_state"], nxt["free_belief"])
    torch.testing.assert_close(nxt["reward"], wm.reward_head(head_input))


def test_controllable_mode_ignores_the_free_branch_unless_the_reward_reads_it():
    wm, imagination, actor = build(mode="controllable")
    out = imagination(*random_start(wm)[:2], actor=actor)
    assert "free_state" not in out.keys() and "free_window" not in out.keys()
    torch.testing.assert_close(out["attended_state"], features(out))
    wm, imagination, actor = build(mode="controllable", reward_uses_free=True)
    with pytest.raises(ValueError, match="free_state/free_belief needed"):
        imagination(*random_start(wm)[:2], actor=actor)


def test_imagination_starts_from_every_posterior_of_the_replay_batch():
    wm, imagination, actor = build()
    batch, time = 2, 3
    td = TensorDict(
        {
            "action": torch.zeros(batch, time, A),
            "is_init": torch.zeros(batch, time, 1, dtype=torch.bool),
            ("next", "pixels"): torch.randint(0, 256, (batch, time, 3, 64, 64), dtype=torch.uint8),
            ("next", "reward"): torch.zeros(batch, time, 1),
        },
        [batch, time],
    )
    _, model_out = IsoDreamV2ModelLoss(wm)(td)
    nxt = model_out["next"]
    start = [nxt[k].reshape(batch * time, -1) for k in ("state", "belief", "free_state", "free_belief")]
    out = imagination(*start, actor=actor)
    assert out.batch_size == (batch * time, L)
    torch.testing.assert_close(out["state"][:, 0], start[0].detach())
    assert torch.autograd.grad(out["state"][:, 0].sum(), start[0], allow_unused=True) == (None,)


def test_bad_configuration_is_rejected():
    wm, imagination, actor = build()
    with pytest.raises(ValueError, match="attention_window"):
        IsoDreamV2Imagination(wm, imagination.policy_input, attention_window="sliding")
    with pytest.raises(ValueError, match="feature_dim"):
        IsoDreamV2Imagination(wm, PolicyInput(mode="attention", feature_dim=7, window=TAU, width=8))
    with pytest.raises(ValueError, match="flat"):
        imagination(*[s[None] for s in random_start(wm)], actor=actor)
