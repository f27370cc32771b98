"""``bench/time_to_score.py`` on a crafted learning-bench JSON: minutes to a normalised score per seed, a seed that
never gets there sorted last in the median."""

import json

import pytest

from tests.conftest import load_bench


@pytest.fixture(scope="module")
def bench():
    return load_bench("time_to_score")


def curve(returns, minutes):
    return {
        "env_steps": [1000 * (i + 1) for i in range(len(returns))],
        "eval_return": returns,
        "wall_s": [60.0 * m for m in minutes],
        "finished": True,
    }


def learning_json(tmp_path):
    # constant 10, scripted 110: normalised 0.5 is a return of 60
    results = {
        "constant_return": 10.0,
        "scripted_return": 110.0,
        "cpu": "crafted",
        "algos": {
            "fast": {
                "seeds": [0, 1, 2],
                "normalised_per_seed": [0.9, 0.6, 0.3],
                "wall_s_per_seed": [600.0, 600.0, 1200.0],
                "curves": {
                    "0": curve([20.0, 60.0, 100.0], [2, 4, 10]),  # 0.5 exactly at 4 minutes
                    "1": curve([20.0, 59.0, 70.0], [3, 6, 10]),  # 0.49 is not 0.5: 10 minutes
                    "2": curve([20.0, 30.0, 40.0], [5, 10, 20]),  # never
                    "3": curve([90.0], [1]) | {"finished": False},  # not finished: not counted
                },
            },
            "slow": {
                "seeds": [0, 1],
                "normalised_per_seed": [0.55, 0.2],
                "wall_s_per_seed": [300.0, 300.0],
                "curves": {"0": curve([65.0], [5]), "1": curve([12.0], [5])},
            },
        },
    }
    path = tmp_path / "learning.json"
    path.write_text(json.dumps(results))
    return path


def test_minutes_to_the_score_and_their_median_count_a_seed_that_never_scores_as_the_slowest(bench, tmp_path):
    out_path = tmp_path / "tts.json"
    out = bench.main([str(learning_json(tmp_path)), "--json", str(out_path)])
    assert json.loads(out_path.read_text()) == out
    fast, slow = out["algos"]["fast"], out["algos"]["slow"]
    assert fast["minutes_to_0_5_per_seed"] == [4.0, 10.0, None]
    assert fast["median_minutes_to_0_5"] == 10.0
    assert fast["final_score_per_minute_per_seed"] == pytest.approx([0.09, 0.06, 0.015])
    assert fast["median_final_score_per_minute"] == pytest.approx(0.06)
    # two seeds, one never: the median lands next to it
    assert slow["minutes_to_0_5_per_seed"] == [5.0, None]
    assert slow["median_minutes_to_0_5"] is None
    assert out["source_cpu"] == "crafted" and out["score"] == 0.5 and "cpu" in out


def test_a_file_that_is_not_a_learning_bench_json_is_refused(bench, tmp_path):
    path = tmp_path / "other.json"
    path.write_text(json.dumps({"algos": {}}))
    with pytest.raises(SystemExit):
        bench.main([str(path), "--json", str(tmp_path / "out.json")])
