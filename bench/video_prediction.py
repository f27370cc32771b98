"""Train every video-prediction variant on the local BAIR-like pusher set with bouncing balls, at CPU
scale, and evaluate them on the fixed test split (2 -> 28 frames).

Writes the JSON (``--json``), and next to it a markdown table (``.md``), the per-frame curves
(``_curves.png``) and a Figure-6-style showcase of the full model (``_showcase.png``).

    python bench/video_prediction.py --json docs/results/video_prediction.json

``--speed`` instead times training iterations (forward, backward, gradient clipping, Adam step) of the
plain path (contiguous layout, fp32: the predictor as committed before channels-last) against the fast
paths (channels-last fp32; channels-last + bf16 autocast) at the same sizes, from the same weights, in one
process with one thread, round-robin, and reports iterations per second (median) and the ratios:

    python bench/video_prediction.py --speed --json docs/results/video_prediction_speed.json

``--paper-scale`` counts the FLOPs of an iteration at the bench's and at the paper's sizes and estimates what the
paper's 80k iterations cost on this CPU and on a GPU:

    python bench/video_prediction.py --paper-scale --json docs/results/video_prediction_paper_scale.json

Each run (variant x seed) trains in its own process (``isodream-video train --resume``) with one torch thread;
``--parallel`` of them run at a time, seed by seed, the full model and ``no_action_free`` first. Every run
trains the same ``--iterations`` (``--max-minutes`` per process only cuts a session short), draws a validation
point every ``--val-every`` iterations (MSE / PSNR / SSIM over the predicted frames of the first test batches:
the curve that shows whether training has flattened) and checkpoints every ``--checkpoint-every`` iterations.
The bench is resumable: run the same command again and finished runs are skipped, interrupted ones continue
from their last checkpoint; raising ``--iterations`` trains every run further (Adam's learning rate is
constant). ``--collect-only`` writes the JSON and pictures from the runs on disk.

    python bench/video_prediction.py --iterations 1000 --seeds 0 1 --parallel 2 --out-dir runs/bench_video \
        --json docs/results/video_prediction.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_name, git_commit  # noqa: E402

from isodream_rl.run_utils.json_io import nan_if_none, write_json  # noqa: E402

VARIANTS = ("isodream", "no_action_free", "no_inverse", "predrnn")
SPEED_PATHS = {
    "plain": {"channels_last": False, "precision": "fp32"},
    "channels_last": {"channels_last": True, "precision": "fp32"},
    "channels_last_bf16": {"channels_last": True, "precision": "bf16"},
}
"""Timed by ``--speed``: ``plain`` is the reference the others are compared with."""


def _native_bf16() -> bool:
    """Whether the CPU has bf16 dot-product instructions (``avx512_bf16`` or ``amx_bf16``)."""
    cpuinfo = Path("/proc/cpuinfo")
    flags = set(cpuinfo.read_text().split()) if cpuinfo.exists() else set()
    return bool(flags & {"avx512_bf16", "amx_bf16"})


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--json", type=Path, help="default: video_prediction.json (video_prediction_speed.json with --speed)"
    )
    p.add_argument("--speed", action="store_true", help="time the plain and fast paths instead of training")
    p.add_argument(
        "--paper-scale",
        action="store_true",
        help="count the FLOPs of a training iteration at the paper's sizes and estimate the cost of its 80k "
        "iterations (no training)",
    )
    p.add_argument("--speed-repeats", type=int, default=8, help="timed iterations per path and variant")
    p.add_argument("--frames", type=int, default=12, help="frames per training clip (--speed, --paper-scale)")
    p.add_argument("--out-dir", type=Path, default=Path("runs/bench_video"))
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--iterations", type=int, default=1000, help="iterations of every run (equal budgets)")
    p.add_argument(
        "--max-minutes",
        type=float,
        default=0.0,
        help="stop each process after this long (0: no limit); rerun to resume",
    )
    p.add_argument("--parallel", type=int, default=1, help="runs at a time (one thread each)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument(
        "--single-seed-variants",
        nargs="*",
        default=["no_inverse", "predrnn"],
        help="variants trained with the first seed only",
    )
    p.add_argument(
        "--data-seed", type=int, default=0, help="seed of the pusher set and the test balls (shared)"
    )
    p.add_argument(
        "--rgb-activation",
        choices=("sigmoid", "linear"),
        default="sigmoid",
        help="branch outputs bounded by a sigmoid (default) or linear (the authors')",
    )
    p.add_argument("--val-every", type=int, default=250)
    p.add_argument("--val-batches", type=int, default=4)
    p.add_argument("--checkpoint-every", type=int, default=250)
    p.add_argument(
        "--collect-only", action="store_true", help="only write the JSON and pictures from the runs"
    )
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--hidden-channels", type=int, default=32)
    p.add_argument("--kernel-size", type=int, default=3)
    p.add_argument("--encoder-channels", type=int, nargs=2, default=[16, 32])
    p.add_argument("--action-embedding", type=int, default=32)
    p.add_argument("--train-sequences", type=int, default=1000)
    p.add_argument("--test-sequences", type=int, default=128)
    p.add_argument("--seed", type=int, default=0, help="--speed only: seed of the weights and clips")
    p.add_argument(
        "--precision",
        choices=("fp32", "bf16"),
        default="bf16" if _native_bf16() else "fp32",
        help="training precision; default bf16 where the CPU has native bf16 (1.55x per iteration on an "
        "avx512_bf16 CPU, docs/results/video_prediction_speed.json), else fp32",
    )
    args = p.parse_args()
    if args.json is None:
        args.json = Path(
            "video_prediction_speed.json"
            if args.speed
            else "video_prediction_paper_scale.json"
            if args.paper_scale
            else "video_prediction.json"
        )
    return args


def _runs(args: argparse.Namespace) -> list[tuple[str, int]]:
    """``(variant, seed)`` in running order: seed by seed, every variant of a seed before the next seed;
    ``--single-seed-variants`` run with the first seed only."""
    return [
        (variant, seed)
        for i, seed in enumerate(args.seeds)
        for variant in args.variants
        if i == 0 or variant not in args.single_seed_variants
    ]


def _run_dir(args: argparse.Namespace, variant: str, seed: int) -> Path:
    return args.out_dir / variant / f"seed_{seed}"


def _finished(args: argparse.Namespace, variant: str, seed: int) -> dict | None:
    """The run's result if it has trained ``--iterations`` already."""
    path = _run_dir(args, variant, seed) / "result.json"
    if not path.exists():
        return None
    result = json.loads(path.read_text())
    return result if result["iterations"] >= args.iterations else None


def _train_command(args: argparse.Namespace, variant: str, seed: int) -> list[str]:
    out = _run_dir(args, variant, seed)
    return [
        sys.executable, "-m", "isodream_rl.video_prediction.cli", "train",
        "--variant", variant,
        "--iterations", str(args.iterations),
        *(["--max-minutes", str(args.max_minutes)] if args.max_minutes else []),
        "--eval-every", str(10**9),
        "--val-every", str(args.val_every),
        "--val-batches", str(args.val_batches),
        "--checkpoint-every", str(args.checkpoint_every),
        "--batch-size", str(args.batch_size),
        "--lr", str(args.lr),
        "--hidden-channels", str(args.hidden_channels),
        "--kernel-size", str(args.kernel_size),
        "--encoder-channels", *map(str, args.encoder_channels),
        "--action-embedding", str(args.action_embedding),
        "--train-sequences", str(args.train_sequences),
        "--test-sequences", str(args.test_sequences),
        "--seed", str(seed),
        "--data-seed", str(args.data_seed),
        "--precision", args.precision,
        "--rgb-activation", args.rgb_activation,
        "--threads", "1",
        "--out-dir", str(out),
        "--result-json", str(out / "result.json"),
        "--no-progress",
        "--resume",
    ]  # fmt: skip


def _table(variants: dict, copy_last: dict) -> str:
    lines = [
        "| variant | seeds | iterations | PSNR 10 | SSIM 10 | PSNR 28 | SSIM 28 | PSNR 28 (uint8) | SSIM 28 (uint8) |"
        " minutes per run |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def cell(values: list[float], digits: int) -> str:
        mean = sum(values) / len(values)
        if len(values) == 1:
            return f"{mean:.{digits}f}"
        return f"{mean:.{digits}f} ({min(values):.{digits}f} to {max(values):.{digits}f})"

    for name, v in variants.items():
        runs = v["seeds"]
        row = [name, str(len(runs)), "/".join(str(r["iterations"]) for r in runs)]
        for key, digits in (("psnr_10", 2), ("ssim_10", 3), ("psnr_28", 2), ("ssim_28", 3),
                            ("psnr_uint8_28", 2), ("ssim_uint8_28", 3)):  # fmt: skip
            row.append(cell([r[key] for r in runs], digits))
        row.append(cell([r["train_minutes"] for r in runs], 1))
        lines.append("| " + " | ".join(row) + " |")
    lines.append(
        f"| copy_last_frame | - | - | {copy_last['psnr_10']:.2f} | {copy_last['ssim_10']:.3f} | "
        f"{copy_last['psnr_28']:.2f} | {copy_last['ssim_28']:.3f} | {copy_last['psnr_uint8_28']:.2f} | "
        f"{copy_last['ssim_uint8_28']:.3f} | - |"
    )
    return "\n".join(lines) + "\n"


def _copy_last_frame(args: argparse.Namespace) -> tuple[dict[str, float], dict[str, list[float]]]:
    """Scores of repeating the last observed frame, the floor every variant should clear: summary and curves."""
    from isodream_rl.video_prediction.metrics import FrameMetrics
    from isodream_rl.video_prediction.trainer import VideoTrainConfig, build_split

    config = VideoTrainConfig(
        seed=args.data_seed, test_sequences=args.test_sequences, train_sequences=args.train_sequences
    )
    metrics = FrameMetrics()
    for clip in build_split(config, "test"):
        frames = clip["frames"][None]
        last = frames[:, config.context - 1 : config.context]
        metrics.update(last.expand_as(frames[:, config.context :]), frames[:, config.context :])
    curves = metrics.compute()
    summary = FrameMetrics.summarize(curves, config.horizons)
    return {k: round(v, 4) for k, v in summary.items()}, {
        k: [round(float(x), 5) for x in v] for k, v in curves.items()
    }


def _aims(variants: dict, copy_last: dict) -> dict:
    """The issue's aims, checked on every seed: above copy-last-frame at 28 frames, and the full model's
    PSNR gain over ``no_action_free`` (seed by seed, same seeds)."""
    out = {
        "above_copy_last_frame": {
            name: {key: all(r[key] > copy_last[key] for r in v["seeds"]) for key in ("psnr_28", "ssim_28")}
            for name, v in variants.items()
        }
    }
    if "isodream" in variants and "no_action_free" in variants:
        full = {r["seed"]: r["psnr_28"] for r in variants["isodream"]["seeds"]}
        ablation = {r["seed"]: r["psnr_28"] for r in variants["no_action_free"]["seeds"]}
        gains = [round(full[k] - ablation[k], 3) for k in sorted(full) if k in ablation]
        out["psnr_28_gain_over_no_action_free"] = {
            "per_seed": gains,
            "mean": round(sum(gains) / len(gains), 3) if gains else None,
            "aim_db": 1.0,
            "met": bool(gains) and min(gains) >= 1.0,
        }
    return out


def _save_validation_curves(path: Path, history: dict) -> None:
    """Validation MSE and PSNR (mean over the predicted frames) against training iterations, per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    for variant, runs in history.items():
        for run, points in runs.items():
            steps = [p["iteration"] for p in points]
            mse_key = max((k for k in points[0] if k.startswith("mse_")), key=lambda k: int(k.split("_")[1]))
            psnr_key = mse_key.replace("mse", "psnr")
            axes[0].plot(steps, [p[mse_key] for p in points], label=f"{variant} {run}")
            axes[1].plot(steps, [p[psnr_key] for p in points], label=f"{variant} {run}")
    axes[0].set_ylabel(f"validation MSE ({mse_key.split('_')[1]} frames)")
    axes[1].set_ylabel(f"validation PSNR (dB, {psnr_key.split('_')[1]} frames)")
    for ax in axes:
        ax.set_xlabel("training iteration")
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _speed(args: argparse.Namespace) -> dict:
    """Iterations per second of each of :data:`SPEED_PATHS` per variant, timed round-robin in this process."""
    import torch

    from isodream_rl.video_prediction.config import variant_config
    from isodream_rl.video_prediction.objective import VideoPredictionLoss
    from isodream_rl.video_prediction.predictor import ThreeBranchPredictor

    torch.set_num_threads(1)
    sizes = dict(
        hidden_channels=args.hidden_channels,
        kernel_size=args.kernel_size,
        encoder_channels=tuple(args.encoder_channels),
        action_embedding=args.action_embedding,
    )
    batch = _random_batch(args.batch_size, args.frames, seed=args.seed)
    results = {}
    for variant in args.variants:
        runs = {}
        for name, switches in SPEED_PATHS.items():
            torch.manual_seed(args.seed)
            model = ThreeBranchPredictor(config=variant_config(variant, **sizes, **switches))
            if runs:  # every path starts from the same weights
                model.load_state_dict(next(iter(runs.values()))[0].state_dict())
            runs[name] = (model, VideoPredictionLoss(model), torch.optim.Adam(model.parameters(), lr=args.lr))

        def iteration(model, loss_fn, optimizer) -> float:
            start = time.perf_counter()
            total = sum(loss_fn(batch).values())
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            optimizer.step()
            return time.perf_counter() - start

        # FLOPs of one iteration's forward + backward (equal on every path; counted on the plain one).
        gflop = _iteration_gflop(runs["plain"][1], batch)
        seconds = {name: [] for name in runs}
        for repeat in range(args.speed_repeats + 1):  # the first round warms up (oneDNN kernels, allocator)
            for name, run in runs.items():
                elapsed = iteration(*run)
                if repeat:
                    seconds[name].append(elapsed)
        median = {name: statistics.median(v) for name, v in seconds.items()}
        results[variant] = {
            "iterations_per_s": {name: round(1 / t, 3) for name, t in median.items()},
            "ratio_vs_plain": {name: round(median["plain"] / t, 3) for name, t in median.items()},
            "gflop_per_iteration": round(gflop, 2),
            "achieved_gflop_per_s": {name: round(gflop / t, 1) for name, t in median.items()},
            "seconds": {name: [round(x, 4) for x in v] for name, v in seconds.items()},
        }
        print(variant, results[variant]["iterations_per_s"], results[variant]["ratio_vs_plain"], flush=True)
    return results


PAPER_SIZES = {"hidden_channels": 64, "kernel_size": 5, "encoder_channels": (32, 64), "action_embedding": 64}
"""The paper's BAIR model (Appendix D): batch 8, 2 + 10 training frames, Adam 1e-4, 80k iterations."""
PAPER_ITERATIONS = 80_000


def _random_batch(batch_size: int, frames: int, *, seed: int = 0):
    """Random clips of the training shape (64x64, 4-dim actions): the model's cost does not depend on the pixels."""
    import torch
    from tensordict import TensorDict

    generator = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "frames": torch.rand(batch_size, frames, 3, 64, 64, generator=generator),
            "actions": torch.randn(batch_size, frames, 4, generator=generator),
        },
        batch_size=[batch_size],
    )


def _iteration_gflop(loss_fn, batch) -> float:
    """FLOPs of one training iteration's forward + backward (``torch.utils.flop_counter``), in GFLOP."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        sum(loss_fn(batch).values()).backward()
    return counter.get_total_flops() / 1e9


def _variant_gflop(variant: str, sizes: dict, *, batch_size: int, frames: int) -> float:
    """:func:`_iteration_gflop` of a fresh ``variant`` model of ``sizes``."""
    from isodream_rl.video_prediction.config import variant_config
    from isodream_rl.video_prediction.objective import VideoPredictionLoss
    from isodream_rl.video_prediction.predictor import ThreeBranchPredictor

    model = ThreeBranchPredictor(config=variant_config(variant, **sizes))
    return _iteration_gflop(VideoPredictionLoss(model), _random_batch(batch_size, frames))


def _write_paper_scale(args: argparse.Namespace) -> None:
    """GFLOP per iteration at the bench's and the paper's sizes, and what 80k paper-size iterations cost: on this
    CPU at the throughput ``--speed`` measured (``video_prediction_speed.json``), and on a GPU at a few sustained
    throughputs (assumptions, stated as such: no GPU was measured)."""
    import torch

    torch.set_num_threads(1)
    speed_path = Path(__file__).resolve().parents[1] / "docs" / "results" / "video_prediction_speed.json"
    speed = json.loads(speed_path.read_text()) if speed_path.exists() else None
    bench_sizes = {
        "hidden_channels": args.hidden_channels,
        "kernel_size": args.kernel_size,
        "encoder_channels": tuple(args.encoder_channels),
        "action_embedding": args.action_embedding,
    }
    variants = {}
    for variant in args.variants:
        bench = _variant_gflop(variant, bench_sizes, batch_size=args.batch_size, frames=args.frames)
        paper = _variant_gflop(variant, PAPER_SIZES, batch_size=8, frames=12)
        row = {
            "gflop_per_iteration_bench_sizes": round(bench, 2),
            "gflop_per_iteration_paper_sizes": round(paper, 2),
            "paper_iterations": PAPER_ITERATIONS,
            "paper_pflop_total": round(paper * PAPER_ITERATIONS / 1e6, 2),
            "gpu_hours_at_sustained_tflop_per_s": {
                str(t): round(paper * PAPER_ITERATIONS / (t * 1e3) / 3600, 2) for t in (10, 30, 100)
            },
        }
        if speed is not None and variant in speed["variants"]:
            for path, rate in speed["variants"][variant]["achieved_gflop_per_s"].items():
                row.setdefault("cpu_one_thread_hours_at_measured_gflop_per_s", {})[path] = round(
                    paper * PAPER_ITERATIONS / rate / 3600, 1
                )
        variants[variant] = row
        print(variant, row, flush=True)
    out = {
        "variants": variants,
        "paper_sizes": {**PAPER_SIZES, "batch_size": 8, "frames": 12, "num_layers": 2},
        "bench_sizes": {**bench_sizes, "batch_size": args.batch_size, "frames": args.frames, "num_layers": 2},
        "note": "GPU hours are FLOPs / an assumed sustained throughput (10, 30, 100 TFLOP/s); no GPU was measured. "
        "CPU hours use the GFLOP/s this CPU sustained at the bench's sizes (video_prediction_speed.json); "
        "larger convolutions usually run at least as fast, so they are upper bounds for one thread.",
        "speed_json_cpu": None if speed is None else speed["cpu"],
        "cpu": cpu_name(),
        "commit": git_commit(),
        "command": " ".join(["python", *sys.argv]),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, out, indent=2)


def _write_speed(args: argparse.Namespace) -> None:
    start = time.monotonic()
    results = _speed(args)
    committed = Path(__file__).resolve().parents[1] / "docs" / "results" / "video_prediction.json"
    reference = {}
    if committed.exists():
        # The committed bench's training rate (two variants at a time on a loaded machine): context only,
        # since it was not measured side by side with the paths above.
        for name, v in json.loads(committed.read_text())["variants"].items():
            for run in v.get("seeds", [v]):
                reference.setdefault(name, round(run["iterations"] / run["train_minutes"], 2))
    out = {
        "variants": results,
        "paths": SPEED_PATHS,
        "config": {
            "batch_size": args.batch_size,
            "frames": args.frames,
            "context": 2,
            "image_size": 64,
            "hidden_channels": args.hidden_channels,
            "kernel_size": args.kernel_size,
            "encoder_channels": args.encoder_channels,
            "action_embedding": args.action_embedding,
            "num_layers": 2,
            "threads": 1,
            "timed_iterations_per_path": args.speed_repeats,
            "iteration": "loss forward + backward + grad-norm clip + Adam step, random clips (no data loading)",
        },
        "committed_bench_iterations_per_minute": reference,
        "cpu": cpu_name(),
        "cpu_native_bf16": _native_bf16(),
        "commit": git_commit(),
        "command": " ".join(["python", *sys.argv]),
        "seconds_total": round(time.monotonic() - start, 1),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, out, indent=2)


def _train_all(args: argparse.Namespace) -> None:
    """Run every pending ``(variant, seed)``, ``--parallel`` at a time; finished runs are skipped."""
    from isodream_rl.data import load_pusher_dataset

    # Generate / load the cached data set once, before the training processes race for it.
    for split, n in (("train", args.train_sequences), ("test", args.test_sequences)):
        load_pusher_dataset(n, 30, seed=args.data_seed, split=split, workers=2)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    start = time.monotonic()
    pending = [run for run in _runs(args) if _finished(args, *run) is None]
    running: list = []
    while pending or running:
        while pending and len(running) < args.parallel:
            variant, seed = pending.pop(0)
            out = _run_dir(args, variant, seed)
            out.mkdir(parents=True, exist_ok=True)
            log = open(out / "train.log", "a")  # noqa: SIM115 - closed below
            proc = subprocess.Popen(_train_command(args, variant, seed), stdout=log, stderr=log, env=env)
            running.append((variant, seed, proc, log))
        time.sleep(1.0)
        for item in list(running):
            variant, seed, proc, log = item
            if proc.poll() is None:
                continue
            running.remove(item)
            log.close()
            if proc.returncode != 0:
                raise RuntimeError(
                    f"training {variant} seed {seed} failed; see {_run_dir(args, variant, seed)}/train.log"
                )
            print(f"{variant} seed {seed} stopped at {(time.monotonic() - start) / 60:.1f} min", flush=True)


def _collect(args: argparse.Namespace) -> dict:
    variants, curves, history = {}, {}, {}
    for variant, seed in _runs(args):
        result = _finished(args, variant, seed)
        if result is None:
            raise RuntimeError(
                f"{variant} seed {seed} has not trained {args.iterations} iterations yet; run the bench again"
            )
        runs = variants.setdefault(variant, {"seeds": []})["seeds"]
        runs.append(
            {
                "seed": seed,
                **{k: round(nan_if_none(v), 4) for k, v in result["metrics"].items()},  # null: nan
                "iterations": result["iterations"],
                "train_minutes": round(result["train_seconds"] / 60, 2),
            }
        )
        curves.setdefault(variant, {})[f"seed_{seed}"] = result["curves"]
        history.setdefault(variant, {})[f"seed_{seed}"] = result["history"]
    copy_summary, copy_curves = _copy_last_frame(args)
    skip = (
        "json",
        "out_dir",
        "variants",
        "speed",
        "speed_repeats",
        "frames",
        "seed",
        "collect_only",
        "paper_scale",
    )
    config = {k: v for k, v in vars(args).items() if k not in skip}
    config.update(
        dataset="pusher (local BAIR-like, 64x64) + 3 bouncing balls (fixed on test)",
        train="2 -> 10 frames",
        test="2 -> 28 frames, one clip per test sequence",
        validation=f"the first {args.val_batches} test batches, every {args.val_every} iterations",
        threads_per_process=1,
    )
    return {
        "variants": variants,
        "copy_last_frame": copy_summary,
        "aims": _aims(variants, copy_summary),
        "config": config,
        "curves": {**curves, "copy_last_frame": copy_curves},
        "history": history,
        "cpu": cpu_name(),
        "cpu_native_bf16": _native_bf16(),
        "commit": git_commit(),
        "command": " ".join(["python", *sys.argv]),
    }


def main() -> int:
    args = _parse()
    if args.speed:
        _write_speed(args)
        return 0
    if args.paper_scale:
        _write_paper_scale(args)
        return 0
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if not args.collect_only:
        _train_all(args)
    out = _collect(args)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, out, indent=2)
    table = _table(out["variants"], out["copy_last_frame"])
    args.json.with_suffix(".md").write_text(table)

    from isodream_rl.video_prediction.showcase import save_metric_curves, save_showcase, showcase_rows
    from isodream_rl.video_prediction.trainer import build_split, load_checkpoint

    first = f"seed_{args.seeds[0]}"
    save_metric_curves(
        args.json.with_name(args.json.stem + "_curves.png"),
        {name: runs[first] if name != "copy_last_frame" else runs for name, runs in out["curves"].items()},
    )
    _save_validation_curves(args.json.with_name(args.json.stem + "_validation.png"), out["history"])
    if "isodream" in out["variants"]:
        model, config_, _ = load_checkpoint(_run_dir(args, "isodream", args.seeds[0]))
        clip = build_split(config_, "test")[0]
        rows = showcase_rows(model, clip["frames"], clip["actions"], context=config_.context)
        save_showcase(args.json.with_name(args.json.stem + "_showcase.png"), rows)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
