"""Train every video-prediction variant on the local BAIR-like pusher set with bouncing balls, at CPU
scale, and evaluate them on the fixed test split (2 -> 28 frames).

Writes the JSON (``--json``), and next to it a markdown table (``.md``), the per-frame curves
(``_curves.png``) and a Figure-6-style showcase of the full model (``_showcase.png``).

    python bench/video_prediction.py --json docs/results/video_prediction.json

Each variant trains in its own process (``isodream-video train``) with one torch thread; ``--parallel``
of them run at a time (the full model and ``no_action_free`` first, so the comparison that matters
sees the same machine load). Each stops at ``--iterations`` or ``--max-minutes``, whichever comes first.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

VARIANTS = ("isodream", "no_action_free", "no_inverse", "predrnn")


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", type=Path, default=Path("video_prediction.json"))
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
    return p.parse_args()


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


def main() -> int:
    args = _parse()
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
    config = {k: v for k, v in vars(args).items() if k not in ("json", "out_dir", "variants")}
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
