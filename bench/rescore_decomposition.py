"""Score finished runs' decompositions again, from their newest checkpoints, with every score the library has now.

A run's ``summary.json`` holds the decomposition scores of the library that trained it; a score added later (which
branch draws the sprites target: ``target_share_<branch>``, ``iou_<branch>_vs_target``) is missing there. This
replays each run's final evaluation episode (:func:`isodream_rl.trainers.run.checkpoint_decomposition`: the same
seed, the newest checkpoint) and scores it again; where the run's ``summary.json`` has a decomposition, the JSON
also says how far the scores both have apart are (0 when the checkpoint is the final one).

With ``--probe`` (sprites runs only) each run also gets the latent probe of the same checkpoint
(:func:`isodream_rl.trainers.run.checkpoint_probe`): the held-out R^2 of ridge read-outs of each sprite's centre from
each branch's posterior state, on fresh episodes of the run's scene. Without a static branch the mask IoU
``iou_free_vs_distractors`` is capped by the discs' share of the frame the action-free branch draws (the background
too); the probe says whether that branch's state carries the discs.

Writes ``--json``::

    {"runs": {label: {"run_dir": ..., "decomposition": {...}, "isolation": {...}, "checkpoint": ...,
                      "episode_steps": N, "max_difference_to_summary": float | null,
                      "probe": {"r2_<branch>_<sprite>": float}}},  # with --probe only
     "commit": ..., "cpu": ..., "command": ...}

    python bench/rescore_decomposition.py --runs static=/path/run_a nostatic=/path/run_b --json out.json [--probe]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance  # noqa: E402

from isodream_rl.run_utils.json_io import write_json  # noqa: E402


def _label_and_dir(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    return (label, Path(path)) if sep else (Path(text).name, Path(text))


def max_difference(first: dict, second: dict) -> float | None:
    """The largest absolute difference between the finite scores both dicts have (``None``: none shared); an absent
    score (``null``, or ``NaN`` in an older ``summary.json``) is left out."""
    shared = [
        abs(first[k] - second[k])
        for k in first.keys() & second.keys()
        if isinstance(first[k], float)
        and isinstance(second[k], float)
        and math.isfinite(first[k])
        and math.isfinite(second[k])
    ]
    return max(shared) if shared else None


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="+", required=True, help="run folders, each optionally as label=path")
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--probe",
        action="store_true",
        help="also the latent probe of each run's checkpoint (sprites runs): held-out R^2 per branch and sprite",
    )
    parser.add_argument(
        "--probe-episodes", type=int, default=32, help="probe episodes (half fit, half score)"
    )
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from isodream_rl.trainers.run import checkpoint_decomposition, checkpoint_probe

    results = {"runs": {}, **provenance("rescore_decomposition.py", argv, parallel=1)}
    for text in args.runs:
        label, run_dir = _label_and_dir(text)
        out = checkpoint_decomposition(run_dir, device=args.device)
        summary_path = run_dir / "summary.json"
        summary = json.loads(summary_path.read_text()).get("decomposition") if summary_path.exists() else None
        out["max_difference_to_summary"] = max_difference(out["decomposition"], summary) if summary else None
        if args.probe:
            probed = checkpoint_probe(run_dir, episodes=args.probe_episodes, device=args.device)
            out["probe"] = probed["probe"]
        results["runs"][label] = {"run_dir": str(run_dir), **out}
        shown = {
            k: v for k, v in out["decomposition"].items() if "target" in k or k == "iou_control_vs_agent"
        }
        shown.update(out.get("probe", {}))
        print(f"{label}: " + ", ".join(f"{k} {v:.2f}" for k, v in shown.items()), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, results, indent=2, default=float)
    return results


if __name__ == "__main__":
    main()
