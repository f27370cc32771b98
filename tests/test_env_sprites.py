import numpy as np
import pytest

from isodream_rl.envs.sprites import DISTRACTOR_COLOURS, SpritesEnv

_PALETTE = np.array(list(DISTRACTOR_COLOURS.values()), dtype=np.uint8)


def _centroid(mask: np.ndarray) -> np.ndarray:
    return np.argwhere(mask).mean(axis=0)


def _rollout(env: SpritesEnv, actions: np.ndarray, seed: int):
    obs, info = env.reset(seed=seed)
    frames, infos, rewards = [obs], [info], []
    for a in actions:
        obs, reward, _, _, info = env.step(a)
        frames.append(obs)
        infos.append(info)
        rewards.append(reward)
    return np.stack(frames), infos, np.array(rewards)


def test_observation_and_masks_have_declared_shapes_and_dtypes():
    env = SpritesEnv(task="reach")
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert obs.shape == (64, 64, 3) and obs.dtype == np.uint8
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)
    assert isinstance(reward, float) and terminated is False and truncated is False
    for key in ("mask_agent", "mask_distractors", "mask_target"):
        assert info[key].shape == (64, 64) and info[key].dtype == bool


def test_same_seed_gives_same_episode_and_other_seed_differs():
    actions = np.random.default_rng(0).uniform(-1, 1, (30, 2))
    f1, i1, r1 = _rollout(SpritesEnv(task="reach"), actions, seed=3)
    f2, i2, r2 = _rollout(SpritesEnv(task="reach"), actions, seed=3)
    f3, _, _ = _rollout(SpritesEnv(task="reach"), actions, seed=4)
    np.testing.assert_array_equal(f1, f2)
    np.testing.assert_array_equal(r1, r2)
    assert all((a["mask_distractors"] == b["mask_distractors"]).all() for a, b in zip(i1, i2))
    assert not np.array_equal(f1, f3)


def test_masks_are_disjoint_and_match_the_drawn_sprites():
    env = SpritesEnv(task="reach", num_distractors=4)
    actions = np.random.default_rng(1).uniform(-1, 1, (40, 2))
    frames, infos, _ = _rollout(env, actions, seed=5)
    palette = {tuple(c) for c in _PALETTE}
    for frame, info in zip(frames, infos):
        agent, distractors, target = info["mask_agent"], info["mask_distractors"], info["mask_target"]
        assert not (agent & distractors).any() and not (target & (agent | distractors)).any()
        assert agent.sum() == (2 * env.radius + 1) ** 2  # the agent is on top: always fully visible
        assert {tuple(p) for p in frame[agent]} <= {(255, 255, 255), (0, 0, 0)}
        assert {tuple(p) for p in frame[distractors]} <= palette
        assert {tuple(p) for p in frame[target]} <= {(30, 200, 60)}
        ids = info["distractor_ids"]
        np.testing.assert_array_equal(ids > 0, distractors)
        for i in range(1, 5):  # each id marks exactly the pixels drawn in that distractor's colour
            assert (frame[ids == i] == _PALETTE[i - 1]).all()
        # Outside every mask the frame is exactly the episode's static background.
        unmasked = ~(agent | distractors | target)
        np.testing.assert_array_equal(frame[unmasked], env._background[unmasked])


def test_agent_follows_the_action():
    env = SpritesEnv(num_distractors=0, agent_speed=0.05)
    _, info = env.reset(seed=0)
    # Start from the centre so no border clamps the move.
    env._agent[:] = 32.0
    *_, info = env.step(np.zeros(2))
    start = _centroid(info["mask_agent"])
    *_, info = env.step(np.array([1.0, 0.0]))  # +x: right
    np.testing.assert_allclose(_centroid(info["mask_agent"]) - start, [0.0, 3.0], atol=1.0)
    *_, info = env.step(np.array([0.0, -1.0]))  # -y: up
    np.testing.assert_allclose(_centroid(info["mask_agent"]) - start, [-3.0, 3.0], atol=1.0)
    *_, info2 = env.step(np.zeros(2))
    np.testing.assert_array_equal(info2["mask_agent"], info["mask_agent"])


def test_distractors_move_independently_of_the_action():
    env_a, env_b = SpritesEnv(num_distractors=5), SpritesEnv(num_distractors=5)
    _, ia = env_a.reset(seed=7)
    _, ib = env_b.reset(seed=7)
    moved = False
    for _ in range(20):
        prev = ia["mask_distractors"]
        _, _, _, _, ia = env_a.step(np.array([1.0, 1.0]))
        _, _, _, _, ib = env_b.step(np.array([-1.0, -0.5]))
        hidden = ia["mask_agent"] | ib["mask_agent"]
        np.testing.assert_array_equal(ia["mask_distractors"] & ~hidden, ib["mask_distractors"] & ~hidden)
        moved |= not np.array_equal(prev, ia["mask_distractors"])
    assert moved


def test_distractors_bounce_and_stay_inside_the_frame():
    env = SpritesEnv(num_distractors=1, distractor_speed=0.1, agent_speed=0.0)
    _, info = env.reset(seed=2)
    centres = []
    for _ in range(100):
        _, _, _, _, info = env.step(np.zeros(2))
        visible = info["mask_distractors"] | info["mask_agent"]
        assert visible.any()
        centres.append(env._distractors[0].copy())
    steps = np.diff(np.array(centres), axis=0)
    # Each coordinate's velocity changes sign at a wall, keeping its magnitude.
    assert (np.sign(steps[:, 0]) > 0).any() and (np.sign(steps[:, 0]) < 0).any()
    assert (np.sign(steps[:, 1]) > 0).any() and (np.sign(steps[:, 1]) < 0).any()


def test_task_none_gives_zero_reward_and_truncates_at_max_steps():
    env = SpritesEnv(max_steps=5)
    env.reset(seed=0)
    for t in range(5):
        _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        assert reward == 0.0 and not terminated
        assert truncated == (t == 4)


def test_sparse_reach_rewards_reaching_the_target_and_penalises_contact():
    env = SpritesEnv(task="reach", num_distractors=0, max_steps=300, progress_reward=0.0)
    _, info = env.reset(seed=0)
    total = 0.0
    for _ in range(300):
        delta = _centroid(info["mask_target"]) - _centroid(info["mask_agent"])  # (dy, dx)
        action = np.clip(np.array([delta[1], delta[0]]) / 3.0, -1, 1)
        _, reward, _, _, info = env.step(action)
        assert reward in (0.0, 1.0) and (reward == 1.0) == info["reached"]
        total += reward
    assert total >= 5  # a greedy reacher collects several respawned targets

    env = SpritesEnv(task="reach", num_distractors=6, contact_penalty=0.5, progress_reward=0.0)
    env.reset(seed=1)
    touched = 0
    for _ in range(200):
        _, reward, _, _, info = env.step(env.action_space.sample())
        if info["touching"] and not info["reached"]:
            assert reward == -0.5
            touched += 1
        if not info["touching"] and not info["reached"]:
            assert reward == 0.0
    assert touched > 0


def test_progress_reward_is_the_distance_gained_towards_the_target_it_was_heading_for():
    env = SpritesEnv(task="reach", num_distractors=0, progress_reward=10.0, reach_reward=1.0)
    env.reset(seed=3)
    reaches, total, steps = 0, 0.0, 0
    while reaches < 3:
        before = np.sqrt(((env._agent - env._target) ** 2).sum())
        target = env._target.copy()
        delta = target - env._agent
        _, reward, _, _, info = env.step(np.clip(np.array([delta[1], delta[0]]) / 3.2, -1, 1))
        after = np.sqrt(((env._agent - target) ** 2).sum())  # to the same target, even if it respawned
        expected = 10.0 * (before - after) / 64 + float(info["reached"])
        assert reward == pytest.approx(expected, abs=1e-9)
        # Heading straight at the target never loses shaping reward, a respawn included.
        assert reward > 0
        reaches += info["reached"]
        total += reward
        steps += 1
        assert steps < 200


def test_progress_reward_of_a_parked_agent_is_zero():
    env = SpritesEnv(task="reach", num_distractors=0, progress_reward=10.0)
    env.reset(seed=0)
    for _ in range(40):  # into a corner, then pushing against it
        env.step(np.array([-1.0, -1.0]))
    rewards = [env.step(np.array([-1.0, -1.0]))[1] for _ in range(10)]
    assert rewards == [0.0] * 10


@pytest.mark.parametrize("style, filled", [("disc", True), ("ring", False)])
def test_target_style_draws_a_filled_disc_or_a_ring(style, filled):
    env = SpritesEnv(task="reach", num_distractors=0, target_style=style)
    _, info = env.reset(seed=0)
    y, x = np.rint(env._target).astype(int)
    assert info["mask_target"].any()
    assert bool(info["mask_target"][y, x]) == filled  # the centre pixel


def test_bad_arguments_raise_clear_errors():
    with pytest.raises(ValueError, match="target_style"):
        SpritesEnv(target_style="square")
    with pytest.raises(ValueError, match="progress_reward"):
        SpritesEnv(progress_reward=float("nan"))
    with pytest.raises(ValueError, match="none.*reach"):
        SpritesEnv(task="dance")
    with pytest.raises(ValueError, match="image_size"):
        SpritesEnv(image_size=8)
    env = SpritesEnv()
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros(2))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2,\).*\(3,\)"):
        env.step(np.zeros(3))


def test_other_image_sizes_render_consistently():
    env = SpritesEnv(image_size=32, task="reach")
    obs, info = env.reset(seed=0)
    assert obs.shape == (32, 32, 3) and info["mask_agent"].shape == (32, 32)


def _background(env: SpritesEnv, seed: int) -> np.ndarray:
    obs, info = env.reset(seed=seed)
    visible = ~(info["mask_agent"] | info["mask_distractors"] | info["mask_target"])
    return obs, visible


def test_background_pool_repeats_a_fixed_set_of_backgrounds():
    env = SpritesEnv(num_backgrounds=2, background_seed=3)
    pool = env._background_pool
    assert pool.shape == (2, 64, 64, 3) and not np.array_equal(pool[0], pool[1])
    used = set()
    for seed in range(12):
        obs, visible = _background(env, seed)
        matches = [i for i in range(2) if np.array_equal(obs[visible], pool[i][visible])]
        assert len(matches) == 1, "every episode shows exactly one background of the pool"
        used.add(matches[0])
    assert used == {0, 1}
    # The same background seed gives the same pool in another env; another seed a different one.
    assert np.array_equal(SpritesEnv(num_backgrounds=2, background_seed=3)._background_pool, pool)
    assert not np.array_equal(SpritesEnv(num_backgrounds=2, background_seed=4)._background_pool, pool)


def test_default_draws_a_new_background_per_episode():
    env = SpritesEnv()
    first, visible_a = _background(env, 0)
    second, visible_b = _background(env, 1)
    both = visible_a & visible_b
    assert np.abs(first[both].astype(int) - second[both].astype(int)).mean() > 5


def test_bad_background_pool_size_is_rejected():
    with pytest.raises(ValueError, match="num_backgrounds"):
        SpritesEnv(num_backgrounds=0)


@pytest.mark.parametrize("sprite_size, radius", [(0.06, 4), (0.1, 6)])
def test_sprite_size_sets_the_drawn_sprites_radius(sprite_size, radius):
    env = SpritesEnv(sprite_size=sprite_size, num_distractors=1)
    assert env.radius == radius
    for seed in range(4):
        _, info = env.reset(seed=seed)
        assert info["mask_agent"].sum() == (2 * radius + 1) ** 2
        if not info["mask_distractors"].any():  # the disc hidden under the agent
            continue
        ys, xs = np.nonzero(info["distractor_ids"] == 1)
        assert ys.max() - ys.min() <= 2 * radius and xs.max() - xs.min() <= 2 * radius
    with pytest.raises(ValueError, match="sprite_size"):
        SpritesEnv(sprite_size=0.0)
    with pytest.raises(ValueError, match="sprite_size"):
        SpritesEnv(sprite_size=0.3)


def test_distractor_colours_choose_each_disc_colour_in_drawing_order():
    env = SpritesEnv(num_distractors=2, distractor_colours=("cyan", "yellow"))
    frames, infos, _ = _rollout(env, np.zeros((5, 2)), seed=3)
    for frame, info in zip(frames, infos):
        ids = info["distractor_ids"]
        assert (frame[ids == 1] == DISTRACTOR_COLOURS["cyan"]).all()
        assert (frame[ids == 2] == DISTRACTOR_COLOURS["yellow"]).all()
    assert SpritesEnv(num_distractors=2).distractor_colours == ("red", "blue")
    with pytest.raises(ValueError, match="one colour of"):
        SpritesEnv(num_distractors=2, distractor_colours=("cyan", "teal"))
    with pytest.raises(ValueError, match="per distractor"):
        SpritesEnv(num_distractors=3, distractor_colours=("cyan", "yellow"))


def test_agent_colour_fills_the_agent_inside_its_black_border():
    frames, infos, _ = _rollout(SpritesEnv(agent_colour="magenta"), np.zeros((3, 2)), seed=5)
    white_frames, _, _ = _rollout(SpritesEnv(), np.zeros((3, 2)), seed=5)
    for frame, white, info in zip(frames, white_frames, infos):
        ys, xs = np.nonzero(info["mask_agent"])
        inner = frame[ys.min() + 1 : ys.max(), xs.min() + 1 : xs.max()]
        assert (inner == DISTRACTOR_COLOURS["magenta"]).all()
        assert (frame[ys.min(), xs.min() : xs.max() + 1] == 0).all()  # the border
        outside = ~info["mask_agent"]
        assert (frame[outside] == white[outside]).all()  # the rest of the scene is the same
    with pytest.raises(ValueError, match="agent_colour"):
        SpritesEnv(agent_colour="black")
