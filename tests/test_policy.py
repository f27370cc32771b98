"""Specification of the acting policy (paper §3.4, Algorithm 1 lines 19-22) inside TorchRL collectors."""

import functools

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules.utils import get_primers_from_module

from isodream_rl.envs import make_env
from isodream_rl.modules import PolicyInput
from isodream_rl.modules.isodream_v2 import (
    IsoDreamV2Actor,
    IsoDreamV2Config,
    IsoDreamV2Value,
    IsoDreamV2WorldModel,
)
from isodream_rl.modules.isodream_v2.policy import IsoDreamV2Policy
from isodream_rl.objectives.isodream_v2 import (
    IsoDreamV2ActorLoss,
    IsoDreamV2Imagination,
    IsoDreamV2ModelLoss,
    IsoDreamV2ValueLoss,
    make_target_updater,
)

A, TAU, MAX_STEPS = 2, 3, 15


@pytest.fixture(autouse=True)
def _one_thread():
    """Acting works on a few tiny tensors per step: a second intra-op thread only adds synchronisation, which
    costs 10x on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def build_policy(mode="attention", **wm_kwargs):
    wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=A, **wm_kwargs))
    policy_input = PolicyInput.for_world_model(wm, mode=mode, window=TAU, width=8)
    actor = IsoDreamV2Actor(in_features=policy_input.out_features, action_dim=A, num_cells=8, depth=2)
    return IsoDreamV2Policy(wm, actor, policy_input)


def make_envs(policy, num_envs=2, seed=0):
    env = TransformedEnv(
        SerialEnv(num_envs, functools.partial(make_env, "sprites", max_steps=MAX_STEPS)),
        policy.make_tensordict_primer(),
    )
    env.set_seed(seed)
    return env


def reset_belief(wm, n):
    state, belief = wm.control_rssm.initial((n,))
    return wm.control_rssm.transition(state, belief, torch.zeros(n, A))


def test_collector_with_two_envs_carries_and_resets_both_branches():
    policy = build_policy()
    wm = policy.world_model
    env = make_envs(policy)
    collector = Collector(env, policy, frames_per_batch=100, total_frames=300)
    data = torch.cat(list(collector), dim=1)  # [2 envs, 150 steps], contiguous in time
    collector.shutdown()  # closes the env too
    assert data.batch_size == (2, 150)
    is_init = data["is_init"].squeeze(-1)
    assert (is_init.sum(1) >= 150 // MAX_STEPS).all(), "episodes of 15 steps must have reset"

    # The carried state of step t + 1 is what the policy wrote at step t, inside an episode.
    within = ~is_init[:, 1:]
    for key in ("state", "belief", "free_state", "free_belief", "previous_action"):
        torch.testing.assert_close(data[key][:, 1:][within], data["next", key][:, :-1][within])
    torch.testing.assert_close(data["previous_action"][:, 1:][within], data["action"][:, :-1][within])
    # At a reset the carried state is zero and the filter starts from zero states and action.
    for key in ("state", "belief", "free_state", "free_belief", "previous_action"):
        assert (data[key][is_init] == 0).all()
    h0 = reset_belief(wm, int(is_init.sum()))
    torch.testing.assert_close(data["next", "belief"][is_init], h0)
    # Everywhere the new belief is the transition of the carried posterior and previous action.
    belief = wm.control_rssm.transition(data["state"], data["belief"], data["previous_action"])
    torch.testing.assert_close(data["next", "belief"], belief)
    free_belief = wm.free_rssm.transition(data["free_state"], data["free_belief"])
    torch.testing.assert_close(data["next", "free_belief"], free_belief)
    assert data["action"].abs().max() < 1


def test_policy_resets_on_is_init_even_with_a_stale_carried_state():
    policy = build_policy()
    td = policy.make_tensordict_primer().primers.zero().expand(3).clone()
    td.apply_(lambda x: x.normal_())
    td.update(
        {
            "pixels": torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8),
            "is_init": torch.tensor([[True], [False], [True]]),
        }
    )
    out = policy(td)
    h0 = reset_belief(policy.world_model, 1)[0]
    torch.testing.assert_close(out["next", "belief"][0], h0)
    torch.testing.assert_close(out["next", "belief"][2], h0)
    assert not torch.allclose(out["next", "belief"][1], h0)


def test_evaluation_is_deterministic_under_a_seed_and_uses_the_mode():
    policy = build_policy()
    env = make_envs(policy)

    def run(seed, exploration):
        torch.manual_seed(seed)
        env.set_seed(seed)
        with set_exploration_type(exploration):
            return env.rollout(MAX_STEPS + 5, policy, break_when_any_done=False)

    first, second = run(3, ExplorationType.DETERMINISTIC), run(3, ExplorationType.DETERMINISTIC)
    torch.testing.assert_close(first["action"], second["action"])
    assert first["is_init"][:, MAX_STEPS].all(), "the rollout crosses a reset"
    # Sampling (training) draws other actions from the same seed.
    sampled = run(3, ExplorationType.RANDOM)
    assert not torch.allclose(sampled["action"], first["action"])
    env.close()


@pytest.mark.parametrize("mode", ["controllable", "attention", "concat"])
def test_collect_train_and_act_end_to_end(mode):
    policy = build_policy(mode, reward_uses_free=mode != "controllable")
    wm, actor, policy_input = policy.world_model, policy.actor, policy.policy_input
    imagination = IsoDreamV2Imagination(wm, policy_input, horizon=4)
    value_loss = IsoDreamV2ValueLoss(
        IsoDreamV2Value(in_features=policy_input.out_features, num_cells=8), imagination
    )
    actor_loss = IsoDreamV2ActorLoss(actor, imagination, value_loss)
    model_loss = IsoDreamV2ModelLoss(wm)
    groups = actor_loss.parameter_groups()
    optimisers = {name: torch.optim.Adam(params, lr=1e-3) for name, params in groups.items()}
    updater = make_target_updater(value_loss, period=1)
    env = make_envs(policy)
    collector = Collector(env, policy, frames_per_batch=40, total_frames=80)
    for data in collector:  # [2, 20] windows
        losses, model_out = model_loss(data)
        actor_losses, imagined = actor_loss(model_out)
        value_losses, _ = value_loss(imagined)
        assert imagined.batch_size == (data.numel(), 4)
        total = model_loss.total(losses) + actor_losses["loss_actor"] + value_losses["loss_value"]
        assert torch.isfinite(total)
        total.backward()
        assert all(any(p.grad is not None for p in params) for params in groups.values())
        for optimiser in optimisers.values():
            optimiser.step()
            optimiser.zero_grad()
        updater.step()
        collector.update_policy_weights_()
    collector.shutdown()  # closes the env too


def test_unbatched_env_and_torchrl_primer_discovery():
    policy = build_policy("concat")
    primer = get_primers_from_module(policy)
    assert set(primer.primers.keys()) == {"state", "belief", "free_state", "free_belief", "previous_action"}
    env = make_env("sprites", seed=0, max_steps=MAX_STEPS).append_transform(primer)
    rollout = env.rollout(4, policy)
    assert rollout["action"].shape == (4, A) and rollout["next", "state"].shape == (4, 8)


def test_missing_primer_and_bad_configuration_are_reported():
    policy = build_policy()
    td = TensorDict(
        {"pixels": torch.zeros(3, 64, 64, dtype=torch.uint8), "is_init": torch.ones(1, dtype=torch.bool)}
    )
    with pytest.raises(KeyError, match="make_tensordict_primer"):
        policy(td)
    with pytest.raises(ValueError, match="exploration_noise"):
        IsoDreamV2Policy(policy.world_model, policy.actor, policy.policy_input, exploration_noise=-1.0)
    dreamer = IsoDreamV2WorldModel(IsoDreamV2Config.dreamerv2("tiny", action_dim=A))
    with pytest.raises(ValueError, match="free branch"):
        IsoDreamV2Policy(dreamer, policy.actor, policy.policy_input)


def test_single_branch_world_model_acts_on_the_controllable_state():
    wm = IsoDreamV2WorldModel(IsoDreamV2Config.dreamerv2("tiny", action_dim=A))
    policy_input = PolicyInput.for_world_model(wm, mode="controllable")
    actor = IsoDreamV2Actor(in_features=policy_input.out_features, action_dim=A, num_cells=8, depth=2)
    policy = IsoDreamV2Policy(wm, actor, policy_input)
    assert set(policy.recurrent_spec().keys()) == {"state", "belief", "previous_action"}
    env = make_env("sprites", seed=0, max_steps=MAX_STEPS).append_transform(policy.make_tensordict_primer())
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(3, policy)
    features = torch.cat([rollout["next", "state"], rollout["next", "belief"]], dim=-1)
    torch.testing.assert_close(rollout["action"], actor.mode(features))


def test_exploration_noise_is_added_to_sampled_actions_only():
    policy = build_policy()
    noisy = IsoDreamV2Policy(policy.world_model, policy.actor, policy.policy_input, exploration_noise=10.0)
    td = policy.make_tensordict_primer().primers.zero().expand(64).clone()
    td.update(
        {
            "pixels": torch.zeros(64, 3, 64, 64, dtype=torch.uint8),
            "is_init": torch.ones(64, 1, dtype=torch.bool),
        }
    )
    with set_exploration_type(ExplorationType.RANDOM):
        assert (policy(td.clone())["action"].abs() < 1).all()
        assert (noisy(td.clone())["action"].abs() == 1).float().mean() > 0.5  # clamped to [-1, 1]
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.manual_seed(0)
        clean = policy(td.clone())["action"]
        torch.manual_seed(0)
        torch.testing.assert_close(noisy(td.clone())["action"], clean)
