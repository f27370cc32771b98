"""``isodream-video train|eval``: train a video-prediction variant, or evaluate a checkpoint.

Examples::

    isodream-video train --variant isodream --iterations 80000 --out-dir runs/isodream
    isodream-video train --variant isodream --iterations 80000 --out-dir runs/isodream --resume
    isodream-video train --variant isodream --iterations 1000 --out-dir runs/isodream --overwrite
    isodream-video train --dataset bair --data-path /data/softmotion30_44k --variant no_action_free
    isodream-video eval --checkpoint runs/isodream --json eval.json --showcase fig.png
    isodream-video eval --checkpoint runs/isodream/checkpoints/step_00080000 --dataset robonet --data-path /data/robonet_hdf5 \\
        --test-frames 20 --sequence-length 20 --horizons 10 18
"""

from __future__ import annotations

import argparse
import sys
import typing
from dataclasses import MISSING, fields, replace
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from isodream_rl.run_utils.disk_space import DiskFullError
from isodream_rl.run_utils.json_io import dumps_json, write_json
from isodream_rl.run_utils.run_lock import RunDirBusyError
from isodream_rl.user_errors import exit_stopped, report_user_errors, take_debug_flag
from isodream_rl.video_prediction.metrics import FrameMetrics
from isodream_rl.video_prediction.trainer import (
    VideoTrainConfig,
    build_split,
    evaluate,
    load_checkpoint,
    train,
)

__all__ = ["main"]

_EVAL_OVERRIDES = (
    "dataset",
    "data_path",
    "cache_dir",
    "test_sequences",
    "sequence_length",
    "test_frames",
    "horizons",
    "balls",
    "batch_size",
    "eval_batches",
    "threads",
    "device",
)


def _add_config_arguments(parser: argparse.ArgumentParser, names: typing.Iterable[str] | None = None) -> None:
    hints = typing.get_type_hints(VideoTrainConfig)
    for f in fields(VideoTrainConfig):
        if names is not None and f.name not in names:
            continue
        flag = "--" + f.name.replace("_", "-")
        default = f.default if f.default is not MISSING else f.default_factory()
        hint = hints[f.name]
        help_text = f"default: {default}"
        if hint is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        elif typing.get_origin(hint) is tuple:
            parser.add_argument(flag, type=int, nargs="+", default=None, help=help_text)
        else:
            base = [a for a in typing.get_args(hint) if a is not type(None)] or [hint]
            parser.add_argument(flag, type=base[0], default=None, help=help_text)


def _overrides(args: argparse.Namespace, names: typing.Iterable[str]) -> dict:
    return {n: getattr(args, n) for n in names if getattr(args, n, None) is not None}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="isodream-video", description=__doc__.split("\n")[0])
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)
    train_p = sub.add_parser("train", help="train one variant (see VideoTrainConfig for every option)")
    _add_config_arguments(train_p)
    train_p.add_argument("--result-json", type=Path, help="write iterations, metrics and curves here")
    train_p.add_argument("--no-progress", action="store_true", help="disable the tqdm bar")
    train_p.add_argument(
        "--resume",
        action="store_true",
        help="continue from the newest checkpoint of <out-dir> if it has one (same settings; --iterations may "
        "grow)",
    )
    train_p.add_argument(
        "--overwrite",
        action="store_true",
        help="delete the run already in --out-dir (checkpoints/, logs/) first",
    )
    eval_p = sub.add_parser("eval", help="evaluate a checkpoint on the test split (per-frame PSNR/SSIM)")
    eval_p.add_argument(
        "--checkpoint",
        type=Path,
        required=True,
        help="a train run's --out-dir (its newest readable checkpoint) or one of its checkpoints/step_* folders",
    )
    _add_config_arguments(eval_p, _EVAL_OVERRIDES)
    eval_p.add_argument("--json", type=Path, help="write the summary and the per-frame curves here")
    eval_p.add_argument("--showcase", type=Path, help="write a Figure-6-style PNG of the first test clip")
    eval_p.add_argument("--curves", type=Path, help="write a PNG of PSNR/SSIM per predicted frame")
    return parser


def _train(args: argparse.Namespace) -> dict:
    config = VideoTrainConfig.from_dict(_overrides(args, [f.name for f in fields(VideoTrainConfig)]))
    result = train(config, progress=not args.no_progress, resume=args.resume, overwrite=args.overwrite)
    if "stopped_by_signal" in result:  # no result to write: the run continues with --resume
        return result
    result["config"] = {k: v for k, v in vars(config).items()}
    if args.result_json is not None:
        write_json(args.result_json, result, indent=2, default=list)
    return result


def _eval(args: argparse.Namespace) -> dict:
    if not args.checkpoint.exists():
        raise FileNotFoundError(
            f"--checkpoint {args.checkpoint}: no such folder (give the --out-dir of an isodream-video train run)"
        )
    # read onto the CPU, the model built where it evaluates: a GPU run evaluates on a CPU-only machine
    model, config, _ = load_checkpoint(args.checkpoint, device=args.device or "cpu")
    config = replace(config, **_overrides(args, _EVAL_OVERRIDES))
    config.__post_init__()
    torch.set_num_threads(config.threads)
    test_set = build_split(config, "test")
    loader = DataLoader(test_set, batch_size=config.batch_size)
    curves = evaluate(
        model, loader, context=config.context, device=config.device, max_batches=config.eval_batches
    )
    result = {
        "metrics": FrameMetrics.summarize(curves, config.horizons),
        "curves": {k: [round(float(x), 5) for x in v] for k, v in curves.items()},
    }
    if args.json is not None:
        write_json(args.json, result, indent=2)
    if args.showcase is not None:
        from isodream_rl.video_prediction.showcase import save_showcase, showcase_rows

        clip = test_set[0]
        save_showcase(
            args.showcase, showcase_rows(model, clip["frames"], clip["actions"], context=config.context)
        )
    if args.curves is not None:
        from isodream_rl.video_prediction.showcase import save_metric_curves

        save_metric_curves(args.curves, {config.variant: result["curves"]})
    return result


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``isodream-video``. A user error (a missing path, an invalid option, a file that is not a
    checkpoint, an --out-dir holding another run or used by another process) is one line on stderr and exit
    status 2; ``--debug`` shows the traceback. A training run that SIGINT or SIGTERM stopped writes a checkpoint
    and says ``stopped at N iterations by SIGINT (checkpoint ...); continue with --resume``, with exit status 130
    or 143."""
    args = _parser().parse_args(argv)
    take_debug_flag(["--debug"] if args.debug else [])
    with report_user_errors(
        "isodream-video", (FileNotFoundError, KeyError, ValueError, RunDirBusyError, DiskFullError)
    ):
        result = _train(args) if args.command == "train" else _eval(args)
    if "stopped_by_signal" in result:
        exit_stopped(
            "isodream-video",
            at=f"{result['iterations']} iterations",
            signum=result["stopped_by_signal"],
            checkpoint=result["checkpoint"],
            resume="--resume",
        )
    print(dumps_json(result["metrics"], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
