"""A TorchRL user's own env trains without editing the package: any gymnasium id through its render, or a
factory named in the config (``env=gym env.name=<id>``, ``env.factory=module:function``)."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from isodream_rl.envs import make_env, wrap_gym_env
from isodream_rl.trainers import ConfigError, RunConfig, train, validate_config
from isodream_rl.trainers.builders import env_factory
from tests.test_cli import composed

ENV_ID = "isodream_test/Dot-v0"


class Dot(gym.Env):
    """A red dot on black that the action moves (bounds [-2, 2]), drawn 40x48 by ``render``."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, render_mode=None, speed: float = 1.0):
        self.render_mode = render_mode
        self.speed = speed
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-2.0, 2.0, (2,), dtype=np.float32)
        self.position = np.zeros(2, np.float32)
        self.actions = []

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.position = self.np_random.uniform(-0.5, 0.5, 2).astype(np.float32)
        return self.position.copy(), {}

    def step(self, action):
        self.actions.append(np.asarray(action))
        self.position = np.clip(self.position + 0.05 * self.speed * np.asarray(action), -1, 1).astype(
            np.float32
        )
        return self.position.copy(), float(-np.abs(self.position).sum()), False, False, {}

    def render(self):
        frame = np.zeros((40, 48, 3), np.uint8)
        y, x = ((self.position + 1) / 2 * (np.array([39, 47]))).astype(int)
        frame[max(y - 3, 0) : y + 4, max(x - 3, 0) : x + 4, 0] = 255
        return frame


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=Dot, max_episode_steps=30)


def make_dot_env(speed: float = 1.0):
    """An env factory as a user writes one: their gymnasium env, wrapped by ``wrap_gym_env``."""
    from isodream_rl.envs.builder import RenderedPixels

    return wrap_gym_env(RenderedPixels(gym.wrappers.TimeLimit(Dot(render_mode="rgb_array", speed=speed), 30)))


def test_a_gymnasium_id_gives_64x64_pixels_and_actions_in_the_unit_box():
    env = make_env(ENV_ID, seed=0)
    td = env.rollout(5)
    assert td["next", "pixels"].shape == (5, 3, 64, 64) and td["next", "pixels"].dtype == torch.uint8
    assert (td["next", "pixels"][:, 0] > 0).any() and (td["next", "pixels"][:, 1:] == 0).all()  # the red dot
    assert (env.action_spec.space.low == -1).all() and (env.action_spec.space.high == 1).all()
    env.step(env.reset().set("action", torch.ones(2)))
    inner = env.base_env.env.unwrapped
    np.testing.assert_allclose(inner.actions[-1], [2.0, 2.0])  # [-1, 1] rescaled to the env's bounds
    with pytest.raises(ValueError, match="registered gymnasium id"):
        make_env("NoSuchEnv-v9")


def test_isodream_train_runs_on_a_gymnasium_id_and_on_a_factory(tmp_path):
    def tiny(name: str, **env) -> RunConfig:
        # what `isodream-train env=gym env.name=<id> size=tiny` composes, shrunk further
        cfg = composed("env=gym", f"env.name={ENV_ID}", "size=tiny", f"run_dir={tmp_path / name}")
        cfg.model.size, cfg.model.actor_units, cfg.model.value_units, cfg.model.attention_dim = (
            "tiny",
            16,
            16,
            8,
        )
        cfg.train.batch_size, cfg.train.sequence_length, cfg.train.buffer_size = 2, 6, 100
        cfg.train.prefill_steps, cfg.train.frames_per_batch, cfg.train.total_steps = 10, 10, 20
        cfg.train.threads = 1
        cfg.algo.horizon, cfg.algo.attention_window = 3, 2
        cfg.logging.progress_bar, cfg.logging.eval_every, cfg.logging.final_eval_episodes = False, 0, 1
        cfg.logging.video_length, cfg.logging.video_context = 6, 3
        for key, value in env.items():
            setattr(cfg.env, key, value)
        return cfg

    result = train(tiny("by_id"))
    assert result.env_steps == 20 and result.updates > 0 and result.checkpoint is not None
    cfg = tiny("by_factory", factory=f"{__name__}:make_dot_env", kwargs={"speed": 2.0})
    validate_config(cfg)
    assert env_factory(cfg)().base_env.env.unwrapped.speed == 2.0
    assert train(cfg).updates > 0
    with pytest.raises(ConfigError, match="env.factory"):
        validate_config(tiny("bad", factory=f"{__name__}:no_such_function"))


def test_an_env_with_a_discrete_action_space_is_refused_saying_what_to_give():
    with pytest.raises(
        ValueError, match=r"CartPole-v1 has a discrete action space \(Discrete\(2\)\).*continuous"
    ):
        make_env("CartPole-v1")
    cfg = composed("env=gym", "env.name=CartPole-v1", "size=tiny")
    from isodream_rl.trainers.run_lifecycle import probe_action_dim

    with pytest.raises(
        ConfigError, match=r"env.name='CartPole-v1'.*give an env whose action space is continuous"
    ):
        probe_action_dim(cfg)
