"""Specification of the actor and value losses (paper eq. 7, DreamerV2 lambda-returns)."""

import pathlib
import re

import pytest
import torch
from tensordict import TensorDict

from isodream_rl.modules import PolicyInput
from isodream_rl.modules.isodream_v2 import (
    IsoDreamV2Actor,
    IsoDreamV2Config,
    IsoDreamV2Value,
    IsoDreamV2WorldModel,
)
from isodream_rl.objectives.isodream_v2 import (
    IsoDreamV2ActorLoss,
    IsoDreamV2Imagination,
    IsoDreamV2ValueLoss,
    lambda_returns,
    make_target_updater,
)
from isodream_rl.objectives.isodream_v2.imagination import policy_features

A, L, N = 2, 5, 6
GAMMA, LMBDA = 0.99, 0.95
DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs" / "behavior.md"


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny tensors: a second intra-op thread only adds synchronisation, which costs 10x on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def reference_lambda_returns(reward, next_value, discount, lmbda):
    """Plain loop over time: G_j = r_j + d_j ((1 - lambda) v_{j+1} + lambda G_{j+1}), G_{L-1} = r + d v_L.

    ``reward[j]``, ``discount[j]`` and ``next_value[j] = v(s_{j+1})`` belong to the transition j -> j + 1.
    """
    horizon = len(reward)
    returns = [None] * horizon
    returns[-1] = reward[-1] + discount[-1] * next_value[-1]
    for j in reversed(range(horizon - 1)):
        returns[j] = reward[j] + discount[j] * ((1 - lmbda) * next_value[j] + lmbda * returns[j + 1])
    return returns


def build(mode="attention", gradient="dynamics", attention_through_actor=False, **wm_kwargs):
    wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=A, **wm_kwargs))
    policy_input = PolicyInput.for_world_model(wm, mode=mode, window=3, width=8)
    imagination = IsoDreamV2Imagination(wm, policy_input, horizon=L)
    value_loss = IsoDreamV2ValueLoss(
        IsoDreamV2Value(in_features=policy_input.out_features, num_cells=8), imagination
    )
    actor = IsoDreamV2Actor(in_features=policy_input.out_features, action_dim=A, num_cells=8, depth=2)
    actor_loss = IsoDreamV2ActorLoss(
        actor,
        imagination,
        value_loss,
        gamma=GAMMA,
        lmbda=LMBDA,
        gradient=gradient,
        attention_through_actor=attention_through_actor,
    )
    return wm, actor_loss, value_loss


def start_batch(wm, batch_shape=(N,)):
    return TensorDict(
        {("next", k): torch.randn_like(v) for k, v in wm.initial_state(batch_shape).items()}, batch_shape
    )


@pytest.mark.parametrize("per_step_gamma", [False, True])
def test_lambda_returns_equal_the_reference_loop(per_step_gamma):
    reward, next_value = torch.randn(4, L, 1), torch.randn(4, L, 1)
    gamma = GAMMA * torch.rand(4, L, 1) if per_step_gamma else GAMMA
    discount = gamma if per_step_gamma else torch.full_like(reward, GAMMA)
    expected = reference_lambda_returns(reward.unbind(1), next_value.unbind(1), discount.unbind(1), LMBDA)
    torch.testing.assert_close(lambda_returns(reward, next_value, gamma, LMBDA), torch.stack(expected, 1))


def test_actor_targets_are_aligned_reference_returns_with_continuation_weights():
    wm, actor_loss, value_loss = build(discount_head=True)
    _, imagined = actor_loss(start_batch(wm))
    nxt = imagined["next"]
    next_value = value_loss.target_value(policy_features(value_loss.policy_input, nxt))
    discount = GAMMA * nxt["continuation"]
    expected = reference_lambda_returns(
        nxt["reward"].unbind(1), next_value.unbind(1), discount.unbind(1), LMBDA
    )
    torch.testing.assert_close(imagined["lambda_target"], torch.stack(expected, 1), rtol=1e-5, atol=1e-6)
    # Not time-reversed (the authors' bug): the last return bootstraps from the value after the last step.
    last = nxt["reward"][:, -1] + discount[:, -1] * next_value[:, -1]
    torch.testing.assert_close(imagined["lambda_target"][:, -1], last, rtol=1e-5, atol=1e-6)
    weight = imagined["discount_weight"]
    torch.testing.assert_close(weight[:, 0], torch.ones(N, 1))
    for j in range(1, L):
        torch.testing.assert_close(weight[:, j], discount[:, :j].prod(1), rtol=1e-5, atol=1e-6)


def test_value_loss_regresses_the_value_of_each_state_on_its_own_return():
    wm, actor_loss, value_loss = build()
    _, imagined = actor_loss(start_batch(wm))
    losses, _ = value_loss(imagined)
    value = value_loss.value_network(policy_features(value_loss.policy_input, imagined))
    expected = (imagined["discount_weight"] * 0.5 * (value - imagined["lambda_target"]) ** 2).mean()
    torch.testing.assert_close(losses["loss_value"], expected)
    torch.testing.assert_close(imagined["state_value"], value.detach())


@pytest.mark.parametrize("gradient", ["dynamics", "reinforce"])
@pytest.mark.parametrize("mode", ["attention", "controllable", "concat"])
def test_actor_and_value_losses_never_change_the_world_model(mode, gradient):
    wm, actor_loss, value_loss = build(mode=mode, gradient=gradient, reward_uses_free=mode != "controllable")
    groups = actor_loss.parameter_groups()
    before = [p.detach().clone() for p in groups["world_model"]]
    optimisers = [torch.optim.Adam(groups[name], lr=1e-2) for name in ("actor", "value")]
    for _ in range(2):
        losses, imagined = actor_loss(start_batch(wm))
        value_losses, _ = value_loss(imagined)
        (losses["loss_actor"] + value_losses["loss_value"]).backward()
        assert all(p.grad is None for p in groups["world_model"])
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in groups["actor"])
        for optimiser in optimisers:
            optimiser.step()
            optimiser.zero_grad()
    assert all(torch.equal(a, b) for a, b in zip(before, groups["world_model"]))
    assert all(p.requires_grad for p in wm.parameters())


def test_attention_learns_from_the_value_loss_only_unless_asked():
    for through_actor in (False, True):
        wm, actor_loss, value_loss = build(attention_through_actor=through_actor)
        attention = list(value_loss.policy_input.parameters())
        losses, _ = actor_loss(start_batch(wm))
        losses["loss_actor"].backward()
        reached = [p.grad is not None for p in attention]
        assert any(reached) == through_actor
        assert all(p.grad is None for p in value_loss.value_network.parameters())
        for p in attention:
            p.grad = None
        _, imagined = actor_loss(start_batch(wm))
        value_loss(imagined)[0]["loss_value"].backward()
        assert all(p.grad is not None for p in attention)


def test_dynamics_gradient_reaches_the_actor_through_the_world_model_only():
    wm, actor_loss, _ = build(mode="controllable")
    actor_loss.entropy_bonus = 0.0
    losses, _ = actor_loss(start_batch(wm))
    losses["loss_actor"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor_loss.actor.parameters())


def test_reinforce_scores_detached_actions():
    wm, actor_loss, _ = build(gradient="reinforce")
    losses, imagined = actor_loss(start_batch(wm))
    assert imagined["next", "state"].grad_fn is None
    losses["loss_actor"].backward()
    assert all(p.grad is not None for p in actor_loss.actor.parameters())


def test_parameter_groups_are_disjoint_and_cover_every_module():
    wm, actor_loss, value_loss = build()
    groups = actor_loss.parameter_groups()
    ids = [{id(p) for p in params} for params in groups.values()]
    assert sum(map(len, ids)) == len(set().union(*ids))
    everything = [*wm.parameters(), *actor_loss.actor.parameters(), *value_loss.value_network.parameters()]
    everything += list(value_loss.policy_input.parameters())
    assert set().union(*ids) == {id(p) for p in everything}
    assert {id(p) for p in actor_loss.parameters()} == ids[1]
    assert {id(p) for p in value_loss.parameters()} == ids[2]


def test_slow_value_is_copied_every_period_updates():
    wm, actor_loss, value_loss = build()
    updater = make_target_updater(value_loss, period=3)
    source = value_loss.value_network.net[0].weight
    target = value_loss.target_value_network_params["net", "0", "weight"]
    assert torch.equal(source, target)
    for step in range(1, 7):
        with torch.no_grad():
            source.add_(1.0)
        updater.step()
        assert torch.equal(source, target) == (step % 3 == 0)


def test_missing_start_keys_and_targets_are_reported():
    wm, actor_loss, value_loss = build()
    with pytest.raises(KeyError, match="set_keys"):
        actor_loss(TensorDict({"state": torch.zeros(2, 8)}, [2]))
    with pytest.raises(KeyError, match="lambda_target"):
        value_loss(TensorDict({}, [2, 3]))
    with pytest.raises(ValueError, match="actor gradient"):
        IsoDreamV2ActorLoss(actor_loss.actor, actor_loss.imagination, value_loss, gradient="ppo")


def test_docs_snippet_runs():
    """The "use the modules in your own TorchRL loop" snippet of docs/behavior.md."""
    text = DOCS.read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "docs/behavior.md has no python block"
    exec(compile(blocks[0], str(DOCS), "exec"), {})


def test_loc_penalty_is_the_squared_pre_tanh_mean_and_reaches_the_actor_only():
    wm, actor_loss, value_loss = build(mode="controllable")
    assert actor_loss.loc_penalty == 0.1  # the library's default
    torch.manual_seed(0)
    losses, imagined = actor_loss(start_batch(wm))
    loc, _ = actor_loss.actor(imagined["attended_state"])
    torch.testing.assert_close(losses["loss_actor_loc"], 0.1 * loc.pow(2).mean())
    torch.testing.assert_close(losses["actor_loc_abs"], loc.abs().mean().detach())
    losses["loss_actor_loc"].backward()
    assert all(p.grad is None for p in wm.parameters()) and all(
        p.grad is None for p in value_loss.parameters()
    )
    assert all(p.grad is not None for p in actor_loss.actor.parameters())

    actor_loss.loc_penalty = 0.0  # the paper's loss: no term, the diagnostic stays
    losses, _ = actor_loss(start_batch(wm))
    assert "loss_actor_loc" not in losses.keys() and "actor_loc_abs" in losses.keys()
    with pytest.raises(ValueError, match="loc_penalty must be >= 0"):
        IsoDreamV2ActorLoss(actor_loss.actor, actor_loss.imagination, value_loss, loc_penalty=-1.0)
