import logging

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from isodream_rl.envs import SpritesEnv, make_env, make_parallel_env
from isodream_rl.envs.builder import SimulatorFaultGuard, wrap_gym_env


def _fixed_rollout(env, actions: torch.Tensor):
    """Rolls ``env`` out under fixed actions ``[T, *batch, A]``, resetting at episode ends."""
    it = iter(actions)
    return env.rollout(
        actions.shape[0], policy=lambda td: td.set("action", next(it)), break_when_any_done=False
    )


class _FaultySprites(gym.Wrapper):
    """A sprites env whose simulator raises once, on its ``fail_at``-th step."""

    def __init__(self, fail_at: int):
        super().__init__(SpritesEnv(max_steps=50))
        self.fail_at = fail_at
        self.calls = 0

    def step(self, action):
        self.calls += 1
        if self.calls == self.fail_at:
            raise RuntimeError("injected physics blow-up")
        return self.env.step(action)


def test_sprites_env_specs_pass_with_uint8_chw_pixels_and_float_actions():
    env = make_env("sprites", seed=0, task="reach")
    check_env_specs(env)
    assert env.observation_spec["pixels"].shape == (3, 64, 64)
    assert env.observation_spec["pixels"].dtype == torch.uint8
    assert env.action_spec.dtype == torch.float32
    assert (env.action_spec.space.low == -1).all() and (env.action_spec.space.high == 1).all()
    td = env.rollout(3)
    assert td["next", "reward"].shape == (3, 1) and td["next", "reward"].dtype == torch.float32
    assert td["is_init"][:, 0].tolist() == [True, False, False]
    assert td["next", "step_count"][:, 0].tolist() == [1, 2, 3]
    for key in ("done", "terminated", "truncated"):
        assert td["next", key].shape == (3, 1)


@pytest.mark.parametrize(
    "name, cfg",
    [
        ("highway", {"view": "top_down", "vehicles_count": 5}),
        ("highway", {"view": "first_person", "vehicles_count": 5}),
        ("dmc_walker_walk", {"background": "video_easy", "video_source": "procedural"}),
    ],
)
def test_highway_and_dmc_specs_pass_and_seeds_reproduce_episodes(name, cfg):
    env = make_env(name, seed=0, **cfg)
    check_env_specs(env)
    assert env.observation_spec["pixels"].shape == (3, 64, 64)
    assert env.observation_spec["pixels"].dtype == torch.uint8
    assert env.action_spec.dtype == torch.float32
    assert (env.action_spec.space.low == -1).all() and (env.action_spec.space.high == 1).all()
    shape = env.action_spec.shape
    actions = torch.rand(4, *shape, generator=torch.Generator().manual_seed(0)) * 2 - 1
    env.set_seed(5)
    a = _fixed_rollout(env, actions)
    b = _fixed_rollout(make_env(name, seed=5, **cfg), actions)
    assert torch.equal(a["next", "pixels"], b["next", "pixels"])
    assert torch.equal(a["next", "reward"], b["next", "reward"])


def test_dmc_background_mask_appears_in_the_step_output_when_requested():
    env = make_env("dmc_cheetah_run", seed=0, return_masks=True, video_source="procedural")
    td = env.rollout(2)
    assert td["next", "mask_background"].shape == (2, 64, 64)
    assert td["next", "mask_background"].any() and td["next", "mask_agent"].any()
    assert torch.equal(td["next", "mask_distractors"], td["next", "mask_background"])


def test_pixels_are_the_seeded_gymnasium_frame_in_chw():
    obs, _ = SpritesEnv().reset(seed=4)
    td = make_env("sprites", seed=4).reset()
    np.testing.assert_array_equal(td["pixels"].permute(1, 2, 0).numpy(), obs)


def test_same_seed_gives_same_episodes_across_resets():
    actions = torch.rand(12, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    a = _fixed_rollout(make_env("sprites", seed=1, task="reach", max_steps=5), actions)
    b = _fixed_rollout(make_env("sprites", seed=1, task="reach", max_steps=5), actions)
    c = _fixed_rollout(make_env("sprites", seed=2, task="reach", max_steps=5), actions)
    assert a["next", "truncated"].sum() == 2  # two episode ends inside the window
    assert torch.equal(a["next", "pixels"], b["next", "pixels"])
    assert torch.equal(a["next", "reward"], b["next", "reward"])
    assert not torch.equal(a["next", "pixels"], c["next", "pixels"])


def test_sprites_masks_appear_in_the_step_output_when_requested():
    env = make_env("sprites", seed=0, task="reach", return_masks=True)
    check_env_specs(env)
    td = env.rollout(4)
    for key in ("mask_agent", "mask_distractors", "mask_target"):
        assert td["next", key].shape == (4, 64, 64) and td["next", key].dtype == torch.bool
    pixels = td["next", "pixels"].permute(0, 2, 3, 1)
    agent_pixels = pixels[td["next", "mask_agent"]]
    assert ((agent_pixels == 255).all(-1) | (agent_pixels == 0).all(-1)).all()
    assert "mask_agent" not in make_env("sprites", seed=0).reset().keys()


def test_parallel_sprites_envs_run_in_two_workers_reproducibly():
    actions = torch.rand(6, 2, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1  # [T, worker, A]
    results = []
    for _ in range(2):
        env = make_parallel_env("sprites", num_workers=2, seed=3, mp_start_method="fork", max_steps=4)
        try:
            if not results:
                check_env_specs(env)
                env.set_seed(3)  # check_env_specs stepped the workers; restart them from the seed
            results.append(_fixed_rollout(env, actions))
        finally:
            env.close()
    td = results[0]
    assert td.batch_size == (2, 6) and td["next", "pixels"].shape == (2, 6, 3, 64, 64)
    assert not torch.equal(td["next", "pixels"][0], td["next", "pixels"][1])  # workers get distinct seeds
    assert torch.equal(td["next", "pixels"], results[1]["next", "pixels"])
    assert td["next", "truncated"][:, 3].all()


def test_unknown_env_name_lists_the_valid_ones():
    with pytest.raises(ValueError, match="'sprites', 'highway'.*dmc_walker_walk"):
        make_env("carla")
    with pytest.raises(ValueError, match="dmc_cheetah_run"):
        make_env("dmc_walker_fly")


def test_return_masks_is_rejected_for_envs_without_ground_truth():
    with pytest.raises(ValueError, match=r"'sprites', 'highway' and 'dmc_\*' have them, 'Pendulum-v1' not"):
        make_env("Pendulum-v1", return_masks=True)


@pytest.mark.parametrize("view", ["top_down", "first_person"])
def test_highway_masks_appear_in_the_step_output_when_requested(view):
    env = make_env("highway", seed=0, return_masks=True, view=view, vehicles_count=10)
    check_env_specs(env)
    td = env.rollout(3)
    for key in ("mask_agent", "mask_vehicles", "mask_distractors"):
        assert td["next", key].shape == (3, 64, 64) and td["next", key].dtype == torch.bool
    assert not (td["next", "mask_agent"] & td["next", "mask_vehicles"]).any()
    assert td["next", "mask_agent"].any() == (view == "top_down")
    plain = make_env("highway", seed=0, view=view, vehicles_count=10)
    assert "mask_agent" not in plain.reset().keys() and plain.base_env.env.unwrapped.masks is False


def test_wrong_action_shape_raises_a_clear_error():
    env = make_env("sprites", seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match=r"expects an action of shape \(2,\), got shape \(3,\)"):
        env.step(td.set("action", torch.zeros(3)))


def test_simulator_fault_ends_the_episode_with_a_warning(caplog):
    env = wrap_gym_env(_FaultySprites(fail_at=3), seed=0, name="faulty_sprites")
    with caplog.at_level(logging.WARNING, logger="isodream_rl.envs.builder"):
        td = env.rollout(6, break_when_any_done=False)
    truncated = td["next", "truncated"][:, 0]
    assert truncated.tolist() == [False, False, True, False, False, False]
    assert td["next", "sim_error"].tolist() == [False, False, True, False, False, False]
    assert not td["next", "terminated"].any()
    assert td["next", "reward"][2].item() == 0.0
    # The failed step repeats the last good frame, and a fresh episode starts after it.
    assert torch.equal(td["next", "pixels"][2], td["next", "pixels"][1])
    assert td["is_init"][:, 0].tolist() == [True, False, False, True, False, False]
    (record,) = [r for r in caplog.records if "injected physics blow-up" in r.getMessage()]
    assert record.levelno == logging.WARNING
    assert "faulty_sprites" in record.getMessage() and "RuntimeError" in record.getMessage()


def test_fault_guard_rescales_unit_actions_to_the_env_bounds():
    class Recorder(gym.Env):
        observation_space = gym.spaces.Box(0, 255, (8, 8, 3), np.uint8)
        action_space = gym.spaces.Box(np.array([0.0, -4.0]), np.array([2.0, 4.0]), dtype=np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros((8, 8, 3), np.uint8), {}

        def step(self, action):
            self.last = action
            return np.zeros((8, 8, 3), np.uint8), 0.0, False, False, {}

    guard = SimulatorFaultGuard(Recorder())
    guard.reset()
    assert guard.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    guard.step(np.array([-1.0, 0.5]))
    np.testing.assert_allclose(guard.unwrapped.last, [0.0, 2.0])


def test_gymnasium_ids_are_registered_on_import():
    env = gym.make("isodream/Sprites-v0", task="reach")
    obs, info = env.reset(seed=0)
    assert obs.shape == (64, 64, 3) and "mask_agent" in info
    assert "isodream/Highway-v0" in gym.registry
    assert "isodream/DMC-walker-walk-video_easy-v0" in gym.registry
    assert "isodream/DMC-cheetah-run-none-v0" in gym.registry
