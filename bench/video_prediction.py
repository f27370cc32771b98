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

Each variant trains in its own process (``isodream-video train``) with one torch thread; ``--parallel``
of them run at a time (the full model and ``no_action_free`` first, so the comparison that matters
sees the same machine load). Each stops at ``--iterations`` or ``--max-minutes``, whichever comes first.
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
    p.add_argument("--speed-repeats", type=int, default=8, help="timed iterations per path and variant")
    p.add_argument("--frames", type=int, default=12, help="frames per training clip (--speed only)")
    p.add_argument("--out-dir", type=Path, default=Path("runs/bench_video"))
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--max-minutes", type=float, default=18.0)
    p.add_argument("--parallel", type=int, default=2)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--hidden-channels", type=int, default=32)
    p.add_argument("--kernel-size", type=int, default=3)
    p.add_argument("--encoder-channels", type=int, nargs=2, default=[16, 32])
    p.add_argument("--action-embedding", type=int, default=32)
    p.add_argument("--train-sequences", type=int, default=1000)
    p.add_argument("--test-sequences", type=int, default=128)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--precision",
        choices=("fp32", "bf16"),
        default="bf16" if _native_bf16() else "fp32",
        help="training precision; default bf16 where the CPU has native bf16 (1.55x per iteration on an "
        "avx512_bf16 CPU, docs/results/video_prediction_speed.json), else fp32",
    )
    args = p.parse_args()
    if args.json is None:
        args.json = Path("video_prediction_speed.json" if args.speed else "video_prediction.json")
    return args


def _train_command(args: argparse.Namespace, variant: str) -> list[str]:
    out = args.out_dir / variant
    return [
        sys.executable, "-m", "isodream_rl.video_prediction.cli", "train",
        "--variant", variant,
        "--iterations", str(args.iterations),
        "--max-minutes", str(args.max_minutes),
        "--eval-every", str(10**9),
        "--batch-size", str(args.batch_size),
        "--lr", str(args.lr),
        "--hidden-channels", str(args.hidden_channels),
        "--kernel-size", str(args.kernel_size),
        "--encoder-channels", *map(str, args.encoder_channels),
        "--action-embedding", str(args.action_embedding),
        "--train-sequences", str(args.train_sequences),
        "--test-sequences", str(args.test_sequences),
        "--seed", str(args.seed),
        "--precision", args.precision,
        "--threads", "1",
        "--out-dir", str(out),
        "--result-json", str(out / "result.json"),
        "--no-progress",
    ]  # fmt: skip


def _table(variants: dict) -> str:
    lines = [
        "| variant | iterations | PSNR 10 | SSIM 10 | PSNR 28 | SSIM 28 | PSNR 28 (uint8) | SSIM 28 (uint8) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, v in variants.items():
        lines.append(
            f"| {name} | {v['iterations']} | {v['psnr_10']:.2f} | {v['ssim_10']:.3f} | {v['psnr_28']:.2f} | "
            f"{v['ssim_28']:.3f} | {v['psnr_uint8_28']:.2f} | {v['ssim_uint8_28']:.3f} |"
        )
    return "\n".join(lines) + "\n"


def _copy_last_frame(args: argparse.Namespace) -> dict[str, float]:
    """Scores of repeating the last observed frame: the floor every variant should clear."""
    from isodream_rl.video_prediction.metrics import FrameMetrics
    from isodream_rl.video_prediction.trainer import TrainConfig, build_split

    config = TrainConfig(
        seed=args.seed, test_sequences=args.test_sequences, train_sequences=args.train_sequences
    )
    metrics = FrameMetrics()
    for clip in build_split(config, "test"):
        frames = clip["frames"][None]
        last = frames[:, config.context - 1 : config.context]
        metrics.update(last.expand_as(frames[:, config.context :]), frames[:, config.context :])
    summary = FrameMetrics.summarize(metrics.compute(), config.horizons)
    return {k: round(v, 4) for k, v in summary.items()}


def _speed(args: argparse.Namespace) -> dict:
    """Iterations per second of each of :data:`SPEED_PATHS` per variant, timed round-robin in this process."""
    import torch
    from tensordict import TensorDict
    from torch.utils.flop_counter import FlopCounterMode

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
    generator = torch.Generator().manual_seed(args.seed)
    # Random clips of the training shape: the model's cost does not depend on the pixels.
    batch = TensorDict(
        {
            "frames": torch.rand(args.batch_size, args.frames, 3, 64, 64, generator=generator),
            "actions": torch.randn(args.batch_size, args.frames, 4, generator=generator),
        },
        batch_size=[args.batch_size],
    )
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
        with FlopCounterMode(display=False) as counter:
            sum(runs["plain"][1](batch).values()).backward()
        gflop = counter.get_total_flops() / 1e9
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


def _write_speed(args: argparse.Namespace) -> None:
    start = time.monotonic()
    results = _speed(args)
    committed = Path(__file__).resolve().parents[1] / "docs" / "results" / "video_prediction.json"
    reference = {}
    if committed.exists():
        # The committed bench's training rate (two variants at a time on a loaded machine): context only,
        # since it was not measured side by side with the paths above.
        for name, v in json.loads(committed.read_text())["variants"].items():
            reference[name] = round(v["iterations"] / v["train_minutes"], 2)
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
    args.json.write_text(json.dumps(out, indent=2) + "\n")


def main() -> int:
    args = _parse()
    if args.speed:
        _write_speed(args)
        return 0
    args.out_dir.mkdir(parents=True, exist_ok=True)
    # Generate / load the cached data set once, before the training processes race for it.
    from isodream_rl.data import load_pusher_dataset

    for split, n in (("train", args.train_sequences), ("test", args.test_sequences)):
        load_pusher_dataset(n, 30, seed=args.seed, split=split, workers=2)

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    start = time.monotonic()
    pending = list(args.variants)
    for i in range(0, len(pending), args.parallel):
        group = pending[i : i + args.parallel]
        procs = []
        for variant in group:
            (args.out_dir / variant).mkdir(parents=True, exist_ok=True)
            log = open(args.out_dir / variant / "train.log", "w")  # noqa: SIM115 - closed below
            procs.append(
                (
                    variant,
                    subprocess.Popen(_train_command(args, variant), stdout=log, stderr=log, env=env),
                    log,
                )
            )
        for variant, proc, log in procs:
            if proc.wait() != 0:
                raise RuntimeError(f"training {variant} failed; see {args.out_dir / variant / 'train.log'}")
            log.close()
            print(f"{variant} done at {(time.monotonic() - start) / 60:.1f} min", flush=True)

    variants, curves = {}, {}
    for variant in args.variants:
        result = json.loads((args.out_dir / variant / "result.json").read_text())
        variants[variant] = {
            **{k: round(v, 4) for k, v in result["metrics"].items()},
            "iterations": result["iterations"],
            "train_minutes": round(result["train_seconds"] / 60, 2),
        }
        curves[variant] = result["curves"]
    skip = ("json", "out_dir", "variants", "speed", "speed_repeats", "frames")
    config = {k: v for k, v in vars(args).items() if k not in skip}
    config.update(
        dataset="pusher (local BAIR-like, 64x64) + 3 bouncing balls (fixed on test)",
        train="2 -> 10 frames",
        test="2 -> 28 frames, one clip per test sequence",
        threads_per_process=1,
        total_minutes=round((time.monotonic() - start) / 60, 2),
    )
    config["copy_last_frame"] = _copy_last_frame(args)
    if "isodream" in variants and "no_action_free" in variants:
        gap = variants["isodream"]["psnr_28"] - variants["no_action_free"]["psnr_28"]
        config["psnr_28_gain_over_no_action_free"] = round(gap, 3)
    out = {"variants": variants, "config": config, "curves": curves}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2))
    args.json.with_suffix(".md").write_text(_table(variants))

    from isodream_rl.video_prediction.showcase import save_metric_curves, save_showcase, showcase_rows
    from isodream_rl.video_prediction.trainer import build_split, load_checkpoint

    save_metric_curves(args.json.with_name(args.json.stem + "_curves.png"), curves)
    if "isodream" in variants:
        model, config_, _ = load_checkpoint(args.out_dir / "isodream" / "checkpoint.pt")
        clip = build_split(config_, "test")[0]
        rows = showcase_rows(model, clip["frames"], clip["actions"], context=config_.context)
        save_showcase(args.json.with_name(args.json.stem + "_showcase.png"), rows)
    print(_table(variants))
    return 0


if __name__ == "__main__":
    sys.exit(main())
