"""Where a world model puts the agent (Iso-Dream's assignment): the verdict on the decomposition scores, and the one
line a run prints at its end when the agent is not in the controllable branch."""

import math
from pathlib import Path

import pytest

from isodream_rl.cli import _summary
from isodream_rl.evaluation import ISOLATION_AIMS, isolation_verdict
from isodream_rl.trainers.run_lifecycle import RunResult

NAN = math.nan


def scores(control: float, free: float, static: float, distractors: float = NAN, mse_distractors=NAN):
    return {
        "iou_control_vs_agent": control,
        "iou_free_vs_agent": free,
        "iou_static_vs_agent": static,
        "iou_free_vs_distractors": distractors,
        "mse_distractors": mse_distractors,
    }


def test_the_agent_in_the_controllable_branch_isolates():
    verdict = isolation_verdict(scores(0.94, 0.0, 0.0, distractors=0.0))
    assert verdict == {
        "agent_branch": "control",
        "isolates_agent": True,
        "isolates_distractors": None,  # no distractor pixels: nothing to judge
        "message": None,
    }


@pytest.mark.parametrize(
    "ious, branch, words",
    [
        ((0.03, 0.71, 0.0), "free", "in the action-free branch"),
        ((0.05, 0.02, 0.55), "static", "in the static branch"),
        ((0.6, 0.1, 0.0), "control", "mostly in the controllable branch, short of the aims"),
        ((0.8, 0.3, 0.0), "control", "mostly in the controllable branch, short of the aims"),
    ],
)
def test_an_agent_outside_the_aims_is_named_in_one_line(ious, branch, words):
    verdict = isolation_verdict(scores(*ious))
    assert verdict["agent_branch"] == branch and verdict["isolates_agent"] is False
    assert words in verdict["message"] and "\n" not in verdict["message"]
    assert f">= {ISOLATION_AIMS['iou_control_vs_agent']}" in verdict["message"]


def test_distractors_are_judged_where_the_scene_has_them():
    assert isolation_verdict(scores(0.9, 0.0, 0.0, 0.6, mse_distractors=0.01))["isolates_distractors"] is True
    assert (
        isolation_verdict(scores(0.9, 0.0, 0.0, 0.3, mse_distractors=0.01))["isolates_distractors"] is False
    )


def test_no_agent_in_the_windows_is_no_verdict():
    verdict = isolation_verdict(scores(NAN, NAN, NAN))
    assert (
        verdict["agent_branch"] is None and verdict["isolates_agent"] is None and verdict["message"] is None
    )


@pytest.mark.parametrize("isolated", [True, False])
def test_a_run_says_at_its_end_where_the_agent_is_when_not_isolated(isolated):
    verdict = isolation_verdict(scores(0.95, 0.0, 0.0) if isolated else scores(0.03, 0.71, 0.0))
    result = RunResult(
        run_dir=Path("run"),
        checkpoint=None,
        logs=Path("run/logs"),
        pictures=Path("run/pictures"),
        env_steps=100,
        updates=10,
        summary={"eval_return": 1.0, "isolation": verdict},
    )
    warnings = [line for line in _summary(result).splitlines() if line.strip().startswith("warning:")]
    assert warnings == ([] if isolated else [f"  warning: {verdict['message']}"])
