"""Trainer pieces: config checks, the three-optimiser stepper (NaN skipping), open-loop predictions, replay hooks."""

import math

import pytest
import torch
from tensordict import TensorDict

from isodream_rl.trainers import (
    ConfigError,
    IsoDreamOptimizationStepper,
    IsoDreamV2Components,
    NonFiniteLossError,
    RunConfig,
    validate_config,
)
from isodream_rl.trainers.hooks import ReplayPreparation
from isodream_rl.trainers.openloop import open_loop_prediction, prediction_frames, save_gif
from tests.conftest import tiny_run_config


def tiny_config(tmp_path, **algo) -> RunConfig:
    return tiny_run_config(tmp_path, **{f"algo__{key}": value for key, value in algo.items()})


def replay_batch(batch: int = 2, time: int = 6, action_dim: int = 2) -> TensorDict:
    return TensorDict(
        {
            "action": torch.rand(batch * time, action_dim) * 2 - 1,
            ("next", "pixels"): torch.randint(0, 256, (batch * time, 3, 64, 64), dtype=torch.uint8),
            ("next", "reward"): torch.randn(batch * time, 1),
            "is_init": torch.zeros(batch * time, 1, dtype=torch.bool),
        },
        [batch * time],
    )


@pytest.fixture(scope="module")
def components(tmp_path_factory):
    torch.manual_seed(0)
    cfg = tiny_config(tmp_path_factory.mktemp("run"))
    return IsoDreamV2Components(cfg, action_dim=2, scratch_dir=tmp_path_factory.mktemp("scratch"))


class TestConfig:
    def test_default_config_is_valid(self):
        validate_config(RunConfig())

    def test_attention_without_free_branch_names_the_fix(self, tmp_path):
        cfg = tiny_config(tmp_path, free_branch=False, policy_input="attention")
        with pytest.raises(ConfigError, match="set algo.policy_input=controllable or algo.free_branch=true"):
            validate_config(cfg)

    def test_every_problem_is_listed(self, tmp_path):
        cfg = tiny_config(tmp_path, policy_input="bogus")
        cfg.train.frames_per_batch = 7
        cfg.checkpoint.keep = 1
        with pytest.raises(ConfigError) as err:
            validate_config(cfg)
        message = str(err.value)
        for field in ("algo.policy_input", "train.frames_per_batch", "checkpoint.keep"):
            assert field in message

    def test_prefill_shorter_than_a_window_is_rejected(self, tmp_path):
        cfg = tiny_config(tmp_path)
        cfg.train.prefill_steps = 3
        with pytest.raises(
            ConfigError, match="train.prefill_steps=3 is shorter than one replay window per env"
        ):
            validate_config(cfg)

    def test_resume_without_the_replay_buffer_is_rejected(self, tmp_path):
        cfg = tiny_config(tmp_path)
        cfg.resume, cfg.checkpoint.replay = True, False
        with pytest.raises(ConfigError, match="set checkpoint.replay=true"):
            validate_config(cfg)


class TestStepper:
    def test_optimisers_have_the_paper_settings(self, components):
        optimizers = components.stepper.optimizers
        assert sorted(optimizers) == ["actor", "value", "world_model"]
        expected = {"world_model": 3e-4, "actor": 8e-5, "value": 8e-5}
        for name, optimizer in optimizers.items():
            assert optimizer.defaults["lr"] == expected[name]
            assert optimizer.defaults["eps"] == 1e-5

    def test_attention_is_in_the_value_group(self, components):
        value_params = {
            id(p) for g in components.stepper.optimizers["value"].param_groups for p in g["params"]
        }
        attention = components.behavior.policy_input.parameters()
        assert all(id(p) in value_params for p in attention)

    def test_one_update_steps_all_three_groups(self, components):
        stepper = components.stepper
        before = {
            name: [p.detach().clone() for g in opt.param_groups for p in g["params"]]
            for name, opt in stepper.optimizers.items()
        }
        updates = stepper.updates
        metrics = stepper.step(None, replay_batch())
        assert stepper.updates == updates + 1
        assert metrics["nonfinite_skipped"] == 0
        for key in ("loss_model_reco", "loss_actor", "loss_value", "grad_norm_world_model"):
            assert math.isfinite(float(metrics[key]))
        for name, opt in stepper.optimizers.items():
            after = [p for g in opt.param_groups for p in g["params"]]
            assert any(not torch.equal(a, b) for a, b in zip(after, before[name])), name

    def test_world_model_warmup_trains_the_world_model_alone_first(self, tmp_path):
        torch.manual_seed(0)
        cfg = tiny_config(tmp_path)
        cfg.train.world_model_warmup = 2
        stepper = IsoDreamV2Components(cfg, action_dim=2, scratch_dir=tmp_path / "scratch").stepper

        def snapshot(name):
            return [p.detach().clone() for g in stepper.optimizers[name].param_groups for p in g["params"]]

        def changed(name, before):
            return any(not torch.equal(a, b) for a, b in zip(snapshot(name), before))

        for update in range(3):
            before = {name: snapshot(name) for name in stepper.optimizers}
            metrics = stepper.step(None, replay_batch())
            warm = update < 2
            assert changed("world_model", before["world_model"])
            assert changed("actor", before["actor"]) != warm and changed("value", before["value"]) != warm
            assert math.isnan(float(metrics["loss_actor"])) == warm
            assert metrics["nonfinite_skipped"] == 0
        assert stepper.updates == 3

    def test_nonfinite_updates_are_skipped_then_stop_the_run(self, components):
        stepper = components.stepper
        params = [p.detach().clone() for p in components.world_model.parameters()]
        bad = replay_batch()
        bad.set(("next", "reward"), torch.full_like(bad.get(("next", "reward")), float("nan")))
        updates = stepper.updates
        for _ in range(stepper.max_nonfinite - 1):
            metrics = stepper.step(None, bad)
            assert metrics["nonfinite_skipped"] == 1
        assert stepper.updates == updates
        assert all(torch.equal(a, b) for a, b in zip(components.world_model.parameters(), params))
        with pytest.raises(NonFiniteLossError, match="updates in a row had a NaN/inf loss"):
            stepper.step(None, bad)
        stepper.nonfinite_in_a_row = 0

    def test_finite_update_resets_the_nonfinite_count(self, components):
        stepper = components.stepper
        bad = replay_batch()
        bad.set(("next", "reward"), torch.full_like(bad.get(("next", "reward")), float("inf")))
        stepper.step(None, bad)
        assert stepper.nonfinite_in_a_row == 1
        stepper.step(None, replay_batch())
        assert stepper.nonfinite_in_a_row == 0

    def test_a_first_skipped_update_returns_the_keys_of_a_full_one(self, tmp_path):
        # The Trainer averages the updates of a batch key by key from the first one's keys.
        stepper = IsoDreamV2Components(
            tiny_config(tmp_path), action_dim=2, scratch_dir=tmp_path / "rb"
        ).stepper
        bad = replay_batch()
        bad.set(("next", "reward"), torch.full_like(bad.get(("next", "reward")), float("nan")))
        skipped, full = stepper.step(None, bad), stepper.step(None, replay_batch())
        assert list(skipped.keys()) == list(full.keys())
        assert math.isnan(float(skipped["loss_actor"])) and math.isfinite(float(full["loss_actor"]))

    @staticmethod
    def attention_after_one_sgd_update(tmp_path, *, through_actor: bool, actor_scale: float = 1.0):
        """The attention's parameters after one update with plain SGD (lr 1: the step is the gradient)."""
        torch.manual_seed(0)
        parts = IsoDreamV2Components(
            tiny_config(tmp_path, attention_through_actor=through_actor), action_dim=2, scratch_dir=tmp_path
        )
        groups = parts.behavior.actor_loss.parameter_groups()
        actor_loss = parts.behavior.actor_loss

        def scaled_actor_loss(model_out):
            losses, imagined = actor_loss(model_out)
            losses["loss_actor"] = losses["loss_actor"] * actor_scale
            return losses, imagined

        stepper = IsoDreamOptimizationStepper(
            model_loss=parts.model_loss,
            world_model_optimizer=torch.optim.SGD(groups["world_model"], lr=1e-3),
            actor_loss=scaled_actor_loss,
            value_loss=parts.behavior.value_loss,
            actor_optimizer=torch.optim.SGD(groups["actor"], lr=1.0),
            value_optimizer=torch.optim.SGD(groups["value"], lr=1.0),
            sequence_length=6,
        )
        torch.manual_seed(1)
        batch = replay_batch()
        before = [p.detach().clone() for p in parts.behavior.policy_input.parameters()]
        assert stepper.step(None, batch)["nonfinite_skipped"] == 0
        return [a.detach() - b for a, b in zip(parts.behavior.policy_input.parameters(), before)]

    def test_attention_through_actor_adds_the_actor_gradient_to_the_attention_update(self, tmp_path):
        plain = self.attention_after_one_sgd_update(tmp_path / "a", through_actor=False)
        without_actor = self.attention_after_one_sgd_update(
            tmp_path / "b", through_actor=False, actor_scale=0.0
        )
        through = self.attention_after_one_sgd_update(tmp_path / "c", through_actor=True)
        assert any(step.abs().sum() > 0 for step in plain)
        # Without the option the actor loss contributes nothing to the attention ...
        for a, b in zip(plain, without_actor):
            torch.testing.assert_close(a, b)
        # ... with it, its gradient is added to the value loss's before the value optimiser steps.
        assert any(not torch.allclose(a, b) for a, b in zip(plain, through))

    def test_attention_through_actor_needs_the_attention_policy_input(self, tmp_path):
        cfg = tiny_config(tmp_path, attention_through_actor=True, policy_input="controllable")
        with pytest.raises(
            ConfigError, match="set algo.policy_input=attention or algo.attention_through_actor"
        ):
            validate_config(cfg)

    def test_sample_not_a_multiple_of_the_window_is_rejected(self, components):
        with pytest.raises(ValueError, match="not a multiple of the window length"):
            components.stepper.step(None, replay_batch()[:-1])


class TestOpenLoop:
    def test_context_steps_match_filtering_and_the_rest_is_imagined(self, components):
        window = replay_batch().reshape(2, 6)
        torch.manual_seed(1)
        prediction = open_loop_prediction(components.world_model, window, context=3)
        assert prediction.batch_size == torch.Size([2, 6])
        assert prediction["imagined"][0].tolist() == [False] * 3 + [True] * 3
        masks = sum(prediction[k] for k in ("mask_control", "mask_free", "mask_static"))
        torch.testing.assert_close(masks, torch.ones_like(masks))
        assert torch.equal(prediction["pixels"], window["next", "pixels"])

    def test_imagination_ignores_observations_after_the_context(self, components):
        window = replay_batch().reshape(2, 6)
        changed = window.clone()
        changed["next", "pixels"][:, 3:] = 255 - changed["next", "pixels"][:, 3:]
        torch.manual_seed(1)
        a = open_loop_prediction(components.world_model, window, context=3)
        torch.manual_seed(1)
        b = open_loop_prediction(components.world_model, changed, context=3)
        torch.testing.assert_close(a["reco_pixels"], b["reco_pixels"])

    def test_gif_has_one_frame_per_step(self, components, tmp_path):
        from PIL import Image

        prediction = open_loop_prediction(components.world_model, replay_batch().reshape(2, 6), context=3)
        path = save_gif(prediction_frames(prediction), tmp_path / "p.gif")
        with Image.open(path) as gif:
            assert gif.n_frames == 6
            assert gif.width == 8 * 128  # truth, prediction, three components and three masks


class TestReplayPreparation:
    def batch(self, shape) -> TensorDict:
        return TensorDict(
            {
                "action": torch.zeros(*shape, 2),
                "pixels": torch.zeros(*shape, 3, 64, 64, dtype=torch.uint8),
                ("next", "pixels"): torch.zeros(*shape, 3, 64, 64, dtype=torch.uint8),
                ("collector", "traj_ids"): torch.zeros(shape, dtype=torch.long),
            },
            shape,
        )

    def test_stream_id_changes_exactly_at_the_write_cursor(self):
        prep = ReplayPreparation(num_envs=1, capacity_per_env=8)
        streams = torch.cat([prep(self.batch([5]))["collector", "stream"] for _ in range(4)])
        assert streams.tolist() == [0] * 8 + [1] * 8 + [2] * 4
        assert prep.state_dict() == {"written": 20}

    def test_envs_get_their_own_streams_and_root_pixels_are_dropped(self):
        prep = ReplayPreparation(num_envs=2, capacity_per_env=4)
        out = prep(self.batch([2, 3]))
        prep(self.batch([2, 3]))
        assert out["collector", "stream"].tolist() == [[0, 0, 0], [1, 1, 1]]
        assert "pixels" not in out.keys()
        assert prep(self.batch([2, 3]))["collector", "stream"].tolist() == [[2, 2, 4], [3, 3, 5]]

    def test_windows_cross_episode_starts_but_not_the_stream(self, tmp_path):
        from isodream_rl.trainers.builders import make_replay_buffer

        cfg = tiny_config(tmp_path)
        cfg.train.buffer_size, cfg.train.sequence_length, cfg.train.batch_size = 12, 4, 8
        rb = make_replay_buffer(cfg, scratch_dir=tmp_path / "rb")
        prep = ReplayPreparation(num_envs=1, capacity_per_env=12)
        steps = TensorDict(
            {
                "action": torch.arange(16.0)[:, None].expand(16, 2),
                "is_init": (torch.arange(16) % 3 == 0)[:, None],  # episodes of 3 steps
                ("next", "pixels"): torch.zeros(16, 3, 64, 64, dtype=torch.uint8),
                ("next", "reward"): torch.zeros(16, 1),
            },
            [16],
        )
        for chunk in steps.split(4):
            rb.extend(prep(chunk))
        windows = rb.sample()["action"][:, 0].reshape(-1, 4)
        # Consecutive steps only: the wrapped steps 12..15 (stored at 0..3) never join 4..11.
        assert ((windows[:, 1:] - windows[:, :-1]) == 1).all()


def test_dmc_evaluation_env_uses_the_held_out_videos(tmp_path):
    from isodream_rl.trainers.builders import env_factory

    cfg = tiny_config(tmp_path)
    cfg.env.name = "dmc_walker_walk"
    make = env_factory(cfg, eval_mode=True)
    assert make.keywords["video_split"] == "eval"
    assert "video_split" not in env_factory(cfg).keywords
    env = make()
    assert env.reset()["pixels"].shape == (3, 64, 64)
    env.close()
