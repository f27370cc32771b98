"""One finished ``isodream-train`` run's ``summary.json``, with where it came from, as a committable result.

Every ``isodream-train`` run ends by writing ``<run_dir>/summary.json`` (its final evaluation next to the reference
policies, the decomposition scores where the env renders the ground truth, ``isolation``). This script wraps it
with the training command (``common.training_command``: ``isodream-train`` and the overrides Hydra recorded in
``<run_dir>/.hydra/overrides.yaml``), the commit the run was trained at (``--train-commit``: a run folder does not
record it), the CPU and this command::

    {"command": "isodream-train size=quickstart ...", "train_commit": ..., "note": ..., "cpu": ...,
     "summary": {<summary.json as written>}, "collected_by": {"commit": ..., "command": ...}}

    python bench/run_summary.py runs/sprites-isodream-quickstart --train-commit <sha> \\
        --json docs/results/quickstart_summary.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_name, provenance, training_command  # noqa: E402

from isodream_rl.run_utils.json_io import write_json  # noqa: E402


def run_summary(run_dir: Path, *, train_commit: str, note: str = "") -> dict:
    """``run_dir``'s ``summary.json`` with its training command, ``train_commit``, ``note`` and the CPU.

    Raises:
        SystemExit: ``run_dir`` has no ``summary.json`` (an unfinished run) or no Hydra overrides.
    """
    summary_path = run_dir / "summary.json"
    if not summary_path.exists():
        raise SystemExit(f"{summary_path} is missing: the run in {run_dir} has not finished")
    return {
        "command": training_command(run_dir),
        "train_commit": train_commit,
        "note": note,
        "cpu": cpu_name(),
        "summary": json.loads(summary_path.read_text()),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a finished isodream-train run folder")
    parser.add_argument("--train-commit", required=True, help="the commit the run was trained at")
    parser.add_argument("--note", default="", help="how the run was made (machine load, snapshot)")
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    out = run_summary(args.run_dir, train_commit=args.train_commit, note=args.note)
    made = provenance("run_summary.py", argv, parallel=1)
    out["collected_by"] = {"commit": made["commit"], "command": made["command"]}
    write_json(args.json, out, indent=2)
    summary = out["summary"]
    print(
        f"{out['command']}: eval return {summary.get('eval_return')}, normalised {summary.get('normalised_score')}, "
        f"isolation {summary.get('isolation')}"
    )


if __name__ == "__main__":
    main()
