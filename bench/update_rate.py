"""Updates per second of a real ``isodream-train`` run, per algorithm and size, alone on one core.

Each (algo, size) trains one short run on sprites ``reach`` (the learning bench's env settings by default) with
one torch thread, one run at a time, no evaluation: ``--updates`` updates after the size's random prefill. The
rate is read from the run's own ``updates_per_s`` log (collection included, as in a long run), from the rows
logged after the prefill, skipping the first of them (start-up, first compilation of the kernels). Writes
``--json`` (default ``docs/results/update_rate.json``): per algo and size the median rate, the env steps per
second and the hours 10000 updates take at that rate, with the CPU and the commit. Run it with nothing else on the machine: the
number plans the learning bench's budget (``bench/learning.py``), it is not a speed claim.

    python bench/update_rate.py
    python bench/update_rate.py --algos dreamerv2 --sizes tiny --updates 40 --json /tmp/rate.json
    python bench/update_rate.py --algos torchrl_dreamer_v3 --sizes tiny --updates 2 --log-every 4 \
        --override train.frames_per_batch=5 --json /tmp/rate.json   # a check in two updates
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance, read_scalar  # noqa: E402

from isodream_rl.run_utils.json_io import write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: the learning bench's rung-1 env (no distractors, radius-6 sprites, a pool of 8 backgrounds)
RUNG1 = ["+env.kwargs.num_distractors=0", "+env.kwargs.sprite_size=0.1", "+env.kwargs.num_backgrounds=8"]


def size_settings(size: str) -> dict:
    """``prefill_steps`` and ``train_every`` of a size preset (``train_every`` defaults to 5)."""
    train = yaml.safe_load((ROOT / "isodream_rl" / "configs" / "size" / f"{size}.yaml").read_text())["train"]
    return {"prefill": int(train.get("prefill_steps", 2500)), "train_every": int(train.get("train_every", 5))}


def measure(algo: str, size: str, args: argparse.Namespace) -> dict:
    settings = size_settings(size)
    total = settings["prefill"] + settings["train_every"] * args.updates
    with tempfile.TemporaryDirectory() as run_dir:
        command = [
            sys.executable,
            "-m",
            "isodream_rl.cli",
            f"algo={algo}",
            f"size={size}",
            f"train.total_steps={total}",
            "train.threads=1",
            "logging.eval_every=0",
            "logging.final_eval_episodes=0",
            "logging.progress_bar=false",
            f"logging.log_every={args.log_every}",
            "checkpoint.every_updates=1000000",
            f"run_dir={run_dir}",
            *args.override,
        ]
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        subprocess.run(command, cwd=ROOT, env=env, check=True, capture_output=True)

        def after_prefill(name: str) -> list[float]:
            """The rows of ``name`` after the random prefill (no updates there), less the first (start-up)."""
            return [v for step, v in read_scalar(Path(run_dir), name) if step > settings["prefill"]][1:]

        rates, env_rates = after_prefill("updates_per_s"), after_prefill("env_steps_per_s")
    if not rates:
        raise RuntimeError(f"{algo}/{size}: too few log rows; raise --updates or lower --log-every")
    rate = statistics.median(rates)
    return {
        "updates_per_s": rate,
        "updates_per_s_rows": rates,
        "env_steps_per_s": statistics.median(env_rates) if env_rates else None,
        "hours_per_10k_updates": 10_000 / rate / 3600,
        "updates": args.updates,
        "env_steps": total,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--algos",
        type=lambda s: s.split(","),
        default=["isodream", "isodream_v2", "dreamerv2", "torchrl_dreamer", "torchrl_dreamer_v3"],
    )
    parser.add_argument("--sizes", type=lambda s: s.split(","), default=["bench", "small"])
    parser.add_argument("--updates", type=int, default=400)
    parser.add_argument("--log-every", type=int, default=500, help="env steps between the rate's log rows")
    parser.add_argument(
        "--override", action="append", default=None, help="isodream-train override (RUNG1 if none)"
    )
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "results" / "update_rate.json")
    args = parser.parse_args(argv)
    args.override = RUNG1 if args.override is None else args.override
    result = {"rates": {}, "overrides": args.override, **provenance("update_rate.py", argv, parallel=1)}
    for algo in args.algos:
        for size in args.sizes:
            entry = measure(algo, size, args)
            result["rates"].setdefault(algo, {})[size] = entry
            print(
                f"{algo} {size}: {entry['updates_per_s']:.2f} updates/s, "
                f"{entry['hours_per_10k_updates']:.2f} h per 10k updates",
                flush=True,
            )
            args.json.parent.mkdir(parents=True, exist_ok=True)
            write_json(args.json, result, indent=1)
    return result


if __name__ == "__main__":
    main()
