"""The TorchRL baselines behind the run interface. What both share, parametrized over ``algo=torchrl_dreamer`` and
``algo=torchrl_dreamer_v3`` (shared weights, non-finite skipping, windows, the acting policy's carried state, train
+ resume), then ``algo=torchrl_dreamer``'s own (TorchRL's Dreamer: widths, stepper, rollout reset, evaluation).
DreamerV3's own are in ``tests/test_torchrl_dreamer_v3.py``, which imports the helpers here."""

import json
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type
from torchrl.objectives import DreamerActorLoss, DreamerModelLoss, DreamerValueLoss

from isodream_rl.baselines import TorchRLDreamerComponents, TorchRLDreamerV3Components
from isodream_rl.envs import make_env
from isodream_rl.modules import SIZE_PRESETS
from isodream_rl.trainers import RunConfig, train

TINY = SIZE_PRESETS["tiny"]
S, D, A = TINY["state_dim"], TINY["belief_dim"], 2
B, T = 2, 8
BUILDERS = {"torchrl_dreamer": TorchRLDreamerComponents, "torchrl_dreamer_v3": TorchRLDreamerV3Components}
#: widths of each baseline's ``"state"`` and ``"belief"`` at size=tiny (DreamerV3: 32 categoricals of 2 classes,
#: a GRU state of 8 x hidden 32)
LATENT = {"torchrl_dreamer": (S, D), "torchrl_dreamer_v3": (32 * 2, 256)}


def tiny_config(tmp_path, algo: str = "torchrl_dreamer", **train_changes) -> RunConfig:
    cfg = RunConfig(run_dir=str(tmp_path), size_name="tiny")
    cfg.algo.name, cfg.algo.policy_input = algo, "controllable"
    cfg.algo.free_branch = cfg.algo.static_branch = cfg.algo.inverse_dynamics = False
    cfg.model.size, cfg.model.actor_units, cfg.model.value_units = "tiny", 16, 16
    cfg.train.batch_size, cfg.train.sequence_length, cfg.train.buffer_size = B, T, 200
    cfg.train.prefill_steps, cfg.train.frames_per_batch, cfg.train.total_steps = 20, 20, 60
    cfg.train.threads = 1
    for name, value in train_changes.items():
        setattr(cfg.train, name, value)
    cfg.algo.horizon = 3
    cfg.logging.progress_bar, cfg.logging.eval_every, cfg.logging.final_eval_episodes = False, 0, 1
    cfg.logging.log_every = 20
    cfg.logging.video_length, cfg.logging.video_context = 6, 3
    cfg.env.kwargs = {"task": "reach", "max_steps": 20}
    return cfg


def replay_batch(*, init_at: int | None = None, done_at: int | None = None) -> TensorDict:
    """A flat ``[B * T]`` sample with the replay buffer's keys (root ``"pixels"`` is not stored)."""
    is_init = torch.zeros(B, T, 1, dtype=torch.bool)
    is_init[:, 0] = True  # SliceSampler marks every window start
    done = torch.zeros(B, T, 1, dtype=torch.bool)
    if init_at is not None:
        is_init[:, init_at] = True
    if done_at is not None:
        done[:, done_at] = True
    return TensorDict(
        {
            "action": torch.rand(B * T, A) * 2 - 1,
            "is_init": is_init.reshape(B * T, 1),
            ("next", "pixels"): torch.randint(0, 256, (B * T, 3, 64, 64), dtype=torch.uint8),
            ("next", "reward"): torch.randn(B * T, 1),
            ("next", "done"): done.reshape(B * T, 1),
            ("next", "terminated"): torch.zeros(B * T, 1, dtype=torch.bool),
            ("next", "truncated"): done.reshape(B * T, 1),
        },
        [B * T],
    )


def env_batch(policy, n=3, is_init=False) -> TensorDict:
    """An env step's input to ``policy``: its primer's zeros, random uint8 pixels, ``is_init``."""
    td = policy.make_tensordict_primer().primers.zero().expand(n).clone()
    td.update(
        {
            "pixels": torch.randint(0, 256, (n, 3, 64, 64), dtype=torch.uint8),
            "is_init": torch.full((n, 1), is_init),
        }
    )
    return td


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """``build(algo)``: that baseline's components at the test sizes, built once per module (seed 0)."""
    built = {}

    def get(algo: str):
        if algo not in built:
            torch.manual_seed(0)
            cfg = tiny_config(tmp_path_factory.mktemp("run"), algo)
            built[algo] = BUILDERS[algo](cfg, action_dim=A, scratch_dir=tmp_path_factory.mktemp("scratch"))
        return built[algo]

    return get


@pytest.fixture
def components(build):
    return build("torchrl_dreamer")


@pytest.fixture(params=sorted(BUILDERS))
def baseline(request, build):
    """``(algo, components)`` of each baseline."""
    return request.param, build(request.param)


class TestBothBaselines:
    def test_policy_and_imagination_share_the_trained_weights(self, baseline):
        _, parts = baseline
        trained = {id(p) for module in parts.modules().values() for p in module.parameters()}
        assert {id(p) for p in parts.behavior.policy.parameters()} <= trained
        assert {id(p) for p in parts.behavior.actor_loss.model_based_env.parameters()} <= trained
        world_model = {id(p) for p in parts.modules()["world_model"].parameters()}
        actor = {id(p) for p in parts.modules()["actor"].parameters()}
        assert world_model.isdisjoint(actor)

    def test_nonfinite_update_is_skipped(self, baseline):
        _, parts = baseline
        stepper, world_model = parts.stepper, parts.modules()["world_model"]
        params = [p.detach().clone() for p in world_model.parameters()]
        batch = replay_batch()
        batch["next", "reward"][0] = math.nan
        metrics = stepper.step(None, batch)
        assert metrics["nonfinite_skipped"] == 1 and stepper.nonfinite_in_a_row == 1
        assert all(torch.equal(a, b) for a, b in zip(world_model.parameters(), params))
        stepper.step(None, replay_batch())
        assert stepper.nonfinite_in_a_row == 0

    def test_sample_not_a_multiple_of_the_window_is_rejected(self, baseline):
        _, parts = baseline
        with pytest.raises(ValueError, match="not a multiple of the window length"):
            parts.stepper.step(None, replay_batch()[:-1])


class TestBothPolicies:
    def test_acts_and_writes_the_next_recurrent_state(self, baseline):
        algo, parts = baseline
        state_dim, belief_dim = LATENT[algo]
        out = parts.behavior.policy(env_batch(parts.behavior.policy))
        assert out["action"].shape == (3, A) and out["action"].abs().max() <= 1
        assert out["next", "state"].shape == (3, state_dim) and out["next", "belief"].shape == (3, belief_dim)
        assert "encoded_latents" not in out.keys() and "loc" not in out.keys()

    def test_resets_the_carried_state_at_is_init(self, baseline):
        _, parts = baseline
        policy = parts.behavior.policy
        fresh = env_batch(policy, is_init=True)
        stale = fresh.clone()
        stale["state"], stale["belief"] = (
            torch.rand(3, stale["state"].shape[-1]),
            torch.randn(3, stale["belief"].shape[-1]),
        )
        if "previous_action" in stale.keys():
            stale["previous_action"] = torch.ones(3, A)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            torch.manual_seed(0)
            a = policy(fresh.clone())
            torch.manual_seed(0)
            b = policy(stale.clone())
            stale["is_init"][:] = False
            torch.manual_seed(0)
            c = policy(stale.clone())
        torch.testing.assert_close(a["action"], b["action"])
        torch.testing.assert_close(a["next", "belief"], b["next", "belief"])
        assert not torch.allclose(a["action"], c["action"])
        assert not torch.allclose(a["next", "belief"], c["next", "belief"])

    def test_runs_in_a_primed_env(self, baseline):
        _, parts = baseline
        policy = parts.behavior.policy
        env = make_env("sprites", task="reach", max_steps=20)
        env.append_transform(policy.make_tensordict_primer())
        rollout = env.rollout(5, policy)
        assert rollout["belief"][0].abs().max() == 0  # primer zeros at reset
        torch.testing.assert_close(rollout["belief"][1:], rollout["next", "belief"][:-1])
        assert rollout["belief"][1:].abs().sum() > 0
        if "previous_action" in policy.widths:
            torch.testing.assert_close(rollout["previous_action"][1:], rollout["action"][:-1])


@pytest.mark.parametrize("algo", sorted(BUILDERS))
def test_train_writes_a_summary_and_resumes(algo, tmp_path):
    cfg = tiny_config(tmp_path, algo)
    result = train(cfg)
    assert result.env_steps == 60 and result.updates > 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["algo"] == algo and summary["eval_episodes"] == 1
    assert math.isfinite(summary["eval_return"])
    assert math.isfinite(result.metrics["loss_model_reco"]) and math.isfinite(result.metrics["loss_actor"])
    assert result.checkpoint is not None and result.checkpoint.exists()

    cfg.resume, cfg.train.total_steps = True, 80
    resumed = train(cfg)
    assert resumed.resumed_from == result.checkpoint
    assert resumed.env_steps == 80 and resumed.updates > result.updates


class TestComponents:
    def test_torchrl_losses_at_the_preset_widths(self, components):
        assert isinstance(components.model_loss, DreamerModelLoss)
        assert isinstance(components.behavior.actor_loss, DreamerActorLoss)
        assert isinstance(components.behavior.value_loss, DreamerValueLoss)
        assert components.world_model is None  # no open-loop prediction in the evaluation
        prior = components.behavior.model_based_env.world_model[0][0].module
        assert prior.rnn.hidden_size == D and prior.state_dim == S
        assert prior.action_state_projector[0].out_features == TINY["hidden_dim"]
        encoder_first = components.dreamer_world_model[0][0].module.encoder[0]
        assert encoder_first.out_channels == TINY["depth"]
        check_env_specs(components.behavior.model_based_env)

    def test_one_update_steps_world_model_actor_and_value(self, components):
        stepper = components.stepper
        before = {
            name: [p.detach().clone() for g in opt.param_groups for p in g["params"]]
            for name, opt in stepper.optimizers.items()
        }
        updates = stepper.updates
        metrics = stepper.step(None, replay_batch(init_at=4))
        assert stepper.updates == updates + 1
        assert set(metrics.keys()) == {
            "loss_model_kl",
            "loss_model_reco",
            "loss_model_reward",
            "grad_norm_world_model",
            "loss_actor",
            "grad_norm_actor",
            "loss_value",
            "grad_norm_value",
            "nonfinite_skipped",
        }
        assert all(math.isfinite(float(v)) for v in metrics.values())
        assert metrics["nonfinite_skipped"] == 0
        for name, opt in stepper.optimizers.items():
            after = [p for g in opt.param_groups for p in g["params"]]
            assert any(not torch.equal(a, b) for a, b in zip(after, before[name])), name

    def test_rollout_restarts_from_zeros_at_is_init(self, components):
        """With the noise fixed at 0, a window reset at step 4 continues exactly as a window starting there."""

        def posteriors(sample):
            td = components.stepper.prepare(sample).reshape(1, -1)
            td["prior_noise"] = torch.zeros(*td.shape, S)
            td["posterior_noise"] = torch.zeros(*td.shape, S)
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                return components.dreamer_world_model(td)

        sample = replay_batch()[:T]
        tail = posteriors(sample[4:].clone())
        sample["is_init"][4] = True
        reset = posteriors(sample.clone())
        torch.testing.assert_close(reset["next", "state"][0, 4:], tail["next", "state"][0])
        assert reset["belief"][0, 4].abs().max() == 0
        sample["is_init"][4] = False
        carried = posteriors(sample.clone())
        assert not torch.allclose(carried["next", "state"][0, 4:], tail["next", "state"][0])


class TestPolicy:
    def test_the_prior_advances_the_belief_from_zeros(self, components):
        out = components.behavior.policy(env_batch(components.behavior.policy))
        assert out["next", "belief"].abs().sum() > 0

    def test_deterministic_in_evaluation_random_otherwise(self, components):
        policy = components.behavior.policy
        td = env_batch(policy)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            a, b = policy(td.clone()), policy(td.clone())
        torch.testing.assert_close(a["action"], b["action"])
        torch.testing.assert_close(a["next", "state"], b["next", "state"])
        with set_exploration_type(ExplorationType.RANDOM):
            c, d = policy(td.clone()), policy(td.clone())
        assert not torch.allclose(c["action"], d["action"])
        # exploration type unset: samples too
        assert not torch.allclose(policy(td.clone())["action"], policy(td.clone())["action"])
