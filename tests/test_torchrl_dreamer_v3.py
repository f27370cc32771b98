"""``algo=torchrl_dreamer_v3``: TorchRL's DreamerV3 behind the run interface (sizes, settings, stepper, policy,
keys, input errors, an exact resume). What it shares with ``algo=torchrl_dreamer`` (shared weights, non-finite
skipping, the policy's carried state, train + resume) is tested for both in ``tests/test_torchrl_dreamer.py``, whose
helpers this file uses."""

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type
from torchrl.objectives import DreamerV3ActorLoss, DreamerV3Loss, DreamerV3ModelLoss, DreamerV3ValueLoss
from torchrl.trainers.algorithms import DreamerV3Optimizer

import isodream_rl.cli  # noqa: F401  (registers the config schema)
from isodream_rl.baselines import DreamerV3Widths, TorchRLDreamerV3Components
from isodream_rl.baselines.torchrl_dreamer_v3 import dreamer_v3_model_loss, make_torchrl_dreamer_v3
from isodream_rl.modules.dreamer_v3 import TORCHRL_DREAMER_V3_SETTINGS
from isodream_rl.run_utils.checkpoint import set_rng_state
from isodream_rl.trainers import CheckpointManager, ConfigError, RunConfig, validate_config
from isodream_rl.trainers.hooks import ReplayPreparation
from isodream_rl.trainers.isodream_v2 import make_world_model_loss
from tests.test_torchrl_dreamer import A, B, T, env_batch, replay_batch, tiny_config

CONFIGS = Path(isodream_rl.cli.__file__).parent / "configs"
ALGO = "torchrl_dreamer_v3"


def composed(*overrides) -> RunConfig:
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return OmegaConf.to_object(compose(config_name="config", overrides=list(overrides)))


def loss_batch(components, **changes) -> TensorDict:
    """A ``[B, T]`` batch as ``DreamerV3Loss`` reads it, with entries replaced (``None`` removes one)."""
    batch = components.stepper.prepare(replay_batch()).reshape(B, T)
    for key, value in changes.items():
        key = tuple(key.split("__")) if "__" in key else key
        if value is None:
            del batch[key]
        else:
            batch.set(key, value)
    return batch


def params_of(stepper, name: str) -> list[torch.Tensor]:
    return [p for group in stepper.optimizers[name].param_groups for p in group["params"]]


@pytest.fixture(scope="module")
def components(tmp_path_factory):
    torch.manual_seed(0)
    cfg = tiny_config(tmp_path_factory.mktemp("run"), ALGO)
    return TorchRLDreamerV3Components(cfg, action_dim=A, scratch_dir=tmp_path_factory.mktemp("scratch"))


class TestComposition:
    def test_torchrl_dreamerv3_losses_and_optimisers(self, components):
        learner = components.learner
        assert isinstance(components.model_loss, DreamerV3ModelLoss)
        assert isinstance(learner.actor_loss, DreamerV3ActorLoss)
        assert isinstance(learner.value_loss, DreamerV3ValueLoss)
        assert isinstance(learner.loss_module, DreamerV3Loss)
        assert components.world_model is None  # no open-loop prediction in the evaluation
        assert set(components.stepper.optimizers) == {"world_model", "actor", "value"}
        assert all(isinstance(o, DreamerV3Optimizer) for o in components.stepper.optimizers.values())
        check_env_specs(learner.model_based_env)

    def test_widths_follow_dreamerv3s_size_rule(self, components):
        widths = DreamerV3Widths.from_run(tiny_config("unused", ALGO))
        assert (widths.hidden, widths.deter, widths.classes) == (32, 256, 2)  # tiny: hidden_dim 16 x 1.875
        prior = components.learner.world_model[2].rssm_prior.module
        assert prior.recurrent_model == "block_gru" and prior.rnn_hidden_dim == 256
        assert (prior.num_categoricals, prior.num_classes) == (32, 2)
        encoder = components.learner.world_model[1].module
        assert encoder.out_channels == 2 * 4  # depth = hidden / 16, times the last stage's multiplier 4

    @pytest.mark.parametrize("size", ["bench", "small"])
    def test_world_model_has_isodreams_parameter_count(self, size):
        """Matched to the DreamerV2-style learner's three-branch world model: 1.84 M vs 1.87 M at bench, 7.15 M vs
        6.74 M at small."""
        ours = composed(f"size={size}", "algo=isodream_v2")
        ours_count = sum(
            p.numel() for p in make_world_model_loss(ours, action_dim=A).world_model.parameters()
        )
        v3 = make_torchrl_dreamer_v3(action_dim=A, widths=DreamerV3Widths.from_run(composed(f"size={size}")))
        v3_count = sum(p.numel() for p in v3.world_model.parameters())
        assert abs(v3_count / ours_count - 1) < 0.07, (v3_count, ours_count)

    def test_dreamerv3_settings_are_those_of_torchrls_reproduction(self, components):
        learner, settings = components.learner, TORCHRL_DREAMER_V3_SETTINGS
        model_loss, actor_loss, value_loss = learner.model_loss, learner.actor_loss, learner.value_loss
        assert (model_loss.kl_mode, model_loss.free_bits, model_loss.unimix) == ("separate", 1.0, 0.01)
        assert (model_loss.lambda_dynamic, model_loss.lambda_representation) == (1.0, 0.1)
        assert model_loss.continue_target_scale == pytest.approx(1 - 1 / 333)
        assert (
            model_loss.reward_two_hot and model_loss.num_reward_bins == 255 and not model_loss.detach_output
        )
        assert (
            actor_loss.use_reinforce and actor_loss.entropy_bonus == 3e-4 and actor_loss.return_normalization
        )
        assert actor_loss.return_normalization_quantiles == (0.05, 0.95)
        assert (actor_loss.return_normalization_rate, actor_loss.return_normalization_min_scale) == (
            0.01,
            1.0,
        )
        estimator = actor_loss.value_estimator
        assert (float(estimator.gamma), float(estimator.lmbda)) == pytest.approx((1.0, 0.95))
        assert value_loss.value_loss == "two_hot" and value_loss.slow_critic_regularization == 1.0
        assert learner.target_updater.eps == pytest.approx(1 - 0.02)  # SoftUpdate(tau=0.02)
        assert learner.loss_module.replay_value_loss_weight == 0.3
        optimizer = components.stepper.optimizers["world_model"]
        assert {k: optimizer.defaults[k] for k in ("agc", "eps", "warmup_steps")} == {
            "agc": settings.agc,
            "eps": 1e-20,
            "warmup_steps": 1000,
        }
        assert [g["lr"] for g in optimizer.param_groups] == [RunConfig().train.world_model_lr]

    def test_every_trained_parameter_is_in_one_optimiser(self, components):
        """(The policy and imagination share the trained weights: tests/test_torchrl_dreamer.py.)"""
        trained = {id(p) for module in components.modules().values() for p in module.parameters()}
        groups = {
            name: {id(p) for p in params_of(components.stepper, name)} for name in ("world_model", "actor")
        }
        assert groups["world_model"].isdisjoint(groups["actor"])
        optimised = set().union(
            *({id(p) for p in params_of(components.stepper, n)} for n in components.stepper.optimizers)
        )
        assert trained == optimised  # every trained parameter once, and the slow critic in none


class TestStepper:
    def test_updates_step_world_model_actor_and_value(self, components):
        """The optimiser's warm-up gives the first update a learning rate of 0: two updates move every group."""
        stepper = components.stepper
        before = {name: [p.detach().clone() for p in params_of(stepper, name)] for name in stepper.optimizers}
        updates = stepper.updates
        for _ in range(2):
            metrics = stepper.step(None, replay_batch(init_at=4, done_at=3))
        assert stepper.updates == updates + 2
        assert {k for k in metrics.keys() if k.startswith("loss_")} == {
            "loss_model_reco",
            "loss_model_reward",
            "loss_model_dynamic",
            "loss_model_representation",
            "loss_model_continue",
            "loss_actor",
            "loss_value",
            "loss_replay_value",
        }
        assert {"grad_norm_world_model", "grad_norm_actor", "grad_norm_value", "nonfinite_skipped"} <= set(
            metrics.keys()
        )
        assert all(math.isfinite(float(v)) for v in metrics.values()) and metrics["nonfinite_skipped"] == 0
        for name in stepper.optimizers:
            assert any(not torch.equal(a, b) for a, b in zip(params_of(stepper, name), before[name])), name

    def test_world_model_warmup_trains_the_world_model_alone(self, tmp_path):
        torch.manual_seed(0)
        cfg = tiny_config(tmp_path, ALGO, world_model_warmup=2)
        parts = TorchRLDreamerV3Components(cfg, action_dim=A, scratch_dir=tmp_path / "scratch")
        stepper = parts.stepper
        actor = [p.detach().clone() for p in params_of(stepper, "actor")]
        for _ in range(2):
            metrics = stepper.step(None, replay_batch())
            assert math.isnan(metrics["loss_actor"]) and math.isfinite(metrics["loss_model_reco"])
        assert all(torch.equal(a, b) for a, b in zip(params_of(stepper, "actor"), actor))
        # the actor's and value's optimisers start counting (bias correction, warm-up) when they start learning
        counts = {name: opt.param_groups[0]["step"] for name, opt in stepper.optimizers.items()}
        assert counts == {"world_model": 2, "actor": 0, "value": 0}
        assert math.isfinite(stepper.step(None, replay_batch())["loss_actor"])
        assert stepper.optimizers["actor"].param_groups[0]["step"] == 1


PIXELS = torch.randint(0, 256, (B, T, 3, 64, 64), dtype=torch.uint8)
#: The messages (patterns) of tests/test_faults.py for Iso-Dream's world model, on the same bad batches.
BAD_INPUTS = {
    "float pixels in [0, 255]": (
        {"next__pixels": PIXELS.float()},
        r"must be in \[0, 1\].*\[0, 255\].*divide .* by 255",
    ),
    "float pixels in [-0.5, 0.5]": (
        {"next__pixels": PIXELS.float() / 255 - 0.5},
        r"must be in \[0, 1\].*add 0.5",
    ),
    "NaN pixels": ({"next__pixels": torch.full((B, T, 3, 64, 64), float("nan"))}, "NaN or inf"),
    "inf action": ({"action": torch.full((B, T, A), float("inf"))}, "'action' holds NaN or inf"),
    "no is_init": ({"is_init": None}, "needs 'is_init'"),
    "63x63 pixels": ({"next__pixels": PIXELS[..., :63, :63]}, r"\[\*batch, 3, 64, 64\]"),
}


class TestInputs:
    @pytest.mark.parametrize("case", list(BAD_INPUTS), ids=list(BAD_INPUTS))
    def test_bad_batches_get_the_other_algos_one_line_errors(self, components, case):
        changes, message = BAD_INPUTS[case]
        with pytest.raises(ValueError, match=message) as error:
            components.model_loss(loss_batch(components, **changes))
        assert "\n" not in str(error.value)

    def test_one_step_window_is_refused(self, components):
        with pytest.raises(ValueError, match="at least 2 steps.*got T=1"):
            components.model_loss(loss_batch(components)[:, :1])

    def test_float_pixels_in_0_1_give_the_uint8_loss(self, components):
        batch = loss_batch(components)
        floats = batch.clone().set(("next", "pixels"), batch["next", "pixels"].float() / 255)
        torch.manual_seed(3)
        reference, _ = components.model_loss(batch)
        torch.manual_seed(3)
        same, _ = components.model_loss(floats)
        for key in reference.keys():
            torch.testing.assert_close(same[key], reference[key])


class Renamed(TensorDictModuleBase):
    """The world model with its outputs written under ``("next", "out_<key>")``: other key names."""

    def __init__(self, world_model, keys):
        super().__init__()
        self.world_model, self.keys = world_model, keys
        self.in_keys, self.out_keys = world_model.in_keys, [("next", f"out_{k}") for k in keys]

    def forward(self, tensordict):
        out = self.world_model(tensordict)
        for key in self.keys:
            out.rename_key_(("next", key), ("next", f"out_{key}"))
        return out


class TestKeys:
    def test_model_loss_keys_remap_through_set_keys(self, components):
        outputs = ["reco_pixels", "reward_logits", "prior_logits", "posterior_logits", "continue_pred"]
        batch = loss_batch(components)
        renamed_batch = batch.clone()
        renamed_batch.rename_key_(("next", "reward"), ("next", "rew"))
        torch.manual_seed(1)
        reference, _ = components.model_loss(batch.clone())
        loss = dreamer_v3_model_loss(Renamed(components.learner.world_model, outputs))
        with pytest.raises(KeyError):
            loss(renamed_batch.clone())
        loss.set_keys(reward="rew", **{key: f"out_{key}" for key in outputs})
        torch.manual_seed(1)
        remapped, _ = loss(renamed_batch.clone())
        assert set(remapped.keys()) == set(reference.keys())
        for key in reference.keys():
            torch.testing.assert_close(remapped[key], reference[key])

    def test_replay_value_reads_the_remapped_reward(self, components):
        """``DreamerV3Loss``'s replay-value term reads the reward through the value loss's keys."""
        learner = components.learner
        batch = loss_batch(components)
        torch.manual_seed(2)
        reference = learner.loss_module(batch.clone())["replay_value"]
        renamed = batch.clone()
        renamed.set(("next", "rew"), renamed["next", "reward"])
        renamed.set(("next", "reward"), torch.zeros_like(renamed["next", "reward"]) + 100.0)
        learner.value_loss.set_keys(reward="rew")
        try:
            torch.manual_seed(2)
            remapped = learner.loss_module(renamed)["replay_value"]
        finally:
            learner.value_loss.set_keys(reward="reward")
        # the model loss still reads ("next", "reward") (set to 100), the replay value ("next", "rew")
        torch.testing.assert_close(remapped, reference)


class TestPolicy:
    """(Acting, the reset at ``is_init`` and a primed env: tests/test_torchrl_dreamer.py, for both baselines.)"""

    def test_carries_the_action_and_samples_one_hot_categoricals(self, components):
        out = components.behavior.policy(env_batch(components.behavior.policy))
        torch.testing.assert_close(out["next", "previous_action"], out["action"])
        assert out["next", "state"].reshape(3, -1, 2).sum(-1).eq(1).all()  # one-hot categoricals

    def test_evaluation_takes_the_actors_mean(self, components):
        policy = components.behavior.policy
        td = env_batch(policy)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            torch.manual_seed(0)
            a = policy(td.clone())
            torch.manual_seed(0)
            b = policy(td.clone())
        torch.testing.assert_close(a["action"], b["action"])
        with set_exploration_type(ExplorationType.RANDOM):
            torch.manual_seed(0)
            c = policy(td.clone())
        # the same posterior sample (same seed), then the mean against a sample of the actor
        torch.testing.assert_close(a["next", "state"], c["next", "state"])
        assert not torch.allclose(a["action"], c["action"])


def assert_resume_is_exact(builder, cfg, tmp_path):
    """Components restored from a checkpoint continue with the uninterrupted run's metrics, bit for bit (optimiser
    moments and counters, slow critic, return statistics, random generators); ``builder(cfg, action_dim=...,
    scratch_dir=...)`` builds the components of a DreamerV3-learner run."""
    manager = CheckpointManager(tmp_path / "checkpoints", keep=2)
    torch.manual_seed(0)
    live = builder(cfg, action_dim=A, scratch_dir=tmp_path / "scratch_a")
    steps = TensorDict(
        {
            "action": torch.rand(40, A) * 2 - 1,
            "is_init": (torch.arange(40) % 20 == 0)[:, None],
            ("next", "pixels"): torch.randint(0, 256, (40, 3, 64, 64), dtype=torch.uint8),
            ("next", "reward"): torch.randn(40, 1),
            ("next", "done"): (torch.arange(40) % 20 == 19)[:, None],
            ("next", "terminated"): torch.zeros(40, 1, dtype=torch.bool),
            ("next", "truncated"): (torch.arange(40) % 20 == 19)[:, None],
        },
        [40],
    )
    live.replay_buffer.extend(ReplayPreparation(num_envs=1, capacity_per_env=200)(steps))

    def update(parts) -> dict[str, float]:
        return {k: float(v) for k, v in parts.stepper.step(None, parts.replay_buffer.sample()).items()}

    for _ in range(3):
        update(live)
    manager.save(3, live.state(cfg, env_steps=0, trainer=None), replay_buffer=live.replay_buffer)
    after = [update(live) for _ in range(2)]
    assert after[0]["loss_actor"] != 0.0 and live.learner.actor_loss.return_high != 0

    restored = builder(cfg, action_dim=A, scratch_dir=tmp_path / "scratch_b")
    state, _ = manager.load_latest(replay_buffer=restored.replay_buffer)
    restored.load_models(state)
    restored.stepper.load_state_dict(state["stepper"])
    set_rng_state(state["rng"])
    assert [update(restored) for _ in range(2)] == after


def test_resume_is_exact(tmp_path):
    assert_resume_is_exact(TorchRLDreamerV3Components, tiny_config(tmp_path / "run", ALGO), tmp_path)


def test_bf16_is_refused_in_one_line(tmp_path):
    cfg = tiny_config(tmp_path, ALGO)
    cfg.model.precision = "bf16"
    with pytest.raises(ConfigError, match="fp32 only.*drop the override"):
        DreamerV3Widths.from_run(cfg)


def test_world_model_mode_is_refused(tmp_path):
    cfg = tiny_config(tmp_path, ALGO)
    cfg.mode = "world_model"
    with pytest.raises(
        ConfigError,
        match="mode=world_model trains the world model of Iso-Dream's learners.*pick one of algo=isodream,",
    ):
        validate_config(cfg)
