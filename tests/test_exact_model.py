"""The behavior learner on an exact model of sprites ``reach`` (``isodream_rl.evaluation.exact_sprites``).

The model is the env itself written in torch, so these tests separate what the behavior learner can do from
what a young world model lets it do: the default's learner (DreamerV3's, ``algo=isodream``,
``isodream_rl.evaluation.exact_sprites_behavior``), checked to be the one a run builds, must learn the task, and it must
recover once an early, systematic reward error of the model is gone (the lock-in that real runs show when their
world model is still young). The DreamerV2-style learner (``algo=isodream_v2``) is checked to be the one a run of
it builds and to train; how it learns and recovers, with and without its loc penalty, is
``bench/exact_model.py --variants isodream_v2,paper``'s (``docs/results/exact_model_isodream_v2.json``).
"""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import DreamerV3ActorLoss
from torchrl.trainers.algorithms import DreamerV3Optimizer

from isodream_rl.envs.sprites import SpritesEnv
from isodream_rl.evaluation import ExactSpritesModel
from isodream_rl.evaluation.exact_sprites_behavior import make_exact_model_behavior
from isodream_rl.modules.isodream.world_model import IsoDreamConfig
from isodream_rl.objectives.isodream import make_isodream
from isodream_rl.objectives.isodream_v2 import IsoDreamV2ActorLoss
from isodream_rl.trainers import RunConfig
from isodream_rl.trainers.exact_model import exact_model_learner, train_behavior_on_exact_model
from isodream_rl.trainers.learners import ISODREAM_ALGOS, resolved

#: start states per update: a quarter of the bench's B * T = 512, so that the two learning tests take about 2.5
#: minutes of one core (DreamerV3's learner: about 0.14 s per update)
BATCH = 128


@pytest.fixture
def one_thread():
    """One torch thread, as ``bench/exact_model.py`` trains the learner: its updates are small ops, which the
    second thread of ``conftest.py`` only slows down, and on a busy machine (CI's two workers on two cores) by
    several times, its threads waiting for each other."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def bench_behavior_config(algo: str = "isodream") -> RunConfig:
    """The learning bench's behavior (``size=bench``: 128-unit actor and value, horizon 15) of ``algo`` at the
    library's defaults for sprites (``env.domain=sprites``, which ``env=sprites`` picks: the DreamerV2-style
    learner's table has the discount 0.9 there, which DreamerV3's learner does not read), on ``[s, h]`` (the exact
    model has no noncontrollable branch)."""
    cfg = RunConfig()
    cfg.algo.name = algo
    cfg.env.domain = "sprites"
    cfg.algo.policy_input = "controllable"
    cfg.model.actor_units = cfg.model.value_units = 128
    cfg.train.threads = 1
    return cfg


def test_the_model_steps_like_the_env_until_the_first_reach():
    env = SpritesEnv(task="reach", num_distractors=0, sprite_size=0.1)
    model = ExactSpritesModel(sprite_size=0.1)
    rng = np.random.default_rng(0)
    compared = reaches = 0
    for episode in range(20):
        env.reset(seed=episode)
        # the env stores (row, col) = (y, x); the model (x, y), in units of the frame
        state = torch.tensor([[*env._agent[::-1], *env._target[::-1]]], dtype=torch.float32) / 64
        for _ in range(60):
            action = rng.uniform(-1.3, 1.3, size=2)  # beyond the bounds too: both clip
            if rng.random() < 0.5:  # steer at the target half the time, so reaches happen
                action = model.scripted_action(state)[0].numpy()
            _, reward, _, _, info = env.step(action.astype(np.float32))
            next_state, model_reward, reached = model.step(
                state, torch.as_tensor(action, dtype=torch.float32)[None]
            )
            assert model_reward.item() == pytest.approx(reward, abs=1e-4)
            assert reached.item() == info["reached"]
            assert next_state[0, :2].numpy() * 64 == pytest.approx(env._agent[::-1], abs=1e-3)
            compared += 1
            if info["reached"]:  # the reach: both respawn their target at random, so the episodes part here
                reaches += 1
                assert not torch.equal(next_state[0, 2:], state[0, 2:])
                break
            state = next_state
    assert compared > 200 and reaches >= 5


def test_the_reward_is_differentiable_in_the_action_and_the_error_points_one_way():
    model = ExactSpritesModel(reward_error=0.3, error_direction=(0.0, 1.0))
    state = torch.tensor([[0.5, 0.5, 0.2, 0.5]])  # the target to the left
    action = torch.zeros(1, 2, requires_grad=True)
    _, _, _, reward = model.imagine_step(state, torch.zeros(1, 1), action)
    assert reward.shape == (1, 1)
    reward.sum().backward()
    # moving left earns progress (10 * 0.05 per unit action); the error pays 0.3 per unit of +y
    assert action.grad[0].tolist() == pytest.approx([-0.5, 0.3], abs=1e-4)
    with pytest.raises(ValueError, match=r"states \[N, 4\] with actions \[N, 2\]"):
        model.imagine_step(state, torch.zeros(1, 1), torch.zeros(1, 3))


def test_the_learner_learns_the_task_on_the_exact_model(one_thread):
    # evaluated at the start and after the last update, the one asserted
    result = train_behavior_on_exact_model(bench_behavior_config(), updates=600, batch=BATCH, eval_every=600)
    assert result.scripted_return > 100 and abs(result.constant_return) < 5
    # the deterministic policy heads for the target and scores most of the scripted controller's return
    assert result.cosine[-1] > 0.8, result.as_dict()
    assert result.returns[-1] >= 0.8 * result.scripted_return, result.as_dict()


def test_the_exact_model_trains_the_learner_of_algo_isodream():
    """The actor, critic and losses on the exact model are those of ``make_isodream`` (which composes its own),
    and imagination steps the exact model, its reward error included."""
    world_model_config = IsoDreamConfig(
        action_dim=2,
        hidden=16,
        image_depth=2,
        units=16,
        free_branch=False,
        static_branch=False,
        inverse_dynamics=False,
        reward_uses_free=False,
    )
    run = make_isodream(
        world_model_config, policy_input="controllable", actor_units=8, value_units=8, horizon=7
    )
    model = ExactSpritesModel(reward_error=0.3, error_direction=(0.0, 1.0))
    exact = make_exact_model_behavior(model, actor_units=8, value_units=8, horizon=7)
    ours, theirs = exact.losses.actor_loss, run.actor_loss
    for name in (
        "imagination_horizon",
        "entropy_bonus",
        "use_reinforce",
        "discount_loss",
        "return_normalization",
    ):
        assert getattr(ours, name) == getattr(theirs, name), name
    assert ours.retnorm.quantiles == theirs.retnorm.quantiles
    assert (ours.retnorm.rate, ours.retnorm.min_scale) == (theirs.retnorm.rate, theirs.retnorm.min_scale)
    for name in ("gamma", "lmbda"):
        assert float(getattr(ours.value_estimator, name)) == float(getattr(theirs.value_estimator, name)), (
            name
        )
    ours_v, theirs_v = exact.losses.value_loss, run.value_loss
    for name in ("value_loss", "slow_critic_regularization", "discount_loss"):
        assert getattr(ours_v, name) == getattr(theirs_v, name), name
    assert ours_v.value_bins.shape == theirs_v.value_bins.shape
    assert exact.losses.target_updater.eps == pytest.approx(run.target_updater.eps)
    for a, b in ((exact.actor, run.actor), (exact.value, run.value)):
        assert [type(m).__name__ for m in a.modules()] == [type(m).__name__ for m in b.modules()]
    # imagination: the model's step (the belief is the step's reward), the exact continuation 1 - 1/333
    state, belief = model.initial_state(4)
    losses, imagined = ours(TensorDict({"state": state, "belief": belief}, [4]))
    next_state, reward, _ = model.step(imagined["state"][:, 0], imagined["action"][:, 0])
    assert torch.allclose(imagined["next", "state"][:, 0], next_state)
    assert torch.allclose(imagined["next", "reward"][:, 0, 0], reward)
    assert torch.allclose(imagined["next", "belief"][:, 0, 0], reward)
    assert float(losses["continuation_mean"]) == pytest.approx(1 - 1 / run.loss_module.continuation_horizon)
    assert float(losses["continuation_mean"]) == pytest.approx(run.model_loss.continue_target_scale)


@pytest.mark.parametrize(
    "algo", ["isodream", "isodream_no_static", "isodream_v2", "isodream_paper", "dreamerv2"]
)
def test_the_exact_model_trains_the_learner_of_the_runs_algo(algo):
    """DreamerV3's learner for the default and its ablations (a ``DreamerV3Optimizer`` per group, its own adaptive
    clipping); the DreamerV2-style one for the other algos: ``make_behavior``'s losses with the run's loc penalty
    and discount, Adam at the run's learning rates clipped at ``train.grad_clip``."""
    cfg = bench_behavior_config(algo)
    learner = exact_model_learner(cfg, ExactSpritesModel())
    assert set(learner.optimizers) == {"actor", "value"}
    if algo in ISODREAM_ALGOS:
        assert isinstance(learner.actor_loss, DreamerV3ActorLoss) and learner.grad_clip == math.inf
        assert all(isinstance(opt, DreamerV3Optimizer) for opt in learner.optimizers.values())
        return
    actor_loss, cfg = learner.actor_loss, resolved(cfg)
    assert cfg.algo.gamma == 0.9  # the sprites domain's
    assert isinstance(actor_loss, IsoDreamV2ActorLoss) and learner.grad_clip == cfg.train.grad_clip
    assert (actor_loss.loc_penalty, actor_loss.gamma) == (cfg.algo.actor_loc_penalty, cfg.algo.gamma)
    for name, lr in (("actor", cfg.train.actor_lr), ("value", cfg.train.value_lr)):
        optimizer = learner.optimizers[name]
        assert type(optimizer) is torch.optim.Adam and optimizer.param_groups[0]["lr"] == lr, name


def test_the_dreamerv2_style_learner_trains_and_is_evaluated_on_the_exact_model():
    """``train_behavior_on_exact_model`` runs the DreamerV2-style learner for ``algo=isodream_v2`` (a few updates:
    the path, not the learning, which the bench measures)."""
    result = train_behavior_on_exact_model(
        bench_behavior_config("isodream_v2"), updates=20, batch=16, eval_every=10, eval_episodes=2
    )
    assert result.updates == [0, 10, 20]
    assert all(np.isfinite(result.returns)) and all(np.isfinite(result.entropy))
    assert result.scripted_return > result.constant_return


def test_the_learner_recovers_from_an_early_fixed_direction_reward_error(one_thread):
    result = train_behavior_on_exact_model(
        bench_behavior_config(), updates=500, batch=BATCH, reward_error=0.3, error_updates=250, eval_every=250
    )
    # while the error lasts the policy follows it into the wall; 250 exact updates later it has the task back
    # (the bench's aim allows 500: bench/exact_model.py)
    assert result.returns[1] < 0.1 * result.scripted_return, result.as_dict()
    assert result.returns[-1] >= 0.5 * result.scripted_return, result.as_dict()
