"""Reference policies (random, best constant action, scripted) and the normalised score."""

import numpy as np
import pytest

from isodream_rl.envs import make_env
from isodream_rl.envs.builder import make_gym_env
from isodream_rl.envs.reference import (
    CONSTANT_ACTIONS,
    normalised_score,
    reference_returns,
    run_reference_episodes,
    scripted_action,
)
from isodream_rl.envs.task_metrics import episode_metrics


def test_constant_candidates_are_zero_and_the_eight_directions():
    assert len(CONSTANT_ACTIONS) == 9 and len(set(CONSTANT_ACTIONS)) == 9
    assert (0.0, 0.0) in CONSTANT_ACTIONS and all(max(map(abs, a)) in (0.0, 1.0) for a in CONSTANT_ACTIONS)


def test_sprites_references_rank_scripted_above_constant_above_random():
    refs = reference_returns("sprites", episodes=3, seed=0, task="reach", num_distractors=3, max_steps=100)
    assert refs["scripted"]["return"] > refs["constant"]["return"] > refs["random"]["return"]
    assert refs["scripted"]["reaches"] >= 8  # steering at the target reaches it every few steps
    assert refs["random"]["reaches"] < 1
    assert len(refs["constant"]["action"]) == 2 and len(refs["random"]["returns"]) == 3


def test_constant_reference_is_the_best_candidate():
    candidates = [(1.0, 0.0), (-1.0, -1.0)]
    refs = reference_returns(
        "sprites", episodes=2, seed=1, constant_actions=candidates, task="reach", max_steps=50
    )
    env = make_gym_env("sprites", task="reach", max_steps=50)
    means = []
    for c in candidates:
        action = np.array(c, np.float32)
        returns, _ = run_reference_episodes("sprites", env, lambda _e, _r: action, episodes=2, seed=1)  # noqa: B023
        means.append(np.mean(returns))
    assert refs["constant"]["return"] == pytest.approx(max(means))
    assert refs["constant"]["action"] == list(candidates[int(np.argmax(means))])


def test_references_use_the_same_episodes_for_every_policy():
    env = make_gym_env("sprites", task="reach", max_steps=10)
    first = run_reference_episodes("sprites", env, lambda e, _r: scripted_action(e), episodes=2, seed=5)
    again = run_reference_episodes("sprites", env, lambda e, _r: scripted_action(e), episodes=2, seed=5)
    assert first == again


def test_scripted_action_needs_a_target():
    env = make_gym_env("sprites", task="none")
    env.reset(seed=0)
    with pytest.raises(TypeError, match="reach"):
        scripted_action(env)


def test_normalised_score_scale_and_degenerate_references():
    assert normalised_score(-5.0, constant=-5.0, scripted=15.0) == 0.0
    assert normalised_score(15.0, constant=-5.0, scripted=15.0) == 1.0
    assert normalised_score(5.0, constant=-5.0, scripted=15.0) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="must exceed"):
        normalised_score(0.0, constant=1.0, scripted=1.0)


def test_torchrl_env_exports_the_info_keys_the_success_counts_read():
    env = make_env("sprites", seed=0, task="reach", num_distractors=6, max_steps=60)
    rollout = env.rollout(60)
    steps = [{k: rollout[i]["next", k].item() for k in ("reached", "touching")} for i in range(60)]
    metrics = episode_metrics("sprites", steps)
    assert metrics["contacts"] == float(rollout["next", "touching"].sum()) and metrics["contacts"] > 0
    assert metrics["reaches"] == float(rollout["next", "reached"].sum())


@pytest.mark.parametrize("view", ["top_down"])
def test_highway_scripted_driver_keeps_its_lane_and_speed(view):
    env = make_gym_env("highway", view=view, vehicles_count=1, max_ticks=240)
    returns, metrics = run_reference_episodes(
        "highway", env, lambda e, _r: scripted_action(e), episodes=1, seed=0
    )
    ego = env.unwrapped.ego
    _, lateral = ego.lane.local_coordinates(ego.position)
    assert abs(lateral) < 0.5 and abs(ego.speed - 30.0) < 2.0
    assert metrics[0]["collisions"] == 0 and metrics[0]["distance"] > 60 * 4 * 0.05 * 25
