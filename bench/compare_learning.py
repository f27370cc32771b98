"""Side by side: runs of several learning-bench JSONs (``bench/learning.py``) in one JSON, plot and table.

Each ``--entry LABEL=PATH[:ALGO]`` takes the algorithm ``ALGO`` (default: the JSON's only one) of the bench JSON
at ``PATH`` under the name ``LABEL``: variants of one algorithm trained from different code (a piece of the
learner removed in a snapshot of the repository) or with different settings, each measured by its own bench
command, compared at equal env steps. The entries must share the env and its reference returns (the normalised
scores are against them); a mismatch is refused.

    python bench/compare_learning.py --entry default=a.json --entry "without two-hot=b.json" --json out.json

writes ``out.json`` (the schema of ``bench/learning.py`` with ``algos`` keyed by label, plus per label
``source``, the mean over its evaluations ``mean_eval_per_seed`` and ``eval_at`` (env steps -> return per seed),
and ``sources``: each input's command and commit), ``out.png`` (the curves) and ``out.md`` (the table).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import provenance  # noqa: E402
from learning import STATUS_PAGE, plot, table  # noqa: E402  (bench/learning.py: the bench's own plot and table)

from isodream_rl.run_utils.json_io import nan_if_none, write_json  # noqa: E402


def parse_entry(text: str) -> tuple[str, Path, str | None]:
    """``LABEL=PATH[:ALGO]`` -> ``(label, path, algo or None)``."""
    label, sep, rest = text.partition("=")
    if not sep or not label or not rest:
        raise argparse.ArgumentTypeError(f"--entry takes LABEL=PATH[:ALGO], got {text!r}")
    path, _, algo = rest.partition(":")
    return label, Path(path), algo or None


def compare(entries: list[tuple[str, Path, str | None]]) -> dict:
    """The combined results (module docstring); raises ``ValueError`` on an entry that does not fit."""
    results: dict = {"algos": {}, "sources": {}}
    for label, path, algo in entries:
        if label in results["algos"]:
            raise ValueError(f"label {label!r} given twice")
        source = json.loads(path.read_text())
        algos = source.get("algos", {})
        if algo is None:
            if len(algos) != 1:
                raise ValueError(f"{path} holds algos {sorted(algos)}: name one as {label}={path}:ALGO")
            (algo,) = algos
        if algo not in algos:
            raise ValueError(f"{path} holds no algo {algo!r} (it holds {sorted(algos)})")
        for key in ("env", "env_kwargs", "size", "random_return", "constant_return", "scripted_return"):
            if key in results and results[key] != source.get(key):
                raise ValueError(
                    f"{path}: {key}={source.get(key)!r} differs from the first entry's {results[key]!r}; "
                    "compare runs of one env and one reference set only"
                )
            results.setdefault(key, source.get(key))
        results.setdefault("references", source.get("references"))
        entry = dict(algos[algo], source=f"{path.name}:{algo}")
        entry["mean_eval_per_seed"] = [
            float(np.mean([nan_if_none(v) for v in curve["eval_return"]]))
            for curve in entry["curves"].values()
            if curve["eval_return"]
        ]
        eval_at: dict[str, dict[str, float]] = {}
        for seed, curve in entry["curves"].items():
            for steps, value in zip(curve["env_steps"], curve["eval_return"]):
                eval_at.setdefault(str(steps), {})[seed] = value
        entry["eval_at"] = eval_at
        results["algos"][label] = entry
        results["sources"][label] = {
            "path": path.name,
            "algo": algo,
            "command": source.get("command"),
            "commit": source.get("commit"),
            "overrides": source.get("overrides"),
        }
    return results


def side_table(results: dict, marks: list[int] | None = None) -> str:
    """Markdown: per label, the updates and final return per seed, the mean over its evaluations and the return
    at each env-step mark (default: every evaluation's; per seed, ``/``-separated)."""
    if marks is None:
        marks = sorted({int(steps) for entry in results["algos"].values() for steps in entry["eval_at"]})
    lines = [
        "| variant | updates | final return | mean over evaluations | "
        + " | ".join(f"{m} env steps" for m in marks)
        + " |",
        "|---|---|---|---|" + "---|" * len(marks),
    ]

    def seeds(values, spec: str = ".1f") -> str:
        return " / ".join("-" if v is None else format(v, spec) for v in values) or "-"

    for label, entry in results["algos"].items():
        at = [seeds(entry["eval_at"].get(str(m), {}).values()) for m in marks]
        lines.append(
            f"| {label} | {seeds(entry['updates_per_seed'], '.0f')} | {seeds(entry['final_per_seed'])} "
            f"| {seeds(entry['mean_eval_per_seed'])} | " + " | ".join(at) + " |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--entry", type=parse_entry, action="append", required=True, help="LABEL=PATH[:ALGO]")
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument(
        "--marks",
        type=lambda text: [int(m) for m in text.split(",")],
        help="env steps of the table's columns",
    )
    parser.add_argument("--png", type=Path, help="default: the JSON's path with .png")
    parser.add_argument("--md", type=Path, help="default: the JSON's path with .md")
    args = parser.parse_args(argv)
    try:
        results = compare(args.entry)
    except (ValueError, OSError) as error:
        parser.error(str(error))
    md = args.md or args.json.with_suffix(".md")
    if md.resolve() == STATUS_PAGE.resolve():
        parser.error(f"{md} is the hand-written status page: write the table elsewhere (--md)")
    results.update(provenance("compare_learning.py", argv, parallel=1))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, results, indent=2)
    plot(results, args.png or args.json.with_suffix(".png"))
    text = table(results) + "\n\n" + side_table(results, args.marks)
    md.write_text(
        f"# Side by side on {results['env']}\n\nMade by `{results['command']}` at commit `{results['commit']}`.\n\n{text}\n"
    )
    print(text)
    return results


if __name__ == "__main__":
    main()
