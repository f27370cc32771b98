"""Strict JSON for results (``isodream_rl.run_utils.json_io``): absent scores (``nan``, ``inf``) written as ``null``,
read back as absent, by the library (``isolation_verdict``) and the benches' tables, as older files' ``NaN`` is."""

import json
import math

import numpy as np
import pytest
import torch

from isodream_rl.evaluation import isolation_verdict
from isodream_rl.run_utils.json_io import dumps_json, is_absent, nan_if_none, strict_json, write_json
from isodream_rl.trainers.run_lifecycle import write_summary
from tests.conftest import load_bench


def strict_loads(text: str):
    """``json.loads`` that refuses the bare ``NaN``, ``Infinity`` and ``-Infinity`` Python writes by default."""

    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


NAN, INF = math.nan, math.inf
SCORES = {
    "reco_mse": 0.018,
    "mse_distractors": NAN,
    "curve": [0.5, NAN, INF, (-INF, 1.0)],
    "nested": {"deep": [{"x": -INF}], "n": 3, "flag": True, "name": "sprites", "none": None},
    "numpy": np.float32("nan"),
    "numpy_finite": np.float32(0.25),
    "tensor": torch.tensor(float("inf")),
    "tensor_finite": torch.tensor(2),
}


def test_strict_json_maps_every_non_finite_float_to_none_recursively():
    out = strict_json(SCORES)
    assert out == {
        "reco_mse": 0.018,
        "mse_distractors": None,
        "curve": [0.5, None, None, [None, 1.0]],
        "nested": {"deep": [{"x": None}], "n": 3, "flag": True, "name": "sprites", "none": None},
        "numpy": None,
        "numpy_finite": 0.25,
        "tensor": None,
        "tensor_finite": 2,
    }
    assert type(out["numpy_finite"]) is float and type(out["tensor_finite"]) is int
    assert math.isnan(SCORES["mse_distractors"]) and math.isinf(
        SCORES["curve"][2]
    )  # the input is left as it was


@pytest.mark.parametrize("atomic", [False, True])
def test_write_json_is_strict_json_with_the_indent_asked_for(tmp_path, atomic):
    path = write_json(tmp_path / "scores.json", SCORES, indent=1, atomic=atomic)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text and text.endswith("}\n")
    assert text.startswith('{\n "reco_mse": 0.018,\n "mse_distractors": null,')
    assert strict_loads(text) == strict_json(SCORES)
    assert [p.name for p in tmp_path.iterdir()] == ["scores.json"]  # no temporary file left


def test_dumps_json_passes_json_options_and_refuses_a_non_finite_default():
    assert dumps_json({"b": NAN, "a": {1, 2}}, sort_keys=True, default=sorted) == '{"a": [1, 2], "b": null}'
    with pytest.raises(
        ValueError
    ):  # what ``default`` returns is not made strict: refused, never written as NaN
        dumps_json({"a": object()}, default=lambda _: NAN)


def test_summary_json_is_strict_and_written_atomically(tmp_path):
    path = write_summary(tmp_path, {"eval_return": 12.5, "decomposition": {"mse_distractors": NAN}})
    assert path == tmp_path / "summary.json"
    assert strict_loads(path.read_text()) == {"eval_return": 12.5, "decomposition": {"mse_distractors": None}}
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]


def test_a_score_read_back_as_null_or_nan_is_absent():
    assert math.isnan(nan_if_none(None)) and math.isnan(nan_if_none(NAN)) and nan_if_none(1) == 1.0
    assert is_absent(None) and is_absent(NAN) and is_absent(np.float32("nan"))
    assert not is_absent(0.0) and not is_absent(0) and not is_absent(INF)


def _verdict_scores(**extra):
    return {"iou_control_vs_agent": 0.9, "iou_free_vs_agent": 0.05, "iou_static_vs_agent": 0.0, **extra}


def test_isolation_verdict_reads_a_null_score_as_a_missing_one():
    missing = isolation_verdict(_verdict_scores())
    as_nan = isolation_verdict(_verdict_scores(mse_distractors=NAN, iou_free_vs_distractors=NAN))
    as_null = isolation_verdict(_verdict_scores(mse_distractors=None, iou_free_vs_distractors=None))
    # a summary.json written by the library, read back: mse_distractors is null
    summary = strict_loads(dumps_json(_verdict_scores(mse_distractors=NAN, iou_free_vs_distractors=0.9)))
    assert summary["mse_distractors"] is None
    read_back = isolation_verdict(summary)
    assert missing == as_nan == as_null == read_back
    assert read_back["isolates_distractors"] is None and read_back["isolates_agent"] is True
    no_agent = isolation_verdict({f"iou_{b}_vs_agent": None for b in ("control", "free", "static")})
    assert no_agent["agent_branch"] is None and no_agent["isolates_agent"] is None


def test_the_bench_tables_skip_a_null_score_as_they_do_an_older_nan():
    learning, decomposition = load_bench("learning"), load_bench("decomposition")
    for fmt in (learning._fmt, decomposition._fmt):
        assert fmt([None, NAN]) == "n/a"
        assert fmt([0.5, None]) == fmt([0.5, NAN]) == fmt([0.5])
    entry = {
        "decomposition_per_seed": [
            {"mse_distractors": None, "iou_free_vs_distractors": 0.0},  # written now: null
            {"mse_distractors": NAN, "iou_free_vs_distractors": 0.0},  # written before: NaN
            {"mse_distractors": 0.1, "iou_free_vs_distractors": 0.4},
            None,  # a run without a decomposition
        ]
    }
    assert learning._final_scores(entry, "iou_free_vs_distractors") == [None, None, 0.4, None]


def test_time_to_score_reads_a_null_final_score_as_nan():
    bench = load_bench("time_to_score")
    curve = {"env_steps": [1000], "eval_return": [60.0], "wall_s": [120.0], "finished": True}
    results = {
        "constant_return": 10.0,
        "scripted_return": 110.0,
        "algos": {
            "a": {
                "seeds": [0],
                "normalised_per_seed": [None],
                "wall_s_per_seed": [120.0],
                "curves": {"0": curve},
            }
        },
    }
    out = bench.time_to_score(results)["a"]
    assert out["minutes_to_0_5_per_seed"] == [2.0]
    assert math.isnan(out["final_score_per_minute_per_seed"][0])
    assert strict_loads(dumps_json(out))["final_score_per_minute_per_seed"] == [None]
