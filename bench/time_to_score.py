"""Time to score: the wall-clock a run of ``bench/learning.py`` took to reach a normalised score, per algorithm.

Reads a learning-bench JSON (``bench/learning.py --json``: each seed's curve of evaluation returns with the run's
training wall-clock at each evaluation, ``eval_wall_s``, and the task's reference returns) and writes, per
algorithm and finished seed: the minutes of training until the first evaluation at or above ``--score``
(normalised: 0 the best constant action, 1 the scripted policy; ``null`` where the run never got there), their
median, and the final normalised score per minute of training::

    {"source": ..., "score": 0.5,
     "algos": {algo: {"seeds": [...], "minutes_to_0_5_per_seed": [m or null, ...], "median_minutes_to_0_5": m,
                      "final_normalised_per_seed": [...], "minutes_per_seed": [...],
                      "final_score_per_minute_per_seed": [...], "median_final_score_per_minute": x}},
     "cpu": ..., "commit": ..., "command": ...}

A seed that never reaches the score counts as slower than every seed that does: the median sorts it last, and a
median that falls on (or, with an even count, next to) such a seed is ``null``. The minutes are the runs' own
training clocks (resumed runs add up their segments), measured with one run per core.

    python bench/time_to_score.py docs/results/ladder/r0_plain.json --json docs/results/time_to_score.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance  # noqa: E402

from isodream_rl.run_utils.json_io import nan_if_none, write_json  # noqa: E402


def normalised(value: float, constant: float, scripted: float) -> float:
    """``(value - constant) / (scripted - constant)``: 0 the best constant action, 1 the scripted policy."""
    return (value - constant) / (scripted - constant)


def minutes_to(curve: dict, score: float, constant: float, scripted: float) -> float | None:
    """Minutes of training at the first evaluation of ``curve`` whose normalised return is at least ``score``."""
    for ret, wall in zip(curve["eval_return"], curve["wall_s"], strict=True):
        if ret is not None and wall is not None and normalised(ret, constant, scripted) >= score:
            return wall / 60.0
    return None


def median_with_misses(values: list[float | None]) -> float | None:
    """The median of ``values`` with each ``None`` (a seed that never scored) larger than every number: ``None``
    where the median reaches one."""
    if not values:
        return None
    ordered = sorted(values, key=lambda v: (v is None, v if v is not None else 0.0))
    n = len(ordered)
    middle = ordered[(n - 1) // 2 : n // 2 + 1]
    return None if any(v is None for v in middle) else float(statistics.fmean(middle))


def time_to_score(results: dict, score: float = 0.5) -> dict:
    """Per algorithm of a learning-bench JSON: minutes to ``score`` per finished seed and their median, and the
    final normalised score per minute of training."""
    constant, scripted = results["constant_return"], results["scripted_return"]
    key = f"{score:g}".replace(".", "_")
    out = {}
    for algo, entry in results["algos"].items():
        seeds = entry["seeds"]
        curves = [entry["curves"][str(seed)] for seed in seeds]
        minutes = [minutes_to(curve, score, constant, scripted) for curve in curves]
        walls = [wall / 60.0 for wall in entry["wall_s_per_seed"]]
        finals = entry["normalised_per_seed"]
        # an absent final score (null, or NaN in an older JSON) is NaN per minute, as before
        per_minute = [nan_if_none(final) / wall for final, wall in zip(finals, walls, strict=True)]
        out[algo] = {
            "seeds": seeds,
            f"minutes_to_{key}_per_seed": minutes,
            f"median_minutes_to_{key}": median_with_misses(minutes),
            "final_normalised_per_seed": finals,
            "minutes_per_seed": walls,
            "final_score_per_minute_per_seed": per_minute,
            "median_final_score_per_minute": statistics.median(per_minute) if per_minute else None,
        }
    return out


def table(algos: dict, score: float) -> str:
    key = f"{score:g}".replace(".", "_")

    def fmt(value):
        return "never" if value is None else f"{value:.1f}"

    lines = [
        f"| algo | seeds | minutes to {score:g} per seed | median | final normalised per minute (median) |",
        "|---|---|---|---|---|",
    ]
    for algo, entry in algos.items():
        per_seed = ", ".join(fmt(m) for m in entry[f"minutes_to_{key}_per_seed"])
        lines.append(
            f"| {algo} | {len(entry['seeds'])} | {per_seed} | {fmt(entry[f'median_minutes_to_{key}'])} | "
            f"{entry['median_final_score_per_minute']:.4f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a bench/learning.py JSON")
    parser.add_argument("--score", type=float, default=0.5, help="the normalised score to reach")
    parser.add_argument("--json", type=Path, default=Path("docs/results/time_to_score.json"))
    args = parser.parse_args(argv)
    if not args.source.exists():
        parser.error(f"no learning-bench JSON at {args.source}")
    results = json.loads(args.source.read_text())
    missing = {"constant_return", "scripted_return", "algos"} - set(results)
    if missing:
        parser.error(f"{args.source} is not a bench/learning.py JSON: no {sorted(missing)}")
    algos = time_to_score(results, args.score)
    out = {
        "source": str(args.source),
        "source_cpu": results.get("cpu"),
        "source_commit": results.get("commit"),
        "score": args.score,
        "algos": algos,
        **provenance("bench/time_to_score.py", argv, parallel=results.get("parallel_runs", 1)),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, out, indent=1)
    print(table(algos, args.score))
    return out


if __name__ == "__main__":
    main()
