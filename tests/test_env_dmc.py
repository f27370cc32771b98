"""DMC with moving backgrounds: spaces, seeding, background motion, exact masks, video splits, bad input."""

import numpy as np
import pytest

from isodream_rl.envs.backgrounds import (
    NATURAL_SOURCES,
    BackgroundSource,
    BackgroundVideos,
    available_sources,
    load_source,
)
from isodream_rl.envs.dmc import BACKGROUNDS, DMCBackgroundEnv, dmc_tasks

# Procedural videos keep the tests free of file decoding; the natural sources are tested on their own.
FAST = {"video_source": "procedural"}


def _make(background="video_easy", domain="walker", task="walk", **kwargs):
    return DMCBackgroundEnv(domain=domain, task=task, background=background, **{**FAST, **kwargs})


def _actions(env, n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, size=(n, *env.action_space.shape)).astype(np.float32)


def _floor_and_sky(env, seg):
    """Pixels a segmentation render labels as skybox (-1) or, for video_hard, a floor-material geom."""
    model = env._env.physics.model
    is_geom = seg[..., 1] == 5  # mjOBJ_GEOM
    background = seg[..., 0] == -1
    if env.background == "video_hard":
        floor_geoms = np.flatnonzero(model.geom_matid == model.name2id("grid", "material"))
        background |= is_geom & np.isin(seg[..., 0], floor_geoms)
    return background


@pytest.fixture(scope="module")
def walker_envs():
    envs = {background: _make(background) for background in BACKGROUNDS}
    yield envs
    for env in envs.values():
        env.close()


def test_spaces_match_observations_and_task(walker_envs):
    env = walker_envs["video_easy"]
    assert env.observation_space.shape == (64, 64, 3) and env.observation_space.dtype == np.uint8
    assert env.action_space.shape == (6,) and env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert info["mask_background"].shape == (64, 64) and info["mask_background"].dtype == bool
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)
    assert isinstance(reward, float) and not terminated and not truncated
    assert "walker-walk" in dmc_tasks() and "cheetah-run" in dmc_tasks()
    # the ids are registered from a written-out copy of the suite's task list (no dm_control at import)
    from dm_control import suite

    assert sorted(dmc_tasks()) == sorted(f"{domain}-{task}" for domain, task in suite.ALL_TASKS)


def test_same_seed_gives_same_episode_and_other_seed_differs(walker_envs):
    first, second = walker_envs["video_easy"], _make("video_easy")
    actions = _actions(first, 8)
    runs = []
    for env in (first, second):
        obs, _ = env.reset(seed=7)
        frames, rewards = [obs], []
        for action in actions:
            obs, reward, *_ = env.step(action)
            frames.append(obs)
            rewards.append(reward)
        runs.append((np.stack(frames), rewards, env.current_video))
    second.close()
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1] and runs[0][2] == runs[1][2]
    other, _ = first.reset(seed=8)
    assert not np.array_equal(other, runs[0][0][0])


def test_background_moves_while_agent_follows_plain_physics(walker_envs):
    video, plain = walker_envs["video_easy"], walker_envs["none"]
    actions = _actions(video, 12, seed=1)
    obs_v, info = video.reset(seed=3)
    obs_p, _ = plain.reset(seed=3)
    previous = obs_v
    for action in actions:
        obs_v, reward_v, *_, info = video.step(action)
        obs_p, reward_p, *_ = plain.step(action)
        mask = info["mask_background"]
        assert reward_v == reward_p
        assert 0.1 < mask.mean() < 0.95
        np.testing.assert_array_equal(obs_v[~mask], obs_p[~mask])
        # The video advanced: the background pixels changed since the previous agent step.
        assert np.any(obs_v[mask] != previous[mask])
        previous = obs_v


@pytest.mark.parametrize("background", ["video_easy", "video_hard"])
def test_mask_is_exactly_sky_and_floor_of_segmentation(walker_envs, background):
    env, plain = walker_envs[background], walker_envs["none"]
    env.reset(seed=5)
    plain.reset(seed=5)
    for action in _actions(env, 6, seed=2):
        obs, *_, info = env.step(action)
        obs_plain, *_ = plain.step(action)
        seg = env._env.physics.render(64, 64, camera_id=env.camera_id, segmentation=True)
        np.testing.assert_array_equal(info["mask_background"], _floor_and_sky(env, seg))
        outside = ~info["mask_background"]
        np.testing.assert_array_equal(obs[outside], obs_plain[outside])


def test_mask_stays_exact_without_shadows():
    video, plain = _make("video_easy", shadows=False), _make("none", shadows=False)
    video.reset(seed=2)
    plain.reset(seed=2)
    for action in _actions(video, 3):
        obs, *_, info = video.step(action)
        obs_plain, *_ = plain.step(action)
        seg = video._env.physics.render(64, 64, camera_id=video.camera_id, segmentation=True)
        np.testing.assert_array_equal(info["mask_background"], _floor_and_sky(video, seg))
        np.testing.assert_array_equal(obs[~info["mask_background"]], obs_plain[~info["mask_background"]])
    video.close()
    plain.close()


def test_plain_env_replaces_nothing(walker_envs):
    _, info = walker_envs["none"].reset(seed=0)
    assert not info["mask_background"].any()
    assert walker_envs["none"].video_sources == ()


def test_hard_background_covers_floor_that_easy_keeps(walker_envs):
    masks = {}
    for background in ("video_easy", "video_hard"):
        _, info = walker_envs[background].reset(seed=4)
        masks[background] = info["mask_background"]
    assert np.all(masks["video_hard"][masks["video_easy"]])
    assert masks["video_hard"].sum() > masks["video_easy"].sum()


def test_each_reset_plays_the_next_video(walker_envs):
    env = walker_envs["video_easy"]
    env.reset(seed=0)
    names = [env.current_video]
    for _ in range(len(env.video_sources) - 1):
        env.reset()
        names.append(env.current_video)
    assert sorted(names) == sorted(env.video_sources)


@pytest.mark.parametrize("video_source", ["natural", "procedural"])
def test_train_and_eval_video_sets_are_disjoint(video_source):
    train = available_sources("train", video_source)
    evaluation = available_sources("eval", video_source)
    assert train and evaluation
    assert not set(train) & set(evaluation)
    files = {s.name: s.path() for s in NATURAL_SOURCES}
    assert not {files.get(n) for n in train} & {files.get(n) for n in evaluation} - {None}


def test_missing_natural_files_fall_back_to_procedural(monkeypatch):
    monkeypatch.setattr(BackgroundSource, "path", lambda self: None)
    with pytest.warns(UserWarning, match="procedural"):
        assert available_sources("eval") == available_sources("eval", "procedural")


def test_natural_sources_load_as_rgb_frames():
    names = available_sources("train") + available_sources("eval")
    assert set(names) <= {s.name for s in NATURAL_SOURCES}, "natural imagery missing from installed packages"
    # The 250-frame bikes clip takes seconds to decode; carphone exercises the same clip path.
    for name in set(names) - {"bikes_clip"}:
        frames = load_source(name)
        assert frames.dtype == np.uint8 and frames.ndim == 4 and frames.shape[-1] == 3
        assert min(frames.shape[1:3]) >= 64 and frames.std() > 10


def test_video_stream_is_deterministic_by_seed():
    def clip(seed):
        video = BackgroundVideos(split="eval", size=32, video_source="procedural", seed=seed).next_video()
        return np.stack([video.frame(t) for t in range(5)])

    np.testing.assert_array_equal(clip(1), clip(1))
    assert not np.array_equal(clip(1), clip(2))


def test_truncates_after_max_sim_steps_and_sums_repeat_rewards_and_renders_last_obs():
    repeat2 = _make("none", max_sim_steps=9, render_mode="rgb_array")
    repeat1 = _make("none", action_repeat=1)
    repeat2.reset(seed=1)
    repeat1.reset(seed=1)
    actions = _actions(repeat2, 5, seed=3)
    for i, action in enumerate(actions):
        obs, reward, terminated, truncated, _ = repeat2.step(action)
        np.testing.assert_array_equal(repeat2.render(), obs)
        expected = repeat1.step(action)[1]
        if i < 4:
            expected += repeat1.step(action)[1]
        assert reward == pytest.approx(expected, abs=1e-12)
        assert not terminated and truncated == (i == 4)
    with pytest.raises(RuntimeError, match="reset"):
        repeat2.step(actions[0])
    repeat1.close()
    repeat2.close()
    assert DMCBackgroundEnv.__init__.__kwdefaults__["max_sim_steps"] == 1000


def test_actions_are_rescaled_to_task_bounds():
    env = DMCBackgroundEnv(domain="quadruped", task="walk", background="none")
    assert env.camera_id == 2
    spec = env._env.action_spec()
    env.reset(seed=0)
    for value, bound in ((1.0, spec.maximum), (-1.0, spec.minimum)):
        env.step(np.full(env.action_space.shape, value, np.float32))
        np.testing.assert_allclose(env._env.physics.control(), bound)
    env.close()


def test_bad_inputs_are_rejected_with_the_valid_choices(walker_envs):
    with pytest.raises(ValueError, match="walker-walk"):
        DMCBackgroundEnv(domain="walker", task="fly")
    with pytest.raises(ValueError, match="cheetah-run"):
        DMCBackgroundEnv(domain="dragon", task="run")
    with pytest.raises(ValueError, match="video_hard"):
        DMCBackgroundEnv(domain="walker", task="walk", background="video_medium")
    with pytest.raises(ValueError, match="eval"):
        DMCBackgroundEnv(domain="walker", task="walk", video_split="test")
    with pytest.raises(ValueError, match="procedural"):
        DMCBackgroundEnv(domain="walker", task="walk", video_source="youtube")
    with pytest.raises(ValueError, match="camera_id"):
        DMCBackgroundEnv(domain="walker", task="walk", camera_id=9)
    env = walker_envs["none"]
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(6,\).*got \(2,\)"):
        env.step(np.zeros(2, np.float32))


@pytest.mark.parametrize("domain,task", [("walker", "walk"), ("cheetah", "run")])
def test_agent_mask_is_the_robot_and_distractors_are_the_video(domain, task):
    env, plain = _make("video_easy", domain, task), _make("none", domain, task)
    env.reset(seed=1)
    plain.reset(seed=1)
    model = env._env.physics.model
    for action in _actions(env, 3, seed=4):
        obs, *_, info = env.step(action)
        obs_plain, *_ = plain.step(action)
        seg = env._env.physics.render(64, 64, camera_id=env.camera_id, segmentation=True)
        robot = (seg[..., 1] == 5) & (model.geom_bodyid[np.maximum(seg[..., 0], 0)] > 0)
        agent, video = info["mask_agent"], info["mask_distractors"]
        assert agent.dtype == bool and agent.shape == (64, 64)
        np.testing.assert_array_equal(agent, robot)
        np.testing.assert_array_equal(video, info["mask_background"])
        assert 0.02 < agent.mean() < 0.5 and not (agent & video).any()
        # the floor of video_easy is neither: it is drawn as in the plain task
        floor = ~agent & ~video
        assert floor.any() and (obs[floor] == obs_plain[floor]).all()
    env.close()
    plain.close()
    _, info = _make("none", masks=False).reset(seed=0)
    assert set(info) == {"mask_background"}
