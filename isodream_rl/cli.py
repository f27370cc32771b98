"""Console entry points: ``isodream-train`` (Hydra overrides), ``isodream-eval`` (a checkpoint's returns) and the
latent probe of a world-model run.

Examples::

    isodream-train                                   # sprites, small size, Iso-Dream
    isodream-train env=highway size=tiny algo=dreamerv2 train.total_steps=500
    isodream-train env=dmc_walker_walk size=paper run_dir=runs/walker
    isodream-train run_dir=runs/walker resume=true   # continue after a crash or Ctrl-C
    isodream-train exp=world_model                   # the world model alone (isodream-demo)
    isodream-eval runs/walker --episodes 10 --video walker.gif

A user error is one line on stderr and exit status 2; ``--debug`` (or ``HYDRA_FULL_ERROR=1``) shows the
traceback (``isodream_rl/user_errors.py``). A run stopped by Ctrl-C (SIGINT) or SIGTERM writes a checkpoint, says
in one line where it stopped and exits with status 130 or 143: continue it with ``resume=true``.

``python -m isodream_rl.cli ...`` runs ``isodream-train``; ``python -m isodream_rl.cli eval ...`` runs
``isodream-eval``; ``python -m isodream_rl.cli probe RUN_DIR [--encoder]`` runs :func:`probe_run`.
"""

from __future__ import annotations

import argparse
import sys

from isodream_rl.process_settings import use_huge_pages

# before torch is imported: PyTorch reads it at its first allocation
use_huge_pages()

import hydra  # noqa: E402
from hydra.core.config_store import ConfigStore  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

import isodream_rl.baselines  # noqa: E402, F401  (registers algo=torchrl_dreamer and torchrl_dreamer_v3)
from isodream_rl.cli_overrides import check_overrides, free_form_overrides  # noqa: E402
from isodream_rl.configs import register_dmc_envs, register_resolvers  # noqa: E402
from isodream_rl.envs.finite import NonFiniteEnvDataError  # noqa: E402
from isodream_rl.evaluation.latent_probe import probe  # noqa: E402
from isodream_rl.run_utils.checkpoint import CheckpointError  # noqa: E402
from isodream_rl.run_utils.disk_space import DiskFullError  # noqa: E402
from isodream_rl.run_utils.json_io import dumps_json  # noqa: E402
from isodream_rl.run_utils.run_lock import RunDirBusyError  # noqa: E402
from isodream_rl.trainers import run as run_module  # noqa: E402
from isodream_rl.trainers.config import ConfigError, RunConfig  # noqa: E402
from isodream_rl.trainers.run_lifecycle import RunResult  # noqa: E402
from isodream_rl.trainers.stepper import NonFiniteLossError  # noqa: E402
from isodream_rl.trainers.world_model_run import load_world_model, probe_scene  # noqa: E402
from isodream_rl.user_errors import exit_stopped, log_to_stderr, report_user_errors, take_debug_flag  # noqa: E402

ConfigStore.instance().store(name="run_schema", node=RunConfig)
register_dmc_envs()  # env=dmc_<domain>_<task> for every dm_control suite task
register_resolvers()  # ${learner_value:...} of the exp files


def _summary(result: RunResult) -> str:
    lines = [
        f"run finished: {result.env_steps} env steps, {result.updates} updates"
        + (f" (resumed from {result.resumed_from})" if result.resumed_from else ""),
        f"  logs:        {result.logs}",
        f"  checkpoint:  {result.checkpoint}",
        f"  pictures:    {result.pictures}",
    ]
    gifs = sorted(result.pictures.glob("openloop_*.gif")) if result.pictures.is_dir() else []
    if gifs:
        lines.append(f"  newest open-loop prediction: {gifs[-1]}")
    if result.summary is not None:
        lines.append(f"  summary:     {result.run_dir / 'summary.json'}")
    for key in ("episode_return", "eval_return", "loss_model_reco", "env_steps_per_s", "updates_per_s"):
        if key in result.metrics:
            lines.append(f"  {key}: {result.metrics[key]:.4g}")
    isolation = (result.summary or {}).get("isolation") or {}
    if isolation.get("message"):
        lines.append(f"  warning: {isolation['message']}")
    return "\n".join(lines)


#: what isodream-train reports in one line (see isodream_rl/user_errors.py)
TRAIN_ERRORS = (
    ConfigError,
    CheckpointError,
    NonFiniteLossError,
    NonFiniteEnvDataError,
    RunDirBusyError,
    DiskFullError,
)


@hydra.main(version_base="1.3", config_path="configs", config_name="config")
def _train_main(dict_cfg: DictConfig) -> None:
    log_to_stderr()
    with report_user_errors("isodream-train", TRAIN_ERRORS):
        cfg: RunConfig = OmegaConf.to_object(dict_cfg)
        # the algorithm is the registered one of cfg.algo.name (isodream_rl.trainers.registry); a world-model run
        # on sprites ends with the latent probe
        result = run_module.train(cfg, probe=probe)
    if result.stopped_by_signal is not None:
        at = f"{result.updates} updates" if cfg.mode == "world_model" else f"{result.env_steps} env steps"
        exit_stopped(
            "isodream-train",
            at=at,
            signum=result.stopped_by_signal,
            checkpoint=result.checkpoint,
            resume="resume=true",
        )
    print(_summary(result))


def train() -> None:
    """``isodream-train [hydra overrides] [--debug]``: train or resume a run (see ``isodream-train --help``).

    A user error (invalid setting or group option, a run_dir holding another run or used by another process, a
    resume with other settings, no readable checkpoint, a full disk, NaN/inf in the env's frames or rewards) is
    one line on stderr and exit status 2; ``--debug`` (or ``HYDRA_FULL_ERROR=1``) shows the traceback. A run that
    SIGINT or SIGTERM stopped after its checkpoint is one line too, ``stopped at N env steps by SIGINT
    (checkpoint ...); continue with resume=true`` (``N updates`` in ``mode=world_model``), and exit status 130
    or 143.
    """
    sys.argv = take_debug_flag(sys.argv)
    sys.argv[1:] = free_form_overrides(sys.argv[1:])
    with report_user_errors("isodream-train", (ConfigError,)):
        check_overrides(sys.argv[1:])
    _train_main()


def evaluate(argv: list[str] | None = None) -> None:
    """``isodream-eval RUN_DIR [--episodes N] [--video PATH] [--seed S] [--device D]``: mean +- std return of a
    checkpoint.

    Returns ``None`` (a console-script return value becomes the exit status).
    """
    parser = argparse.ArgumentParser(
        prog="isodream-eval", description="Evaluate the newest readable checkpoint of a run (mode actions)."
    )
    parser.add_argument("run_dir", help="the run folder given to isodream-train (holds checkpoints/)")
    parser.add_argument("--episodes", type=int, default=5, help="episodes to run (default 5)")
    parser.add_argument("--video", default=None, help="write the first episode as a GIF here")
    parser.add_argument("--seed", type=int, default=0, help="env and policy seed (default 0)")
    parser.add_argument(
        "--device", default="cpu", help="where the policy acts (default cpu, whichever device trained it)"
    )
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    args = parser.parse_args(argv)
    take_debug_flag(["--debug"] if args.debug else [])
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    with report_user_errors(
        "isodream-eval", (CheckpointError, ConfigError, FileNotFoundError, NonFiniteEnvDataError)
    ):
        mean, std, returns = run_module.evaluate_checkpoint(
            args.run_dir, episodes=args.episodes, video=args.video, seed=args.seed, device=args.device
        )
    print(f"return over {len(returns)} episodes: {mean:.2f} +- {std:.2f}")
    if args.video:
        print(f"video: {args.video}")


def probe_run(argv: list[str] | None = None) -> dict[str, float]:
    """``python -m isodream_rl.cli probe RUN_DIR [--encoder] [--episodes N] [--window T] [--json PATH]``: the
    latent probe (:func:`isodream_rl.evaluation.latent_probe.probe`) of a world-model checkpoint, on sprites
    episodes made like the run's from seeds it never trains on.

    Returns:
        The held-out R^2 per branch and sprite (``r2_<branch>_<sprite>``), also printed as JSON.
    """
    parser = argparse.ArgumentParser(
        prog="python -m isodream_rl.cli probe",
        description="Which sprites can be read off each branch's latent state of a world-model run.",
    )
    parser.add_argument(
        "checkpoint",
        help="a run folder of isodream-train on sprites (its newest readable checkpoint) or one of its "
        "checkpoints/step_* folders",
    )
    parser.add_argument("--episodes", type=int, default=32, help="probe episodes (half fit, half score)")
    parser.add_argument("--window", type=int, default=None, help="default: the run's train.sequence_length")
    parser.add_argument(
        "--encoder",
        action="store_true",
        help="also probe the encoder's shared trunk and branch embeddings (r2_trunk_*, r2_embed_*)",
    )
    parser.add_argument("--json", default=None, help="also write the scores here")
    args = parser.parse_args(argv)
    model, cfg = load_world_model(args.checkpoint)
    scene = probe_scene(cfg, window=args.window)
    scores = probe(model, episodes=args.episodes, seed=cfg.train.seed + 1000, encoder=args.encoder, **scene)
    text = dumps_json({k: round(v, 3) for k, v in scores.items()}, indent=2)  # an absent score: null
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")
    return scores


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "eval":
        evaluate(sys.argv[2:])
    elif len(sys.argv) > 1 and sys.argv[1] == "probe":
        probe_run(sys.argv[2:])
    else:
        train()
