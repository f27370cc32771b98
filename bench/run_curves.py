"""The logged curves of runs, finished or not: each run folder's ``eval/decomposition/<score>`` CSV logs (a
world-model run's held-out scores at each evaluation, or an RL run's) and its updates per second, as one JSON.

For a run still going, or stopped before its ``summary.json``: what it has written so far, with the command that
trained it (``.hydra/overrides.yaml``).

    python bench/run_curves.py ~/isodream-runs/dec_final/dmc_walker_walk-isodream_v2-s0 --json /tmp/curves.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance, read_scalar, training_command  # noqa: E402

from isodream_rl.run_utils.json_io import write_json  # noqa: E402

#: the scores each curve holds (``eval/decomposition/<score>``), the held-out ones the aims read
SCORES = (
    "iou_control_vs_agent",
    "iou_free_vs_distractors",
    "iou_free_vs_agent",
    "iou_static_vs_background",
    "reco_mse",
)


def run_curves(run_dir: Path) -> dict:
    """``{"command", "finished", "curves": {score: [[update, value], ...]}, "updates_per_s": [...]}`` of one run."""
    curves = {
        score: [
            [step, round(value, 4)] for step, value in read_scalar(run_dir, f"eval/decomposition/{score}")
        ]
        for score in SCORES
    }
    return {
        "command": training_command(run_dir),
        "finished": (run_dir / "summary.json").exists(),
        "curves": curves,
        "updates_per_s": [[step, round(value, 3)] for step, value in read_scalar(run_dir, "updates_per_s")],
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders")
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    out = {
        "runs": {run.name: run_curves(run) for run in args.runs},
        **provenance("run_curves.py", argv, parallel=1),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, out, indent=1)
    return out


if __name__ == "__main__":
    main()
