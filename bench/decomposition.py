"""The decomposition recipe on four scenes: how each world model's branches split a scene into the agent,
the distractors and the background, scored against the ground truth.

Every (scene, algorithm, seed) is one ``isodream-train exp=decomposition`` run (the world model alone on
random-action episodes, :mod:`isodream_rl.trainers.world_model_run`) in its own folder under ``--runs``,
stopped by its wall-clock budget (``--minutes``, the run's ``world_model.max_minutes``: data collection
included). The scenes differ only by the env:

* ``sprites``: three discs, a new background per episode;
* ``dmc_walker_walk``, ``dmc_cheetah_run``: the robot before a ``video_easy`` background video;
* ``highway``: the top-down view on the road's centre line at 2.5 pixels per metre
  (``top_down_follow="road"``), the ego among the other vehicles: steering moves the ego across the frame. The
  ego-centred view (``"ego"``, the env's default) keeps the ego at one place in the frame, about 3 x 7 pixels,
  so "the controllable branch holds the ego" could not tell a branch that follows the ego from one that does
  not; the first-person view does not show the ego at all.

The algorithms (``--algos``): ``isodream``, the default (Iso-Dream on DreamerV3's learner), and ``isodream_v2``, the
same decomposition on the DreamerV2-style learner, by default; ``dreamerv2``, the single-branch baseline, on
request. ``mode=world_model`` trains each one's own world model with its own loss and optimiser
(:mod:`isodream_rl.trainers.world_model_run`).

Finished runs (a ``summary.json``) are read back, not retrained; an interrupted one resumes from its newest
checkpoint (``resume=true``). ``--parallel`` runs share the machine at one torch thread each.

Writes ``--json`` (default ``docs/results/decomposition.json``)::

    {"scenes": {scene: {algo: [{"seed": s, "iou_control_vs_agent": ..., "iou_free_vs_distractors": ...,
                                 "updates": ..., "wall_minutes": ..., ...}, ...]}},
     "minutes": ..., "commit": ..., "cpu": ..., "command": ..., "overrides": [...]}

(each run's held-out scores of :func:`isodream_rl.evaluation.decomposition_scores`, its scores on as many
training episodes with a ``train_`` prefix), one picture per scene, ``decomposition_<scene>.png`` beside the
JSON (the final ground truth, composite, each branch and its mask over a held-out window of the first
Iso-Dream seed; the default's where it ran), each other algorithm's beside it (``decomposition_<scene>_<algo>.png``,
listed under ``"pictures_by_algo"``), and a table (the JSON's path with ``.md``).

    python bench/decomposition.py                                  # 4 scenes x 2 algos x 2 seeds x 30 min
    python bench/decomposition.py --scenes sprites --algos isodream,isodream_v2,dreamerv2 --seeds 0 --minutes 5 \\
        --runs /tmp/dec --json /tmp/dec/decomposition.json

Former names. The committed results (``docs/results/decomposition.json``) and the run folders made before
``algo=isodream`` became DreamerV3's learner name the DreamerV2-style learner ``isodream``
(``<scene>-isodream-s<seed>``). Which learner a run folder holds is its ``summary.json``'s ``learner``; one without
it was written when ``mode=world_model`` trained the DreamerV2-style world model only (:func:`run_learner`). Such a
former run is read back as ``isodream_v2``'s where ``<scene>-isodream_v2-s<seed>`` has none (so ``--collect-only``
reads those folders under today's name), never as the default's, and the bench does not train the default into
its folder (it says so, and leaves the folder as it is: move it elsewhere to train the default there).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance  # noqa: E402

from isodream_rl.run_utils.json_io import is_absent, write_json  # noqa: E402
from isodream_rl.trainers.learners import LEARNERS, learner_name  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The scenes and the ``isodream-train`` overrides that make each (the rest is ``exp=decomposition``).
SCENES = {
    "sprites": ["env=sprites", "env.kwargs.task=none"],
    "dmc_walker_walk": ["env=dmc_walker_walk"],
    "dmc_cheetah_run": ["env=dmc_cheetah_run"],
    "highway": [
        "env=highway",
        "++env.kwargs.view=top_down",
        "++env.kwargs.top_down_follow=road",
        "++env.kwargs.top_down_scaling=2.5",
    ],
}
#: The algorithms the bench runs: the default and the DreamerV2-style learner (:data:`DEFAULT_ALGOS`), and the
#: single-branch baseline.
ALGOS = ("isodream", "isodream_v2", "dreamerv2")
#: ``--algos``' default: the default's world model, and the DreamerV2-style learner's beside it.
DEFAULT_ALGOS = ("isodream", "isodream_v2")
#: ``algo -> former folder name``: the run folders of ``algo``'s learner made under another name,
#: ``<scene>-<former>-s<seed>`` (the DreamerV2-style learner was ``algo=isodream``), read back where ``algo``'s own
#: folder has no finished run.
FORMER_FOLDER_NAMES = {"isodream_v2": "isodream"}
#: the recipe at a tiny size, a check in seconds (each an ``--override``): 2 updates of 2 windows x 8 steps on two
#: 16-step training episodes and one held-out
TINY = [
    "size=tiny",
    "world_model.updates=2",
    "world_model.episodes=2",
    "world_model.held_out_episodes=1",
    "world_model.episode_length=16",
    "train.sequence_length=8",
    "train.batch_size=2",
]
#: The summary's entries that are not scores.
_NOT_SCORES = (
    "mode",
    "algo",
    "learner",
    "env",
    "updates",
    "stopped_by",
    "seconds",
    "precision",
    "size",
    "seed",
)
#: The table's columns: (heading, score).
_COLUMNS = (
    ("control vs agent", "iou_control_vs_agent"),
    ("noncontrollable vs distractors", "iou_free_vs_distractors"),
    ("static vs background", "iou_static_vs_background"),
    ("reconstruction MSE", "reco_mse"),
)


def run_dir(args: argparse.Namespace, scene: str, algo: str, seed: int) -> Path:
    """The folder of the run of ``algo`` on ``scene`` with ``seed``: ``<runs>/<scene>-<algo>-s<seed>``."""
    return args.runs / f"{scene}-{algo}-s{seed}"


def read_summary(folder: Path) -> dict | None:
    """The ``summary.json`` of the run in ``folder``, ``None`` without one (a run not finished, or not started)."""
    path = folder / "summary.json"
    return json.loads(path.read_text()) if path.exists() else None


def run_learner(summary: dict) -> str:
    """The learner whose world model a run's ``summary.json`` scores: its ``learner``; a summary without one was
    written when ``mode=world_model`` trained the DreamerV2-style world model only, ``isodream_v2``'s whatever its
    ``algo``."""
    return summary.get("learner", "isodream_v2")


def finished_run(args: argparse.Namespace, scene: str, algo: str, seed: int) -> Path | None:
    """The folder holding the finished run of ``algo`` on ``scene`` with ``seed``: its own (:func:`run_dir`) where
    its summary is of ``algo``'s learner, else its former folder's (:data:`FORMER_FOLDER_NAMES`) where that holds
    a finished run of ``algo``'s learner; ``None`` without one."""
    folders = [run_dir(args, scene, algo, seed)]
    if algo in FORMER_FOLDER_NAMES:
        folders.append(run_dir(args, scene, FORMER_FOLDER_NAMES[algo], seed))
    for folder in folders:
        summary = read_summary(folder)
        if summary is not None and run_learner(summary) == learner_name(algo):
            return folder
    return None


def former_run_in_the_way(args: argparse.Namespace, scene: str, algo: str, seed: int) -> str | None:
    """Why the run of ``algo`` cannot be trained in its folder, which holds a finished run of another learner (a
    run of the DreamerV2-style learner made when it was ``algo=isodream``): one line; ``None`` where it can."""
    folder = run_dir(args, scene, algo, seed)
    summary = read_summary(folder)
    if summary is None or run_learner(summary) == learner_name(algo):
        return None
    learner = LEARNERS[run_learner(summary)].title
    return (
        f"{folder} holds a finished run of {learner} (saved as algo={summary.get('algo')}, that learner's name "
        f"then; read back as isodream_v2's), not of algo={algo}'s: left as it is and not trained; move it elsewhere "
        f"to train algo={algo} there"
    )


def run_command(args: argparse.Namespace, scene: str, algo: str, seed: int) -> list[str]:
    """The ``isodream-train`` command of one run: resumed where it has a checkpoint, else started afresh."""
    folder = run_dir(args, scene, algo, seed)
    overrides = [
        "exp=decomposition",
        *SCENES[scene],
        f"algo={algo}",
        f"train.seed={seed}",
        f"world_model.max_minutes={args.minutes}",
        "logging.progress_bar=false",
        f"run_dir={folder}",
        *([f"size={args.size}"] if args.size else []),
        *args.override,
    ]
    if any((folder / "checkpoints").glob("step_*[0-9]")):
        overrides.append("resume=true")
    else:  # never started, or stopped before its first checkpoint: start over (the folder holds bench.log)
        overrides.append("overwrite=true")
    return [sys.executable, "-m", "isodream_rl.cli", *overrides]


def train_all(args: argparse.Namespace) -> None:
    """Run every (scene, algo, seed) without a ``summary.json``, ``--parallel`` at a time, seed by seed (a
    bench stopped early has every scene and algorithm on its first seeds)."""
    pending = []
    for seed in args.seeds:
        for scene in args.scenes:
            for algo in args.algos:
                if finished_run(args, scene, algo, seed) is not None:
                    continue
                in_the_way = former_run_in_the_way(args, scene, algo, seed)
                if in_the_way:
                    print(f"[bench] {scene} {algo} seed {seed}: {in_the_way}", flush=True)
                    continue
                pending.append((scene, algo, seed))
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    running: list[tuple[tuple[str, str, int], subprocess.Popen]] = []
    while pending or running:
        while pending and len(running) < args.parallel:
            run = pending.pop(0)
            folder = run_dir(args, *run)
            folder.mkdir(parents=True, exist_ok=True)
            cmd = run_command(args, *run)
            log = (folder / "bench.log").open("a")
            print(f"[bench] start {' '.join(map(str, run))}: {' '.join(cmd[3:])}", flush=True)
            running.append((run, subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=log)))
        time.sleep(1)
        for item in list(running):
            run, proc = item
            if proc.poll() is not None:
                running.remove(item)
                status = "done" if proc.returncode == 0 else f"FAILED (rc {proc.returncode}, see bench.log)"
                print(f"[bench] {' '.join(map(str, run))}: {status}", flush=True)


def collect(args: argparse.Namespace) -> dict:
    """The finished runs' summaries as ``{scene: {algo: [one dict per seed]}}``."""
    scenes: dict = {}
    for scene in args.scenes:
        scenes[scene] = {}
        for algo in args.algos:
            runs = []
            for seed in args.seeds:
                folder = finished_run(args, scene, algo, seed)
                if folder is None:
                    print(f"[bench] {scene} {algo} seed {seed}: no summary.json, left out", flush=True)
                    continue
                summary = read_summary(folder)
                runs.append(
                    {
                        "seed": seed,
                        # an absent score is null (NaN in an older summary): kept, as null
                        **{
                            k: v
                            for k, v in summary.items()
                            if k not in _NOT_SCORES and (_is_number(v) or v is None)
                        },
                        "updates": summary["updates"],
                        "stopped_by": summary.get("stopped_by"),
                        "wall_minutes": round(summary["seconds"] / 60.0, 3),
                        "size": summary["size"],
                        "picture": summary["png"],
                    }
                )
            scenes[scene][algo] = runs
    return scenes


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def scene_picture_algo(algos: dict) -> str | None:
    """The algorithm whose picture stands for a scene: the default (``isodream``), else the DreamerV2-style learner
    (``isodream_v2``), else the first with a run; ``None`` without runs."""
    for algo in ("isodream", "isodream_v2", *algos):
        if algos.get(algo):
            return algo
    return None


def copy_pictures(scenes: dict, folder: Path) -> tuple[dict[str, str], dict[str, dict[str, str]]]:
    """The final branch pictures (the first seed's) in ``folder``: ``decomposition_<scene>.png`` for the algorithm
    of :func:`scene_picture_algo`, ``decomposition_<scene>_<algo>.png`` for each other one.

    Returns:
        ``({scene: file name}, {scene: {algo: file name}})``: the scene's picture, and every algorithm's.
    """
    per_scene: dict[str, str] = {}
    per_algo: dict[str, dict[str, str]] = {}
    folder.mkdir(parents=True, exist_ok=True)
    for scene, algos in scenes.items():
        chosen = scene_picture_algo(algos)
        for algo, runs in algos.items():
            if not runs or not Path(runs[0]["picture"]).exists():
                continue
            name = f"decomposition_{scene}.png" if algo == chosen else f"decomposition_{scene}_{algo}.png"
            shutil.copyfile(runs[0]["picture"], folder / name)
            per_algo.setdefault(scene, {})[algo] = name
            if algo == chosen:
                per_scene[scene] = name
    return per_scene, per_algo


def _fmt(values: list) -> str:
    values = [v for v in values if not is_absent(v)]  # null (an absent score), or NaN in an older summary
    if not values:
        return "n/a"
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{np.mean(values):.3f} ({min(values):.3f} to {max(values):.3f})"


def table(results: dict) -> str:
    """One row per scene and algorithm: the mean (range) over seeds of each :data:`_COLUMNS` score."""
    lines = [
        "| scene | algo | seeds | " + " | ".join(h for h, _ in _COLUMNS) + " | updates | minutes |",
        "|---|---|---|" + "---|" * len(_COLUMNS) + "---|---|",
    ]
    for scene, algos in results["scenes"].items():
        for algo, runs in algos.items():
            cells = [_fmt([r.get(key) for r in runs]) for _, key in _COLUMNS]
            cells += [
                _fmt([r["updates"] for r in runs]).replace(".000", ""),
                _fmt([r["wall_minutes"] for r in runs]),
            ]
            lines.append(f"| {scene} | {algo} | {len(runs)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=lambda s: s.split(","), default=list(SCENES))
    parser.add_argument(
        "--algos",
        type=lambda s: s.split(","),
        default=list(DEFAULT_ALGOS),
        help=f"comma-separated, of {','.join(ALGOS)} (default: {','.join(DEFAULT_ALGOS)})",
    )
    parser.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1])
    parser.add_argument("--minutes", type=float, default=30.0, help="wall-clock budget per run")
    parser.add_argument("--size", default="", help="the size group of isodream-train (default: the recipe's)")
    parser.add_argument("--parallel", type=int, default=1, help="runs at a time (one torch thread each)")
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "bench_decomposition")
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "results" / "decomposition.json")
    parser.add_argument("--override", action="append", default=[], help="extra isodream-train override")
    parser.add_argument("--collect-only", action="store_true", help="only read the finished runs")
    args = parser.parse_args(argv)
    for name, given, valid in (("scenes", args.scenes, SCENES), ("algos", args.algos, ALGOS)):
        unknown = sorted(set(given) - set(valid))
        if unknown:
            parser.error(f"unknown {name} {unknown}; valid: {list(valid)}")
    if args.parallel < 1 or not args.minutes > 0:
        parser.error("--parallel must be >= 1 and --minutes > 0")
    if not args.collect_only:
        train_all(args)
    scenes = collect(args)
    pictures, pictures_by_algo = copy_pictures(scenes, args.json.parent)
    results = {
        "scenes": scenes,
        "pictures": pictures,
        "pictures_by_algo": pictures_by_algo,
        "minutes": args.minutes,
        "scene_overrides": {scene: SCENES[scene] for scene in args.scenes},
        "overrides": args.override,
        **provenance("decomposition.py", argv, parallel=args.parallel),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, results, indent=2)
    args.json.with_suffix(".md").write_text(
        f"# Decomposition: {args.minutes:g} minutes per run\n\n"
        f"Made by `{results['command']}` at commit `{results['commit']}` on `{results['cpu']}`. IoU of each "
        "branch's pixels (the largest mask) with its ground-truth class on held-out episodes, mean (range) "
        "over seeds.\n\n" + table(results) + "\n"
    )
    print(table(results))
    return results


if __name__ == "__main__":
    main()
