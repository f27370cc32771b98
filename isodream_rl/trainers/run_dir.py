"""``isodream-train``'s run folder: a new run never writes into another run's files, a resumed run continues its own.

A run folder (``run_dir``) holds ``run_config.json``, ``checkpoints/``, ``logs/``, ``pictures/``,
``summary.json`` and ``replay_scratch/`` (:data:`RUN_FILES`). Starting a run where any of them exists is
refused unless ``resume=true`` (continue that run; its configuration must match, see :func:`check_same_run`) or
``overwrite=true`` (delete them first). Both checks run before anything of the folder is written, and
``run_config.json`` is written (:func:`write_run_config`) only once the run is known to start. Hydra's own
records (``.hydra/``, ``<job>.log``) are not a run's files; ``isodream-train`` checks the folder before Hydra
writes them (:class:`RunDirGuard`).

While a run uses its folder, :func:`hold_run_dir` holds it as any program of the library holds its run folder
(:func:`~isodream_rl.run_utils.run_folder.hold_folder`: ``run.lock``, one-line errors of a full disk or a read-only
folder), removes what a start that failed before ``run_config.json`` made (so the corrected command is not
refused), and turns an env's NaN/inf data met on the way into one line naming the checkpoint to continue from.
"""

from __future__ import annotations

import atexit
import dataclasses
import json
import shutil
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import OmegaConf

from isodream_rl.envs.finite import NonFiniteEnvDataError
from isodream_rl.modules.sizes import SIZE_PRESETS
from isodream_rl.run_utils.checkpoint import CheckpointError
from isodream_rl.run_utils.run_folder import (
    RunFlags,
    another_run,
    claim_folder,
    continue_after,
    existing_run_files,
    hold_folder,
    run_dir_problem,
)
from isodream_rl.run_utils.run_lock import RunDirBusyError, RunDirLock
from isodream_rl.trainers.config import ConfigError, RunConfig, config_from_dict
from isodream_rl.trainers.learners import resolved
from isodream_rl.trainers.renames import resumes_former_run
from isodream_rl.user_errors import debugging, exit_user_error, log_to_stderr, one_line

#: the files and folders of a run (a folder holding one of them holds a run)
RUN_FILES = ("run_config.json", "checkpoints", "logs", "pictures", "summary.json", "replay_scratch")

#: the settings a resumed run may change: its length, logging, checkpoint cadence, threads, device, precision,
#: fault tolerance and collector placement; every other one changes the models or the data
RESUMABLE = (
    "run_dir",
    "resume",
    "overwrite",
    "train.total_steps",
    "world_model.updates",
    "world_model.max_minutes",
    "logging.",
    "checkpoint.",
    "train.threads",
    "train.device",
    "train.max_nonfinite_updates",
    "train.collector_backend",
    "train.ray_address",
    "train.collector_cpus",
    "train.distributed_",
    "train.slurm_kwargs",
    "model.precision",
)


#: ``isodream-train``'s names
TRAIN_FLAGS = RunFlags(folder="run_dir", resume="resume=true", overwrite="overwrite=true")


def resuming(cfg: RunConfig) -> bool:
    """``resume=true`` or ``checkpoint.resume=true``."""
    return bool(cfg.resume or cfg.checkpoint.resume)


def claim_run_dir(cfg: RunConfig) -> Path:
    """Check that ``cfg`` may write to its ``run_dir``, clearing it with ``overwrite=true``; the folder.

    Raises:
        ConfigError: the folder holds another run and neither ``resume`` nor ``overwrite`` is set, or both are
            set. Nothing is written or deleted then.
        CheckpointError: ``resume`` and no checkpoint there.
    """
    run_dir = Path(cfg.run_dir)
    if resuming(cfg) and not cfg.overwrite:
        if not any((run_dir / "checkpoints").glob("step_*")):
            raise CheckpointError(
                f"resume=true but there is no checkpoint in {run_dir / 'checkpoints'}; start without resume or "
                "point run_dir at the run to continue"
            )
    return claim_folder(
        run_dir, resume=resuming(cfg), overwrite=cfg.overwrite, run_files=RUN_FILES, flags=TRAIN_FLAGS
    )


@contextmanager
def hold_run_dir(cfg: RunConfig) -> Iterator[Path]:
    """Hold ``cfg.run_dir`` for one run: ``with hold_run_dir(cfg) as run_dir: ...``.

    On entering: refuse a path that cannot be a writable folder, take the folder's lock
    (:class:`~isodream_rl.run_utils.run_lock.RunDirLock`), claim it (:func:`claim_run_dir`), and remove the
    half-written
    checkpoints a killed or failed process left. If the block fails before ``run_config.json`` exists (a new run
    that did not start), the run files it made are removed. A full disk, a read-only folder and an env's NaN/inf
    data met in the block become one-line errors. The lock is released on leaving, however the block ends.

    Raises:
        ConfigError: ``run_dir`` is a file, under a file or not writable; the refusals of :func:`claim_run_dir`.
        RunDirBusyError: another live process holds the folder (the message names its pid).
        DiskFullError: the disk filled up; the message names the last verified checkpoint and says to resume.
        NonFiniteEnvDataError: the env returned NaN/inf; the message names it, the entry, the env step and the
            last verified checkpoint, and says to fix the env and resume.
    """
    with hold_folder(Path(cfg.run_dir), flags=TRAIN_FLAGS, claim=lambda: claim_run_dir(cfg)) as run_dir:
        new = not resuming(cfg)
        try:
            yield run_dir
        except BaseException as err:
            if new and not (run_dir / "run_config.json").exists():
                for name in existing_run_files(run_dir, RUN_FILES):
                    shutil.rmtree(run_dir / name, ignore_errors=True)
            if isinstance(err, NonFiniteEnvDataError):
                then = continue_after(run_dir, TRAIN_FLAGS, fix="fix the env")
                raise NonFiniteEnvDataError(f"{err}; {then}") from err
            raise


def write_run_config(cfg: RunConfig) -> Path:
    """Write ``<run_dir>/run_config.json`` (the configuration with the values its learner reads,
    :func:`~isodream_rl.trainers.learners.resolved`); the path."""
    path = Path(cfg.run_dir) / "run_config.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(dataclasses.asdict(resolved(cfg)), indent=2))
    tmp.replace(path)
    return path


def _flat(tree: dict, prefix: str = "") -> dict[str, Any]:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _compared(cfg: RunConfig) -> dict[str, Any]:
    """The flat settings of ``cfg`` as a resume compares them: the values its learner reads
    (:func:`~isodream_rl.trainers.learners.resolved`), the size preset as the widths it stands for, so a run whose
    widths were written as ``model.<field>`` on another preset (``size=bench`` before it was one) is the same run."""
    tree = dataclasses.asdict(resolved(cfg))
    model = tree["model"]
    if model["size"] in SIZE_PRESETS:
        for name, width in SIZE_PRESETS[model.pop("size")].items():
            model[name] = width if model[name] is None else model[name]
    return _flat(tree)


def differing_settings(saved: dict, cfg: RunConfig) -> dict[str, tuple[Any, Any]]:
    """``{field: (saved, now)}`` for the settings outside :data:`RESUMABLE` where ``cfg`` differs from the
    configuration ``saved`` in a checkpoint (``dataclasses.asdict`` of a :class:`RunConfig`).

    ``algo=isodream_v2`` continues a run saved under a name that changed learner
    (:func:`~isodream_rl.trainers.renames.resumes_former_run`; its weights are checked when they load), read under
    that name, and the ``algo`` fields that set the variant are compared as any other.
    """
    saved_cfg = config_from_dict(saved)
    if resumes_former_run(saved_cfg.algo.name, cfg.algo.name):
        saved_cfg = config_from_dict({**saved, "algo": {**saved["algo"], "name": cfg.algo.name}})
    before = _compared(saved_cfg)
    now = _compared(cfg)
    return {
        key: (before.get(key), now.get(key))
        for key in sorted(before.keys() | now.keys())
        if not key.startswith(RESUMABLE) and before.get(key) != now.get(key)
    }


def check_same_run(saved: dict, cfg: RunConfig) -> None:
    """Refuse to resume with settings that change the models or the data.

    Raises:
        ConfigError: listing every such setting with its saved and its new value.
    """
    differ = differing_settings(saved, cfg)
    if differ:
        listed = ", ".join(f"{key}: {before!r} -> {now!r}" for key, (before, now) in differ.items())
        raise ConfigError(
            f"resume=true continues the run in {cfg.run_dir}, trained with other settings (saved -> now): "
            f"{listed}; keep them, or start a new run in another run_dir"
        )


class RunDirGuard(Callback):
    """A Hydra callback (``hydra.callbacks`` in ``configs/config.yaml``) that runs the refusals of
    :func:`hold_run_dir`, :func:`claim_run_dir` and :func:`check_same_run` before Hydra writes ``.hydra/`` into
    the run folder, so a refused start leaves the folder as it was: a path that cannot be a writable folder, a
    folder another live process holds, a folder holding another run without ``resume``/``overwrite``, and a
    resume whose settings differ from the run's ``run_config.json`` (or whose ``run_config.json`` cannot be
    read). The refusal is one line on stderr and exit status 2. ``overwrite=true`` clears the folder later, in
    :func:`claim_run_dir`; the checkpoint's own configuration is checked again when it loads.

    Hydra turns an exception raised in a callback into a warning and runs the job all the same, so the guard
    fails closed by itself: whatever a check raises ends the process with exit status 2, in one line (after the
    traceback with ``--debug`` or ``HYDRA_FULL_ERROR=1``).
    """

    def on_run_start(self, config, **kwargs) -> None:
        run_dir = Path(str(OmegaConf.select(config, "run_dir", default=None)))
        log_to_stderr()  # a taken-over lock says so
        try:
            self._check(config, run_dir)
        except Exception as err:  # whatever a check raises: Hydra would only warn
            if debugging():
                traceback.print_exc()
            if isinstance(err, (ConfigError, RunDirBusyError)):
                exit_user_error("isodream-train", one_line(err))
            exit_user_error(
                "isodream-train",
                f"checking run_dir {run_dir} failed ({type(err).__name__}: {one_line(err)}); nothing was started: "
                "--debug shows the traceback",
            )

    @staticmethod
    def _check(config, run_dir: Path) -> None:
        def setting(key: str):
            return OmegaConf.select(config, key, default=None)

        problem = run_dir_problem(run_dir, flags=TRAIN_FLAGS)
        if problem:
            raise ConfigError(problem)
        # held from here to the end of the process: a second process started at the same time is refused
        # before Hydra writes into the folder (the run holds it again, see hold_run_dir)
        atexit.register(RunDirLock(run_dir).acquire().release)
        if setting("overwrite"):
            return
        if not (setting("resume") or setting("checkpoint.resume")):
            found = existing_run_files(run_dir, RUN_FILES)
            if found:
                raise ConfigError(another_run(run_dir, found, TRAIN_FLAGS))
            return
        saved = run_dir / "run_config.json"
        if saved.exists():
            task = OmegaConf.masked_copy(config, [key for key in config if key != "hydra"])
            check_same_run(
                read_run_config(saved), config_from_dict(OmegaConf.to_container(task, resolve=True))
            )


def read_run_config(path: Path) -> dict:
    """The configuration a run wrote in ``path`` (its ``run_config.json``, :func:`write_run_config`).

    Raises:
        ConfigError: the file cannot be read or holds no run configuration (cut short, edited); the message names
            it and says how to go on.
    """
    try:
        saved = json.loads(path.read_text())
        _compared(config_from_dict(saved))
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as err:
        raise ConfigError(
            f"{path} holds no readable run configuration ({type(err).__name__}: {one_line(err)}): delete it and "
            "continue with resume=true (the checkpoints hold the run's settings, and the run writes the file "
            "again), or start a new run with overwrite=true"
        ) from err
    return saved
