"""Does every algorithm train, evaluate and resume with ``train.device=cuda``, and what does a GPU buy: one script
for any CUDA machine, one JSON.

Parts (``--parts``, all by default, in this order); each check runs under its own time limit (``--timeout``), its
outcome is recorded (a failure as the last lines of its error) and the JSON is written again after it, so that a
hang or a crash costs one check, not the rest:

* ``runs``: for every algorithm ``isodream-train algo=<name>`` runs (registered in
  :data:`~isodream_rl.trainers.registry.ALGORITHMS` and with an ``algo`` config file), a tiny ``mode=rl`` run on
  sprites on the GPU with an evaluation (episodes, and the open-loop GIF where the algorithm has an Iso-Dream world
  model), a final evaluation and checkpoints, continued (``resume=true``) on the GPU and evaluated on the GPU
  (``isodream-eval --device cuda``); and a tiny ``mode=world_model`` run on the GPU (branch pictures, latent probe)
  continued on the GPU, for each algorithm that has that mode.
* ``cpu_only`` (with ``runs``): every run above evaluated (``isodream-eval``, rl runs) and continued on the CPU in a process that
  sees no GPU (``CUDA_VISIBLE_DEVICES=""``: a GPU run's checkpoints on a CPU-only machine), then continued on the
  GPU again (a CPU run's checkpoints on a GPU).
* ``decomposition``: ``bench/decomposition.py`` on sprites at a tiny size with ``train.device=cuda``.
* ``video``: ``isodream-video train`` on the GPU on a tiny generated BAIR-format set, continued (``--resume``),
  then ``eval`` on the GPU (with the showcase picture) and on the CPU.
* ``update``: one update of every algorithm at each of ``--sizes`` (``bench`` and ``paper``), the sample on the
  GPU, timed between ``torch.cuda.synchronize`` calls, median of ``--rounds`` (``bench/update_speed.py``'s
  ``measure``, as ``python bench/update_speed.py --device cuda`` times them).
* ``end_to_end``: updates per second of a run on the GPU (``--e2e-size``, ``bench``), collection included, for each
  of ``--e2e-algos`` (``bench/update_rate.py``'s ``measure``, ``train.device=cuda`` added to its overrides).

Writes ``--json`` (default ``docs/results/gpu_check.json``): ``gpu``, ``torch``, ``cuda``, ``commit``, ``cpu``,
``command``; ``checks`` (per check, ``rl/<algo>``, ``world_model/<algo>``, ``cpu_only``, ...: ``ok``, ``seconds``
and what it found, or ``error``); ``update`` (per size and algorithm, the entries of ``bench/update_speed.py``'s
``algos``); ``end_to_end`` (per algorithm, an entry of ``bench/update_rate.py``'s ``rates``) and ``ok`` (every
check passed). Its exit status is 1 when a check failed; without a usable CUDA GPU it stops at once, in one line.

    PYTHONPATH=. MUJOCO_GL=egl python bench/gpu_check.py
    PYTHONPATH=. python bench/gpu_check.py --parts update --sizes paper --json /tmp/gpu_update.json

A GPU machine whose Python has torch but not the project's other dependencies, and no package registry: download
their wheels where there is one, for the GPU machine's Python and platform (``cp312``, ``manylinux_2_28`` below),
carry them with the project and install them without dependencies there (the project's ``torch==2.13.0`` pin only
matters to pip; it imports and trains on torch 2.11). MuJoCo, dm-control and highway-env are not needed (sprites
needs none of them; the project imports them lazily); torchmetrics is the ``video`` part's (its PSNR/SSIM)::

    pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 \\
        -d wheels torchrl==0.14.1 tensordict==0.14.3 hydra-core==1.3.2 omegaconf==2.3.0 gymnasium==1.4.0 \\
        farama-notifications orjson pyvers==0.2.3 hoptorch importlib_metadata==8.7.0 torchmetrics \\
        lightning-utilities
    pip wheel --no-deps -w wheels antlr4-python3-runtime==4.9.3      # a source distribution only: built here
    # on the GPU machine, in the project's folder:
    pip install --no-deps wheels/*.whl
    PYTHONPATH=. MUJOCO_GL=egl python bench/gpu_check.py
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import decomposition  # noqa: E402
import update_rate  # noqa: E402
import update_speed  # noqa: E402
from common import composed_run_config, device_provenance, provenance  # noqa: E402

import isodream_rl.cli  # noqa: E402, F401  (registers the config schema and the TorchRL baselines)
from isodream_rl.data import write_tiny_bair  # noqa: E402
from isodream_rl.evaluation.latent_probe import probe  # noqa: E402
from isodream_rl.run_utils.json_io import dumps_json, write_json  # noqa: E402
from isodream_rl.trainers import run as run_module  # noqa: E402
from isodream_rl.trainers.config import ConfigError, RunConfig, config_from_dict, validate_config  # noqa: E402
from isodream_rl.trainers.registry import ALGORITHMS  # noqa: E402
from isodream_rl.trainers.run_lifecycle import RunResult  # noqa: E402
from isodream_rl.video_prediction import cli as video_cli  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "isodream_rl" / "configs"
PARTS = ("runs", "cpu_only", "decomposition", "video", "update", "end_to_end")
#: a tiny sprites run of the RL mode: 50 prefill steps, then one batch (10 updates) per 50 env steps, an evaluation
#: (one episode and the open-loop GIF) at 100 env steps, one final evaluation episode
TINY_RL = [
    "env=sprites",
    "size=tiny",
    "train.total_steps=100",
    "logging.eval_every=100",
    "logging.eval_episodes=1",
    "logging.final_eval_episodes=1",
    "logging.progress_bar=false",
]
#: a tiny world-model run: 4 updates of 2 windows x 8 steps on two 16-step episodes, scored (branch picture) every
#: 2 updates and probed on 4 episodes
TINY_WORLD_MODEL = [
    "exp=world_model",
    "size=tiny",
    "world_model.updates=4",
    "world_model.episodes=2",
    "world_model.held_out_episodes=1",
    "world_model.episode_length=16",
    "world_model.probe_episodes=4",
    "train.sequence_length=8",
    "train.batch_size=2",
    "logging.eval_every=2",
    "logging.progress_bar=false",
]
#: a tiny video predictor (``isodream-video train`` flags)
TINY_VIDEO = ["--hidden-channels", "4", "--encoder-channels", "4", "4", "--kernel-size", "3", "--num-layers", "1",
              "--action-embedding", "4", "--batch-size", "2", "--sequence-length", "5", "--train-frames", "4",
              "--test-frames", "5", "--horizons", "2", "3", "--no-progress"]  # fmt: skip


class CheckFailed(AssertionError):
    """A check found something wrong (the message says what)."""


def require(condition: bool, message: str) -> None:
    """Fail the check with ``message`` unless ``condition``."""
    if not condition:
        raise CheckFailed(message)


def registered_algos() -> list[str]:
    """Every algorithm ``isodream-train algo=<name>`` runs: registered (``isodream_rl.cli`` imports the baselines,
    which register themselves) and with an ``algo`` config file."""
    return sorted(name for name in ALGORITHMS if (CONFIGS / "algo" / f"{name}.yaml").exists())


def composed(*overrides: str) -> RunConfig:
    """The ``RunConfig`` of ``isodream-train <overrides>``."""
    return composed_run_config(*overrides)


def continue_run(run_dir: Path, *, device: str, more: int) -> RunResult:
    """Continue the run of ``run_dir`` with its own settings (``resume=true``) on ``device``, ``more`` env steps
    (``mode=rl``) or updates (``mode=world_model``) further."""
    cfg = config_from_dict(json.loads((run_dir / "run_config.json").read_text()))
    cfg.resume, cfg.train.device = True, device
    if cfg.mode == "world_model":
        cfg.world_model.updates += more
    else:
        cfg.train.total_steps += more
    return run_module.train(cfg, probe=probe)


def require_continued(result: RunResult, *, before: RunResult) -> None:
    """The continued run started from a checkpoint and updated further than the run it continued."""
    require(result.resumed_from is not None, f"{result.run_dir} did not resume from a checkpoint")
    require(result.updates > before.updates, f"{result.run_dir} made no update after resuming")


def check_rl(algo: str, folder: Path, *, device: str) -> dict:
    """A tiny ``mode=rl`` run of ``algo`` on ``device`` (updates, evaluation, open-loop GIF where the algorithm has
    an Iso-Dream world model, final evaluation, checkpoints), continued on ``device``, then ``isodream-eval`` on
    ``device``; what it found."""
    run_dir = folder / f"rl_{algo}"
    first = run_module.train(
        composed(*TINY_RL, f"algo={algo}", f"run_dir={run_dir}", f"train.device={device}")
    )
    require(first.updates > 0, "no update ran")
    require("eval_return" in first.metrics, "no evaluation ran")
    require(
        first.summary is not None and first.checkpoint is not None, "no final evaluation or no checkpoint"
    )
    continued = continue_run(run_dir, device=device, more=50)
    require_continued(continued, before=first)
    mean, _, _ = run_module.evaluate_checkpoint(run_dir, episodes=1, device=device)
    return {
        "run_dir": str(run_dir),
        "updates": continued.updates,
        "openloop_gifs": len(list((run_dir / "pictures").glob("openloop_*.gif"))),
        "eval_return": first.metrics["eval_return"],
        "isodream_eval_return": mean,
    }


def check_world_model(algo: str, folder: Path, *, device: str) -> dict:
    """A tiny ``mode=world_model`` run of ``algo`` on ``device`` (branch pictures, latent probe), continued on
    ``device``; skipped (with the reason) for an algorithm the mode refuses."""
    run_dir = folder / f"world_model_{algo}"
    cfg = composed(*TINY_WORLD_MODEL, f"algo={algo}", f"run_dir={run_dir}", f"train.device={device}")
    try:
        validate_config(cfg)
    except ConfigError as err:
        return {"skipped": str(err)}
    first = run_module.train(cfg, probe=probe)
    require(first.summary is not None, "no summary")
    require(any(key.startswith("probe_r2_") for key in first.summary), "no latent probe")
    require(Path(first.summary["png"]).exists(), "no branch picture")
    continued = continue_run(run_dir, device=device, more=2)
    require_continued(continued, before=first)
    return {"run_dir": str(run_dir), "updates": continued.updates, "reco_mse": first.summary.get("reco_mse")}


def evaluate_and_continue_on_cpu(run_dirs: list[Path]) -> dict:
    """What ``--cpu-only`` does, in a process that must see no GPU: each rl run evaluated (``isodream-eval``) and
    every run continued on the CPU."""
    require(
        not torch.cuda.is_available(), "this process sees a GPU: it must run with CUDA_VISIBLE_DEVICES=''"
    )
    found = {}
    for run_dir in run_dirs:
        cfg = config_from_dict(json.loads((run_dir / "run_config.json").read_text()))
        entry = {}
        if cfg.mode == "rl":
            entry["isodream_eval_return"] = run_module.evaluate_checkpoint(run_dir, episodes=1, device="cpu")[
                0
            ]
        result = continue_run(run_dir, device="cpu", more=50 if cfg.mode == "rl" else 2)
        require(result.resumed_from is not None, f"{run_dir} did not resume on the CPU")
        entry["updates"] = result.updates
        found[run_dir.name] = entry
    return found


def check_cpu_only(run_dirs: list[Path], *, device: str, timeout: int) -> dict:
    """The runs of ``run_dirs`` evaluated and continued on the CPU in a process that sees no GPU
    (:func:`evaluate_and_continue_on_cpu`), then continued on ``device`` again; what each run found."""
    env = dict(os.environ, CUDA_VISIBLE_DEVICES="")
    command = [sys.executable, str(Path(__file__).resolve()), "--cpu-only", *map(str, run_dirs)]
    done = subprocess.run(command, env=env, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    require(done.returncode == 0, f"the CPU-only process failed:\n{done.stderr[-3000:]}")
    found = json.loads(done.stdout.strip().splitlines()[-1])
    for run_dir in run_dirs:
        cfg = config_from_dict(json.loads((run_dir / "run_config.json").read_text()))
        result = continue_run(run_dir, device=device, more=50 if cfg.mode == "rl" else 2)
        require(result.updates > found[run_dir.name]["updates"], f"{run_dir}: no update back on {device}")
        found[run_dir.name]["updates_back_on_device"] = result.updates
    return found


def check_decomposition(folder: Path, *, device: str) -> dict:
    """``bench/decomposition.py`` on sprites, both algorithms, one seed, at a tiny size on ``device``; the scores."""
    out = folder / "decomposition" / "decomposition.json"
    overrides = [*decomposition.TINY, f"train.device={device}"]
    args = ["--scenes", "sprites", "--seeds", "0", "--minutes", "5", "--runs", str(folder / "decomposition")]
    results = decomposition.main([*args, "--json", str(out), *(f"--override={o}" for o in overrides)])
    runs = results["scenes"]["sprites"]
    for algo, (run,) in runs.items():
        require(run["updates"] == 2 and run["stopped_by"] == "updates", f"{algo}: {run}")
    return {algo: {"iou_control_vs_agent": run["iou_control_vs_agent"]} for algo, (run,) in runs.items()}


def check_video(folder: Path, *, device: str) -> dict:
    """``isodream-video train`` on ``device`` (2 iterations, then 2 more resumed), ``eval`` on ``device`` with the
    showcase picture and on the CPU; the PSNR at 3 predicted frames of each evaluation."""
    data, out = write_tiny_bair(folder / "bair"), folder / "video"
    train = ["train", "--dataset", "bair", "--data-path", str(data), "--out-dir", str(out), *TINY_VIDEO]
    require(video_cli.main([*train, "--iterations", "2", "--device", device]) == 0, "training failed")
    require(video_cli.main([*train, "--iterations", "4", "--device", device, "--resume"]) == 0, "no resume")
    psnr = {}
    for where in dict.fromkeys((device, "cpu")):
        summary, showcase = folder / f"video_eval_{where}.json", folder / f"video_showcase_{where}.png"
        evaluation = ["eval", "--checkpoint", str(out), "--horizons", "3", "--no-balls", "--device", where]
        require(
            video_cli.main([*evaluation, "--json", str(summary), "--showcase", str(showcase)]) == 0, where
        )
        require(showcase.stat().st_size > 0, f"no showcase picture on {where}")
        psnr[where] = json.loads(summary.read_text())["metrics"]["psnr_3"]
    return {"psnr_3": psnr}


@contextlib.contextmanager
def time_limit(seconds: int):
    """Raise ``TimeoutError`` in this (main) thread once ``seconds`` have passed; a subprocess waited for is
    killed by ``subprocess.run`` as the error passes."""

    def expire(signum, frame):
        raise TimeoutError(f"over its time limit of {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def error_text(err: BaseException) -> str:
    """The last lines of ``err``'s traceback, and of a failed subprocess's stderr."""
    text = "".join(traceback.format_exception(err))[-2500:]
    stderr = getattr(err, "stderr", None)
    return text + (f"\nstderr:\n{stderr[-2500:]}" if stderr else "")


class Report:
    """The JSON of a check session, written again after every check.

    Args:
        path: where it is written.
        header: what it records first (the machine, the versions, the command).
    """

    def __init__(self, path: Path, header: dict) -> None:
        self.path = path
        self.result = {**header, "checks": {}, "update": {}, "end_to_end": {}, "ok": True}

    def run(self, section: str, name: str, check: Callable[[], dict], *, timeout: int) -> dict | None:
        """Run ``check`` for at most ``timeout`` seconds and write the JSON: its outcome (``ok``, ``seconds``, and
        ``error`` after a failure) under ``checks`` (as ``name`` in section ``checks``, ``<section>/<name>`` in the
        others), what it returns beside the outcome (``checks``) or under ``<section>[name]``.

        Returns:
            what ``check`` returned, ``None`` after a failure.
        """
        started = time.perf_counter()
        try:
            with time_limit(timeout):
                found = check()
            outcome = {"ok": True}
            print(f"ok {section}/{name}", flush=True)
        except Exception as err:
            found, outcome = None, {"ok": False, "error": error_text(err)}
            self.result["ok"] = False
            print(f"FAILED {section}/{name}: {type(err).__name__}: {err}", flush=True)
        outcome["seconds"] = round(time.perf_counter() - started, 1)
        if section == "checks":
            self.result["checks"][name] = {**outcome, **(found or {})}
        else:
            self.result["checks"][f"{section}/{name}"] = outcome
            if found is not None:
                self.result[section][name] = found
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, self.result, indent=2, default=str)
        return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", type=lambda s: s.split(","), default=list(PARTS), help=", ".join(PARTS))
    parser.add_argument(
        "--algos", type=lambda s: s.split(","), default=None, help="default: every registered"
    )
    parser.add_argument("--sizes", type=lambda s: s.split(","), default=["bench", "paper"])
    parser.add_argument("--rounds", type=int, default=8, help="timed updates per algorithm and size")
    parser.add_argument("--warmup", type=int, default=2, help="untimed updates per algorithm and size first")
    parser.add_argument(
        "--e2e-algos", type=lambda s: s.split(","), default=list(update_speed.ALGOS), help="end_to_end's"
    )
    parser.add_argument("--e2e-size", default="bench", help="the size group of the end-to-end runs")
    parser.add_argument("--e2e-updates", type=int, default=100, help="updates of each end-to-end run")
    parser.add_argument("--timeout", type=int, default=300, help="seconds each check may take")
    parser.add_argument(
        "--work", type=Path, default=None, help="folder of the runs (default: a temporary one)"
    )
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "results" / "gpu_check.json")
    parser.add_argument(
        "--cpu-only", nargs="+", type=Path, default=None, metavar="RUN_DIR", help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.cpu_only:  # the script's own child process of the cpu_only part (CUDA_VISIBLE_DEVICES="")
        print(dumps_json(evaluate_and_continue_on_cpu(args.cpu_only)))
        return 0
    if not torch.cuda.is_available():
        raise SystemExit(
            f"bench/gpu_check.py needs a CUDA GPU: torch {torch.__version__} sees none here "
            f"(torch.cuda.is_available() is False; CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES')!r})"
        )
    unknown = sorted(set(args.parts) - set(PARTS))
    if unknown:
        parser.error(f"unknown --parts {unknown}; valid: {list(PARTS)}")
    if "cpu_only" in args.parts and "runs" not in args.parts:
        parser.error("--parts cpu_only continues the runs of the runs part: give both")
    algos = args.algos or registered_algos()
    device = "cuda"
    report = Report(
        args.json,
        {**provenance("gpu_check.py", argv, parallel=1), **device_provenance(device), "algos": algos},
    )
    with contextlib.ExitStack() as stack:
        work = args.work or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="gpu_check_")))
        run_dirs = []
        if "runs" in args.parts:
            for algo in algos:
                for mode, check in (("rl", check_rl), ("world_model", check_world_model)):
                    found = report.run(
                        "checks",
                        f"{mode}/{algo}",
                        lambda check=check, algo=algo: check(algo, work, device=device),
                        timeout=args.timeout,
                    )
                    if found is not None and "run_dir" in found:
                        run_dirs.append(Path(found["run_dir"]))
        if "cpu_only" in args.parts and run_dirs:
            report.run(
                "checks",
                "cpu_only",
                lambda: check_cpu_only(run_dirs, device=device, timeout=args.timeout),
                timeout=args.timeout + 60 * len(run_dirs),
            )
        if "decomposition" in args.parts:
            report.run(
                "checks",
                "decomposition",
                lambda: check_decomposition(work, device=device),
                timeout=args.timeout,
            )
        if "video" in args.parts:
            report.run("checks", "video", lambda: check_video(work, device=device), timeout=args.timeout)
        if "update" in args.parts:
            for size in args.sizes:
                report.run(
                    "update",
                    size,
                    lambda size=size: update_speed.measure(
                        algos,
                        size=size,
                        device=device,
                        rounds=args.rounds,
                        warmup=args.warmup,
                        scratch=work / f"update_{size}",
                    ),
                    timeout=args.timeout,
                )
        if "end_to_end" in args.parts:
            rate_args = argparse.Namespace(
                updates=args.e2e_updates,
                log_every=100,
                override=[*update_rate.RUNG1, f"train.device={device}"],
            )
            for algo in args.e2e_algos:
                report.run(
                    "end_to_end",
                    algo,
                    lambda algo=algo: update_rate.measure(algo, args.e2e_size, rate_args),
                    timeout=args.timeout,
                )
    for size, entries in report.result["update"].items():
        for algo, entry in entries.items():
            print(f"update {size} {algo}: {entry['median_wall_s']:.3f} s ({entry['updates_per_s']:.2f}/s)")
    for algo, entry in report.result["end_to_end"].items():
        print(f"end to end {algo}: {entry['updates_per_s']:.2f} updates/s")
    print(f"{'all checks passed' if report.result['ok'] else 'some checks FAILED'}: {args.json}")
    return 0 if report.result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
