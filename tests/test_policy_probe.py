"""``bench/policy_probe.py`` on a tiny sprites reach run: the imagined against the real reaches and the slow
value against the true potential come out with values in range, for the DreamerV2-style Iso-Dream components and
for the DreamerV3-learner algorithms (``algo=isodream``, ``torchrl_dreamer_v3``)."""

import json
import math

import numpy as np
import pytest

from isodream_rl.trainers.run import train
from tests.conftest import load_bench, tiny_run_config

probe = load_bench("policy_probe")

DREAMERV2 = {
    "algo__free_branch": False,
    "algo__static_branch": False,
    "algo__inverse_dynamics": False,
    "algo__reward_uses_free": False,
    "algo__policy_input": "controllable",
}


def test_linear_fit_recovers_a_line():
    phi = np.array([-3.0, -2.0, -1.0, 0.0])
    fit = probe.linear_fit(phi, 0.5 - phi)
    assert fit["slope"] == pytest.approx(-1.0)
    assert fit["intercept"] == pytest.approx(0.5)
    assert fit["r2"] == pytest.approx(1.0)
    assert fit["correlation"] == pytest.approx(-1.0)
    assert fit["points"] == 4
    assert fit["phi_mean"] == pytest.approx(-1.5) and fit["v_slow_mean"] == pytest.approx(2.0)
    assert probe.linear_fit(np.zeros(3), np.ones(3))["slope"] is None  # one potential: no fit


def test_reach_rates_count_steps_above_the_threshold_against_real_reaches():
    dreamt = np.array([0.9, 0.86, 0.5, 0.71, 1.2, -0.3])  # 0.71: a full-speed diagonal step, not a reach
    reached = np.array([True, False, True, False, False, False])
    rates = probe.reach_rates(dreamt, reached)
    assert rates["imagined_reaches"] == 3 and rates["imagined_reach_rate"] == pytest.approx(0.5)
    assert rates["real_reaches"] == 2 and rates["real_reach_rate"] == pytest.approx(1 / 3)
    assert rates["reach_recall"] == pytest.approx(0.5)  # the first real reach was imagined, the second not
    assert probe.reach_rates(dreamt, np.zeros(6, dtype=bool))["reach_recall"] is None


@pytest.mark.parametrize("algo", ["isodream_v2", "dreamerv2"])
def test_probe_reports_reaches_and_value_against_potential(tmp_path, algo):
    changes = DREAMERV2 if algo == "dreamerv2" else {}
    cfg = tiny_run_config(tmp_path / "run", train__total_steps=30, **changes)
    cfg.env.kwargs = {"task": "reach", "num_distractors": 0}
    cfg.logging.eval_every, cfg.logging.final_eval_episodes, cfg.logging.progress_bar = 0, 0, False
    result = train(cfg)
    assert result.updates >= 1

    out = tmp_path / "probe.json"
    report = probe.main(
        [str(tmp_path / "run"), "--json", str(out), "--starts", "2", "--value-starts", "4"]
        + ["--episodes", "1", "--steps", "8"]
    )
    assert json.loads(out.read_text())["imagination_check"] == report["imagination_check"]
    check = report["imagination_check"]
    # The earlier outputs are still there.
    for key in ("starts", "samples", "imagined_return", "real_return", "reward_correlation"):
        assert key in check
    assert "imagined_reward_mean" in report and "reward_correlation" in report

    steps = check["starts"] * check["samples"] * cfg.algo.horizon
    assert check["reach_threshold"] == probe.REACH_THRESHOLD == 0.85
    for rate, count in (("imagined_reach_rate", "imagined_reaches"), ("real_reach_rate", "real_reaches")):
        assert 0.0 <= check[rate] <= 1.0
        assert check[count] == round(check[rate] * steps)
    if check["real_reaches"]:
        assert 0.0 <= check["reach_recall"] <= 1.0
    else:
        assert check["reach_recall"] is None

    fit = check["value_vs_potential"]
    assert set(fit) == {"slope", "intercept", "r2", "correlation", "points", "v_slow_mean", "phi_mean"}
    assert fit["points"] == 2 + 4 == check["starts"] + check["value_starts"]
    assert all(math.isfinite(fit[key]) for key in ("slope", "intercept", "v_slow_mean", "phi_mean"))
    assert fit["r2"] <= 1.0 + 1e-9 and -1.0 <= fit["correlation"] <= 1.0
    # phi = -progress_reward * d / S with d at most the frame's diagonal.
    assert -10.0 * math.sqrt(2) <= fit["phi_mean"] < 0.0

    grads = check["gradient_check"]
    assert set(grads) == {
        "cosine_reward",
        "cosine_lambda_return",
        "cosine_value",
        "norm_reward",
        "norm_lambda_return",
    }
    for key in ("cosine_reward", "cosine_lambda_return", "cosine_value"):
        assert -1.0 - 1e-6 <= grads[key] <= 1.0 + 1e-6
    assert grads["norm_reward"] >= 0.0 and math.isfinite(grads["norm_lambda_return"])


def in_range_or_nan(x, low=-1.0, high=1.0) -> bool:
    return x is None or math.isnan(x) or low - 1e-6 <= x <= high + 1e-6


def test_the_learner_follows_the_algo():
    for algo in ("isodream_v2", "dreamerv2", "isodream_paper"):
        assert type(probe.probe_learner(None, algo)) is probe.DreamerV2Learner
    for algo in ("isodream", "isodream_no_inverse", "isodream_no_attention", "isodream_no_static"):
        assert type(probe.probe_learner(None, algo)) is probe.DreamerV3Learner
    assert type(probe.probe_learner(None, "torchrl_dreamer_v3")) is probe.DreamerV3Learner


@pytest.mark.parametrize("algo", ["isodream", "torchrl_dreamer_v3"])
def test_probe_reports_imagined_and_real_reaches_of_a_dreamer_v3_learner(tmp_path, algo):
    from tests.test_isodream import isodream_run_config
    from tests.test_torchrl_dreamer import tiny_config

    steps = {"prefill_steps": 10, "frames_per_batch": 10, "total_steps": 30}
    run = tmp_path / "run"
    cfg = isodream_run_config(run, **steps) if algo == "isodream" else tiny_config(run, algo, **steps)
    cfg.logging.final_eval_episodes = 0
    assert train(cfg).updates >= 1

    out = tmp_path / "probe.json"
    report = probe.main(
        [
            str(run),
            "--json",
            str(out),
            "--starts",
            "2",
            "--value-starts",
            "1",
            "--episodes",
            "1",
            "--steps",
            "8",
        ]
    )
    written = json.loads(out.read_text())
    assert written["imagination_check"].keys() == report["imagination_check"].keys()
    assert report["algo"] == algo and report["learner"] == "dreamer_v3"
    for key in ("true_reward_mean", "predicted_reward_mean", "imagined_reward_mean", "lambda_target_mean"):
        assert math.isfinite(report[key]), key
    assert in_range_or_nan(report["reward_correlation"])
    assert len(report["action_mean"]) == len(report["action_std_within_episode"]) == 2

    check = report["imagination_check"]
    assert check["starts"] == 2 and check["samples"] == 32
    steps = check["starts"] * check["samples"] * cfg.algo.horizon
    for rate, count in (("imagined_reach_rate", "imagined_reaches"), ("real_reach_rate", "real_reaches")):
        assert 0.0 <= check[rate] <= 1.0
        assert check[count] == round(check[rate] * steps)
    if check["real_reaches"]:
        assert 0.0 <= check["reach_recall"] <= 1.0
    else:
        assert check["reach_recall"] is None
    assert math.isfinite(check["imagined_return"])
    # A real step earns at least -0.71 (progress at full speed away) and at most 1.71 (a reach).
    assert -0.72 * cfg.algo.horizon <= check["real_return"] <= 1.72 * cfg.algo.horizon
    assert in_range_or_nan(check["reward_correlation"])

    fit = check["value_vs_potential"]
    assert fit["points"] == check["starts"] + check["value_starts"] == 3
    assert math.isfinite(fit["v_slow_mean"]) and -10.0 * math.sqrt(2) <= fit["phi_mean"] < 0.0
    assert in_range_or_nan(fit["correlation"])
    assert check["gradient_check"] is None and "REINFORCE" in check["gradient_check_skipped"]
    assert "value_model" in check


def test_the_direction_to_the_target_is_in_action_coordinates():
    """``gradient_check`` compares gradients with ``(target - agent)[::-1]``: the env stores (row, col), the
    action moves (x, y), so a step along that direction must bring the agent closer."""
    from isodream_rl.envs.sprites import SpritesEnv

    env = SpritesEnv(task="reach", num_distractors=0, sprite_size=0.1)
    for seed in range(10):
        env.reset(seed=seed)
        direction = (env._target - env._agent)[::-1].copy()
        before = np.linalg.norm(env._target - env._agent)
        env.step((direction / np.abs(direction).max()).astype(np.float32))
        assert np.linalg.norm(env._target - env._agent) < before
