"""Collect finished ``isodream-train`` runs of the learning ladder into one JSON.

Each rung of the ladder (docs/results/learning.md) is an ``isodream-train`` command; this script reads
what those runs left in their folders (``.hydra/overrides.yaml``, the CSV logs, ``summary.json`` when the
run finished) and writes, per run: the command, the periodic evaluation returns, the training-episode
returns, the reward-loss curve, the number of updates, and the final summary. The reference returns of the
run's env (random, best constant action, scripted) are measured once per distinct env setting.

    python bench/ladder.py runs/ladder/* --json docs/results/archive/learning_ladder.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_name, git_commit, read_scalar, training_command  # noqa: E402

from isodream_rl.envs.reference import reference_returns
from isodream_rl.run_utils.json_io import write_json

ROOT = Path(__file__).resolve().parents[1]


def scalar(run_dir: Path, name: str) -> list[list[float]]:
    return [[step, round(value, 4)] for step, value in read_scalar(run_dir, name)]


def collect_run(run_dir: Path) -> dict:
    config = yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())
    summary_path = run_dir / "summary.json"
    updates = scalar(run_dir, "updates")
    return {
        "command": training_command(run_dir),
        "algo": config["algo"]["name"],
        "env": config["env"]["name"],
        "env_kwargs": config["env"]["kwargs"],
        "env_steps_logged": updates[-1][0] if updates else 0,
        "updates": updates[-1][1] if updates else 0,
        "finished": summary_path.exists(),
        "eval_return": scalar(run_dir, "eval_return"),
        "episode_return": scalar(run_dir, "episode_return"),
        "loss_model_reward": scalar(run_dir, "loss_model_reward"),
        "actor_entropy": scalar(run_dir, "actor_entropy"),
        "summary": json.loads(summary_path.read_text()) if summary_path.exists() else None,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of isodream-train")
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--reference-episodes", type=int, default=20)
    args = parser.parse_args(argv)
    runs = {run.name: collect_run(run) for run in args.runs}
    references: dict[str, dict] = {}
    for run in runs.values():
        key = json.dumps([run["env"], run["env_kwargs"]], sort_keys=True)
        if key not in references:
            refs = reference_returns(
                run["env"], episodes=args.reference_episodes, seed=10_000, **run["env_kwargs"]
            )
            references[key] = {
                "env": run["env"],
                "env_kwargs": run["env_kwargs"],
                **{name: {k: v for k, v in ref.items() if k != "returns"} for name, ref in refs.items()},
            }
        run["references"] = key
    out = {
        "runs": runs,
        "references": references,
        "commit": git_commit(),
        "cpu": cpu_name(),
        "command": "python bench/ladder.py " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, out, indent=1)
    for name, run in runs.items():
        evals = ", ".join(f"{s}: {v:.2f}" for s, v in run["eval_return"])
        print(f"{name}: {run['updates']} updates; eval returns {evals}")


if __name__ == "__main__":
    main()
