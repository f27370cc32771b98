"""Learning curves of Iso-Dream (on DreamerV3's learner), the DreamerV2 baseline and TorchRL's DreamerV3 at equal
env steps.

Every (algorithm, seed) is one ``isodream-train`` run in its own folder under ``--runs`` (default
``~/isodream-runs/bench_learning``, outside the work tree); ``--parallel`` runs share the machine at one torch
thread each. A run that was interrupted resumes from its newest checkpoint when the bench is started again
(finished runs are read back, not retrained). Each run evaluates its deterministic policy every
``--eval-every`` env steps and at the end (``--eval-episodes`` episodes, ``summary.json``), next to the task's
reference policies (uniform random, best constant action, scripted).

Budget: a run makes one update every ``train.train_every`` env steps after ``train.prefill_steps`` random
steps, so updates = (env_steps - prefill) / train_every; at ``size=bench`` (prefill 1000, train_every 5) the
default 51000 env steps give every run 10000 updates.

Writes ``--json`` (default ``docs/results/learning.json``) while the runs train (at most every
``--write-every`` seconds and whenever a run ends, so a lost machine still leaves the curves so far) and once
more at the end::

    {"env": ..., "env_kwargs": ..., "env_steps": N, "random_return": R, "constant_return": R,
     "scripted_return": R, "references": {...},
     "algos": {algo: {"final_per_seed": [...], "final_successes_per_seed": [...],
                      "normalised_per_seed": [...], "wall_s_per_seed": [...], "updates_per_seed": [...],
                      "contacts_per_seed": [...], "decomposition_per_seed": [{score: value}, ...],
                      "agent_branch_per_seed": [...], "seeds": [...],
                      "curves": {seed: {"env_steps": [...], "eval_return": [...], "wall_s": [...],
                                        "updates": [...], "iou_control_vs_agent": [...], ...,
                                        "finished": bool}}}},
     "commit": ..., "cpu": ..., "command": ..., "overrides": [...], "algo_overrides": {algo: [...]}}

``decomposition_per_seed`` is each finished run's final decomposition (``summary.json``: every mask IoU of its
world model against the env's ground truth, ``None`` for runs without one, e.g. TorchRL's DreamerV3) and
``agent_branch_per_seed`` the branch whose mask holds the agent most; the curves carry the scores of
:data:`CURVE_DECOMPOSITION` at each evaluation. ``contacts_per_seed``: distractor contacts per episode (sprites).
The ``*_per_seed`` lists and ``seeds`` hold the finished runs (those with a ``summary.json``); ``curves`` also
holds the unfinished ones (``"finished": false``: their evaluations so far, from the CSV logs). ``updates`` is
the update count logged at each evaluation's env step (``None`` where none was logged at that step).

At the end, also a picture (``--png``: eval return against env steps, mean and range over seeds and each
seed's curve, the reference returns as lines) and a table (``--md``: finished seeds, and how many are not).

    python bench/learning.py                       # seeds 0,1 at 51000 env steps (10000 updates per run)
    python bench/learning.py --algos dreamerv2 --seeds 0 --env-steps 2000 --runs /tmp/lb --json /tmp/lb.json
    python bench/learning.py --algos isodream,dreamerv2,torchrl_dreamer   # TorchRL's older Dreamer (not a default)
    python bench/learning.py --algos isodream_v2 --seeds 0    # Iso-Dream on the DreamerV2-style learner
    python bench/learning.py --algos isodream,torchrl_dreamer_v3 --override model.hidden_dim=32 \
        --algo-override isodream:model.free_hidden_fraction=0.6   # a setting one learner reads only

A run folder is ``<algo>_s<seed>``: one made before ``algo=isodream`` became DreamerV3's learner holds, under
``isodream_s<seed>``, the DreamerV2-style learner (now ``isodream_v2``), and under ``isodream_v3_s<seed>``
today's ``isodream``; a finished one is read back as it is, so move those folders first.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance, read_scalar  # noqa: E402

from isodream_rl.run_utils.json_io import is_absent, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The default bench: Iso-Dream (on DreamerV3's learner), the single-branch DreamerV2 baseline and TorchRL's
#: DreamerV3 (the world-model agent a TorchRL user would pick instead).
ALGOS = ("isodream", "dreamerv2", "torchrl_dreamer_v3")
#: Accepted by ``--algos`` but not run by default: Iso-Dream on the DreamerV2-style learner, TorchRL's older
#: (DreamerV1-style) Dreamer pieces.
MORE_ALGOS = ("isodream_v2", "torchrl_dreamer")
#: The task's success count reported beside the return, per env.
SUCCESS_KEY = {"sprites": "reaches", "sprites_reach": "reaches", "highway": "distance"}
#: Seconds between polls of the running runs.
POLL_S = 5.0
#: The decomposition scores a curve carries at each evaluation (runs whose env renders the ground truth).
CURVE_DECOMPOSITION = (
    "iou_control_vs_agent",
    "iou_free_vs_agent",
    "iou_static_vs_agent",
    "iou_free_vs_distractors",
    "target_share_static",
    "mse_target",
    "mse_distractors",
    "mse_background",
)
#: The table's column of each score of :data:`CURVE_DECOMPOSITION`.
DECOMPOSITION_COLUMNS = {
    "iou_control_vs_agent": "IoU controllable vs agent",
    "iou_free_vs_agent": "IoU action-free vs agent",
    "iou_static_vs_agent": "IoU static vs agent",
    "iou_free_vs_distractors": "IoU action-free vs distractors",
    "target_share_static": "target's share in static",
    "mse_target": "image error on the target",
    "mse_distractors": "image error on the distractors",
    "mse_background": "image error on the background",
}


def run_command(algo: str, seed: int, run_dir: Path, args: argparse.Namespace) -> list[str]:
    overrides = [
        f"algo={algo}",
        f"env={args.env}",
        f"size={args.size}",
        f"train.seed={seed}",
        f"train.total_steps={args.env_steps}",
        "train.threads=1",
        f"logging.eval_every={args.eval_every}",
        f"logging.eval_episodes={args.eval_episodes}",
        f"logging.final_eval_episodes={args.eval_episodes}",
        "logging.progress_bar=false",
        f"run_dir={run_dir}",
        *args.override,
        *algo_overrides(args).get(algo, []),
    ]
    if (run_dir / "checkpoints").is_dir() and any((run_dir / "checkpoints").glob("step_*[0-9]")):
        overrides.append("resume=true")
    else:  # never started, or stopped before its first checkpoint: start over (the folder holds bench.log)
        overrides.append("overwrite=true")
    return [sys.executable, "-m", "isodream_rl.cli", *overrides]


def algo_overrides(args: argparse.Namespace) -> dict[str, list[str]]:
    """``--algo-override ALGO:KEY=VALUE`` as ``{algo: ["KEY=VALUE", ...]}``: overrides for one algorithm's runs
    only (a setting the others' learners refuse, such as ``model.free_hidden_fraction``).

    Raises:
        SystemExit: an entry without ``ALGO:`` or naming an algorithm not in ``--algos``.
    """
    out: dict[str, list[str]] = {}
    for entry in args.algo_override:
        algo, sep, override = entry.partition(":")
        if not sep or "=" not in override:
            raise SystemExit(f"--algo-override {entry!r}: expected ALGO:KEY=VALUE")
        if algo not in args.algos:
            raise SystemExit(
                f"--algo-override {entry!r}: {algo!r} is not one of --algos {','.join(args.algos)}"
            )
        out.setdefault(algo, []).append(override)
    return out


def train_all(args: argparse.Namespace, on_progress: Callable[[], object] | None = None) -> None:
    """Run every (algo, seed) without a summary.json, ``--parallel`` at a time, seed by seed (so that a bench
    stopped early still compares every algorithm on its first seeds). ``on_progress()`` (e.g. rewrite the
    JSON) is called whenever a run ends and otherwise at most every ``--write-every`` seconds."""
    pending = [
        (algo, seed)
        for seed in args.seeds
        for algo in args.algos
        if not (args.runs / f"{algo}_s{seed}" / "summary.json").exists()
    ]
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    running: list[tuple[str, int, subprocess.Popen]] = []
    last_progress = time.monotonic()
    while pending or running:
        while pending and len(running) < args.parallel:
            algo, seed = pending.pop(0)
            run_dir = args.runs / f"{algo}_s{seed}"
            run_dir.mkdir(parents=True, exist_ok=True)
            cmd = run_command(algo, seed, run_dir, args)
            log = (run_dir / "bench.log").open("a")
            print(f"[bench] start {algo} seed {seed}: {' '.join(cmd[2:])}", flush=True)
            running.append((algo, seed, subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=log)))
        time.sleep(POLL_S)
        ended = False
        for item in list(running):
            algo, seed, proc = item
            if proc.poll() is not None:
                running.remove(item)
                ended = True
                status = "done" if proc.returncode == 0 else f"FAILED (rc {proc.returncode})"
                print(f"[bench] {algo} seed {seed}: {status}", flush=True)
        if on_progress is not None and (ended or time.monotonic() - last_progress >= args.write_every):
            last_progress = time.monotonic()
            try:
                on_progress()
            except Exception as error:  # a failed interim write must not stop the runs
                print(f"[bench] interim write failed: {error!r}", flush=True)


def _curve(run_dir: Path, summary: dict | None) -> dict | None:
    """A run's evaluations from its CSV logs (then its final one from ``summary``, if finished); ``None`` for a
    run without logs."""
    returns = read_scalar(run_dir, "eval_return")
    updates = read_scalar(run_dir, "updates")
    if summary is None and not returns and not updates:
        return None
    walls = dict(read_scalar(run_dir, "eval_wall_s"))
    steps = [s for s, _ in returns]
    curve = {
        "env_steps": steps,
        "eval_return": [v for _, v in returns],
        "wall_s": [walls.get(s) for s in steps],
    }
    # where the world model's masks put the agent and the distractors at each evaluation (Iso-Dream's runs)
    for score in CURVE_DECOMPOSITION:
        logged = dict(read_scalar(run_dir, f"eval/decomposition/{score}"))
        if logged:
            curve[score] = [logged.get(s) for s in steps]
    if summary is not None:
        curve["env_steps"].append(summary["env_steps"])
        curve["eval_return"].append(summary["eval_return"])
        curve["wall_s"].append(summary["wall_s"])
        final = summary.get("decomposition") or {}
        for score in CURVE_DECOMPOSITION:
            if score in curve:
                curve[score].append(final.get(score))
    # the newest update count logged at or before each evaluation (the logs and the evaluations keep their own
    # schedules); the final evaluation also reads summary.json's count
    curve["updates"] = [
        max((u for s, u in updates if s <= step), default=None) for step in curve["env_steps"]
    ]
    if summary is not None and summary.get("updates") is not None:
        curve["updates"][-1] = summary["updates"]
    curve["finished"] = summary is not None
    return curve


def collect(args: argparse.Namespace, verbose: bool = True) -> dict:
    """Read the runs' logs and summaries into the JSON schema of the module docstring (``env_kwargs`` from the
    first run's ``run_config.json``)."""
    results: dict = {"algos": {}}
    references = None
    env_kwargs = None
    success_key = SUCCESS_KEY.get(args.env)
    for algo in args.algos:
        entry = {
            "final_per_seed": [],
            "final_successes_per_seed": [],
            "normalised_per_seed": [],
            "wall_s_per_seed": [],
            "updates_per_seed": [],
            "contacts_per_seed": [],
            "decomposition_per_seed": [],
            "agent_branch_per_seed": [],
            "seeds": [],
            "curves": {},
        }
        for seed in args.seeds:
            run_dir = args.runs / f"{algo}_s{seed}"
            summary_path = run_dir / "summary.json"
            summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
            curve = _curve(run_dir, summary)
            if curve is None:
                if verbose:
                    print(f"[bench] {algo} seed {seed}: no logs, left out", flush=True)
                continue
            entry["curves"][str(seed)] = curve
            if env_kwargs is None and (run_dir / "run_config.json").exists():
                env_kwargs = (
                    json.loads((run_dir / "run_config.json").read_text()).get("env", {}).get("kwargs")
                )
            if summary is None:
                if verbose:
                    print(f"[bench] {algo} seed {seed}: no summary.json, curve only (unfinished)", flush=True)
                continue
            references = references or summary.get("references")
            entry["seeds"].append(seed)
            entry["final_per_seed"].append(summary["eval_return"])
            entry["final_successes_per_seed"].append(summary.get(f"eval_{success_key}"))
            entry["normalised_per_seed"].append(summary.get("normalised_score"))
            entry["wall_s_per_seed"].append(summary["wall_s"])
            entry["contacts_per_seed"].append(summary.get("eval_contacts"))
            entry["decomposition_per_seed"].append(summary.get("decomposition"))
            entry["agent_branch_per_seed"].append((summary.get("isolation") or {}).get("agent_branch"))
            updates = read_scalar(run_dir, "updates")
            entry["updates_per_seed"].append(updates[-1][1] if updates else None)
        results["algos"][algo] = entry
    for name in ("random", "constant", "scripted"):
        results[f"{name}_return"] = None if references is None else references[name]["return"]
    results["references"] = references
    results["env_kwargs"] = env_kwargs
    return results


def plot(results: dict, path: Path) -> None:
    """Eval return against env steps: per algorithm, the mean and range over the seeds whose curve reaches
    each step, and each seed's curve (dashed while unfinished)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=120)
    colours = {
        "isodream": "tab:blue",
        "isodream_v2": "tab:purple",
        "dreamerv2": "tab:orange",
        "torchrl_dreamer": "tab:green",
        "torchrl_dreamer_v3": "tab:red",
    }
    for algo, entry in results["algos"].items():
        curves = [c for c in entry["curves"].values() if c["env_steps"]]
        if not curves:
            continue
        colour = colours.get(algo)
        grid = np.array(sorted(set().union(*(c["env_steps"] for c in curves))))
        values = np.array(
            [
                np.where(
                    grid <= c["env_steps"][-1], np.interp(grid, c["env_steps"], c["eval_return"]), np.nan
                )
                for c in curves
            ]
        )
        unfinished = sum(not c.get("finished", True) for c in curves)
        label = f"{algo} ({len(curves)} seeds" + (f", {unfinished} unfinished)" if unfinished else ")")
        ax.plot(grid, np.nanmean(values, 0), color=colour, label=label)
        ax.fill_between(grid, np.nanmin(values, 0), np.nanmax(values, 0), color=colour, alpha=0.2)
        for c in curves:
            style = "-" if c.get("finished", True) else "--"
            ax.plot(c["env_steps"], c["eval_return"], color=colour, linestyle=style, linewidth=0.7, alpha=0.5)
    for name, style in (("random", ":"), ("constant", "-."), ("scripted", "--")):
        value = results.get(f"{name}_return")
        if value is not None:
            ax.axhline(value, color="grey", linestyle=style, linewidth=1, label=f"{name} policy")
    ax.set_xlabel("env steps")
    ax.set_ylabel("evaluation return (mode actions)")
    ax.set_title(f"{results['env']}: mean and range over seeds")
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def _fmt(values, digits=1) -> str:
    """``mean (min to max)`` of ``values`` less the absent ones (``None``, JSON ``null``, or an older JSON's
    ``nan``); ``n/a`` where none is left."""
    values = [v for v in values if not is_absent(v)]
    if not values:
        return "n/a"
    return f"{np.mean(values):.{digits}f} ({min(values):.{digits}f} to {max(values):.{digits}f})"


def _final_scores(entry: dict, score: str) -> list:
    """Each finished seed's final ``score``; ``None`` where the run has none, or where the score is about the
    distractors and its scene had none (``mse_distractors`` is then ``null``, ``nan`` in a summary written before
    absent scores were ``null``, or missing)."""
    values = []
    for scores in entry.get("decomposition_per_seed", []):
        scores = scores or {}
        absent = score.endswith("_distractors") and is_absent(scores.get("mse_distractors"))
        values.append(None if absent else scores.get(score))
    return values


def table(results: dict) -> str:
    """Markdown table over the finished seeds, with the count of unfinished ones (logs, no summary.json): returns,
    success and contact counts, wall-clock, and the world models' final mask IoUs (:data:`CURVE_DECOMPOSITION`)."""
    success = SUCCESS_KEY.get(results["env"], "successes")
    columns = [DECOMPOSITION_COLUMNS[score] for score in CURVE_DECOMPOSITION]
    lines = [
        f"| algo | seeds | unfinished | final return | normalised score | {success} per episode "
        f"| contacts per episode | wall-clock per run (min) | {' | '.join(columns)} |",
        "|---" * (8 + len(columns)) + "|",
    ]
    for algo, entry in results["algos"].items():
        unfinished = sum(not c.get("finished", True) for c in entry["curves"].values())
        ious = " | ".join(_fmt(_final_scores(entry, score), 2) for score in CURVE_DECOMPOSITION)
        lines.append(
            f"| {algo} | {len(entry['seeds'])} | {unfinished} | {_fmt(entry['final_per_seed'])} | "
            f"{_fmt(entry['normalised_per_seed'], 2)} | {_fmt(entry['final_successes_per_seed'])} | "
            f"{_fmt(entry.get('contacts_per_seed', []))} | "
            f"{_fmt([w / 60 for w in entry['wall_s_per_seed']])} | {ious} |"
        )
    refs = results.get("references") or {}
    for name in ("random", "constant", "scripted"):
        if name in refs:
            ref = refs[name]
            normalised = {"constant": "0", "scripted": "1"}.get(name, "-")
            lines.append(
                f"| {name} policy | - | - | {ref['return']:.1f} | {normalised} "
                f"| {ref.get(success, float('nan')):.1f} | {ref.get('contacts', float('nan')):.1f} | - |"
                + " - |"
                * len(columns)
            )
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The bench's command line (its defaults: see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", type=lambda s: s.split(","), default=list(ALGOS))
    parser.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1])
    parser.add_argument("--env", default="sprites", help="the env group of isodream-train")
    parser.add_argument("--size", default="bench", help="the size group of isodream-train")
    parser.add_argument(
        "--env-steps",
        type=int,
        default=51_000,
        help="per run; 10000 updates at size=bench (module docstring)",
    )
    parser.add_argument("--eval-every", type=int, default=2_500)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--parallel", type=int, default=2, help="runs at a time (one torch thread each)")
    parser.add_argument("--runs", type=Path, default=Path.home() / "isodream-runs" / "bench_learning")
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "results" / "learning.json")
    parser.add_argument("--png", type=Path, default=None, help="default: the JSON's path with .png")
    parser.add_argument(
        "--md",
        type=Path,
        default=None,
        help="default: the JSON's path with .md (learning_table.md for learning.json: learning.md is the status page)",
    )
    parser.add_argument(
        "--write-every", type=float, default=120.0, help="seconds between rewrites of --json while runs train"
    )
    parser.add_argument("--override", action="append", default=[], help="extra isodream-train override")
    parser.add_argument(
        "--algo-override",
        action="append",
        default=[],
        metavar="ALGO:KEY=VALUE",
        help="extra isodream-train override for one algorithm's runs only",
    )
    parser.add_argument("--collect-only", action="store_true", help="train nothing, only read the runs")
    return parser


def write_results(args: argparse.Namespace, argv: list[str] | None, final: bool = True) -> dict:
    """Collect the runs and write ``--json`` (atomically: a temporary file, then a rename); with ``final``,
    also the picture and the table."""
    results = {
        "env": args.env,
        "env_steps": args.env_steps,
        **collect(args, verbose=final),
        "size": args.size,
        "overrides": args.override,
        "algo_overrides": algo_overrides(args),
        **provenance("learning.py", argv, parallel=args.parallel),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, results, indent=2, atomic=True)
    if final:
        plot(results, args.png or args.json.with_suffix(".png"))
        md = args.md or table_path(args.json)
        md.write_text(
            f"# Learning on {args.env}: final evaluation at {args.env_steps} env steps\n\n"
            f"Made by `{results['command']}` at commit `{results['commit']}` on `{results['cpu']}`.\n\n"
            + table(results)
            + "\n"
        )
    return results


#: The hand-written status page of the learning results, which no table may overwrite.
STATUS_PAGE = ROOT / "docs" / "results" / "learning.md"


def table_path(json_path: Path) -> Path:
    """Where the final table of ``json_path`` goes by default: the same path with ``.md``, except where that is
    :data:`STATUS_PAGE` (the default ``--json``): ``learning_table.md`` beside it."""
    md = json_path.with_suffix(".md")
    return md.with_name("learning_table.md") if md.resolve() == STATUS_PAGE.resolve() else md


def main(argv: list[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    unknown = set(args.algos) - set(ALGOS) - set(MORE_ALGOS)
    if unknown:
        parser.error(f"unknown algos {sorted(unknown)}; valid: {list(ALGOS + MORE_ALGOS)}")
    if not args.collect_only:
        train_all(args, on_progress=lambda: write_results(args, argv, final=False))
    results = write_results(args, argv)
    print(table(results))
    return results


if __name__ == "__main__":
    main()
