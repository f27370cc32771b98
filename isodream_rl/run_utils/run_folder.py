"""Who owns a run folder, for every program of the library that writes one (``isodream-train``'s ``run_dir``,
``isodream-video train``'s ``--out-dir``): a new run never writes into another run's files, a resumed run continues
its own.

A folder holding any of a program's run files is refused unless the program's resume setting (continue that run)
or its overwrite setting (delete them first) is given (:func:`refuse_another_run`, :func:`claim_folder`); each
program names its folder and those settings in :class:`RunFlags`, which the one-line errors quote. While a run uses
its folder, :func:`hold_folder` keeps it to this process (``run.lock``, :mod:`isodream_rl.run_utils.run_lock`),
removes the half-written checkpoints a killed process left, and turns a full disk or a read-only folder met on the
way into one line naming the checkpoint to continue from (:func:`continue_after`).
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from isodream_rl.run_utils.checkpoint import CheckpointManager
from isodream_rl.run_utils.disk_space import DiskFullError
from isodream_rl.run_utils.run_lock import RunDirLock
from isodream_rl.user_errors import ConfigError


@dataclass(frozen=True)
class RunFlags:
    """How a program names its run folder and the two settings that let a run use a folder holding another
    run (in its one-line errors)."""

    folder: str
    """The setting or flag that names the folder (``run_dir``, ``--out-dir``)."""
    resume: str
    """The setting that continues the run in it (``resume=true``, ``--resume``)."""
    overwrite: str
    """The setting that replaces the run in it (``overwrite=true``, ``--overwrite``)."""


def existing_run_files(run_dir: str | Path, run_files: Sequence[str]) -> list[str]:
    """The ``run_files`` present in ``run_dir``."""
    run_dir = Path(run_dir)
    return [name for name in run_files if (run_dir / name).exists()]


def refuse_another_run(
    run_dir: str | Path,
    *,
    resume: bool,
    overwrite: bool,
    run_files: Sequence[str],
    flags: RunFlags,
) -> list[str]:
    """The ``run_files`` present in ``run_dir``, once a run may use it; reads only.

    Raises:
        ConfigError: the folder holds another run and neither ``resume`` nor ``overwrite`` is set, or both are.
    """
    if resume and overwrite:
        raise ConfigError(f"{flags.resume} and {flags.overwrite} contradict each other: set one of them")
    found = existing_run_files(run_dir, run_files)
    if found and not (resume or overwrite):
        raise ConfigError(another_run(Path(run_dir), found, flags))
    return found


def run_dir_problem(run_dir: str | Path, *, flags: RunFlags) -> str | None:
    """Why ``run_dir`` cannot hold a run (a file, under a file, on a read-only disk or not writable), or
    ``None``; reads only."""
    run_dir, name = Path(run_dir), flags.folder
    if run_dir.exists() and not run_dir.is_dir():
        return f"{name} {run_dir} is a file, not a folder: give a folder (a new one, or one holding a run)"
    existing = run_dir
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{name} {run_dir} is under {existing}, which is a file: give a path under a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{name} {run_dir} cannot be written ({existing} is read-only or not yours): give another"
    return None


def claim_folder(
    run_dir: Path,
    *,
    resume: bool,
    overwrite: bool,
    run_files: Sequence[str],
    flags: RunFlags,
) -> Path:
    """:func:`refuse_another_run`, then, with ``overwrite``, delete the run files there; the folder, made.

    Raises:
        ConfigError: as :func:`refuse_another_run`; nothing is written or deleted then.
    """
    found = refuse_another_run(run_dir, resume=resume, overwrite=overwrite, run_files=run_files, flags=flags)
    if not resume:
        for name in found:
            path = run_dir / name
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def another_run(run_dir: Path, found: list[str], flags: RunFlags) -> str:
    """The refusal of ``run_dir``, which holds the run files ``found`` of another run, naming what to give instead."""
    return (
        f"{run_dir} holds another run ({', '.join(found)}): continue it with {flags.resume}, replace it with "
        f"{flags.overwrite}, or give another {flags.folder}"
    )


@contextmanager
def hold_folder(
    run_dir: Path,
    *,
    flags: RunFlags,
    resume: bool = False,
    overwrite: bool = False,
    run_files: Sequence[str] = (),
    claim: Callable[[], object] | None = None,
) -> Iterator[Path]:
    """Hold the run folder ``run_dir``: refuse a path that cannot be a writable folder, take its lock
    (:class:`~isodream_rl.run_utils.run_lock.RunDirLock`), claim it (``claim()``, or :func:`claim_folder` with ``resume``,
    ``overwrite``, ``run_files`` and ``flags``), and remove the half-written checkpoints of
    ``<run_dir>/checkpoints`` a killed or failed process left; a full disk and a read-only folder met in the block
    become one-line errors; the lock is released on leaving.

    Raises:
        ConfigError: ``run_dir`` is a file, under a file or not writable; the refusals of :func:`claim_folder`.
        RunDirBusyError: another live process holds the folder (the message names its pid).
        DiskFullError: the disk filled up; the message names the last verified checkpoint and says to resume.
    """
    problem = run_dir_problem(run_dir, flags=flags)
    if problem:
        raise ConfigError(problem)
    lock = RunDirLock(run_dir, setting=flags.folder)
    try:
        lock.acquire()
    except OSError as err:
        raise _os_error(err, run_dir, flags) from err
    try:
        if claim is None:
            claim_folder(run_dir, resume=resume, overwrite=overwrite, run_files=run_files, flags=flags)
        else:
            claim()
        CheckpointManager(run_dir / "checkpoints").remove_leftovers()
        yield run_dir
    except OSError as err:
        raise _os_error(err, run_dir, flags) from err
    finally:
        lock.release()


def continue_after(run_dir: Path, flags: RunFlags, *, fix: str) -> str:
    """How to go on after a fault the user can ``fix`` in the run folder ``run_dir``: from the last checkpoint, or
    from the start."""
    checkpoints = CheckpointManager(run_dir / "checkpoints").checkpoints()
    if checkpoints:
        return f"the last checkpoint, {checkpoints[-1]}, is intact: {fix}, then continue with {flags.resume}"
    return f"no checkpoint was written yet: {fix}, then start again with {flags.overwrite}"


def _os_error(err: OSError, run_dir: Path, flags: RunFlags) -> Exception:
    """The one-line error of an ``OSError`` met while writing ``run_dir`` (``err`` itself when it is not the
    user's to fix)."""
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        then = continue_after(run_dir, flags, fix="free disk space")
        return DiskFullError(f"the disk of {flags.folder} {run_dir} is full ({err.strerror or err}); {then}")
    if err.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return ConfigError(
            f"{flags.folder} {run_dir} cannot be written ({err.strerror}: {err.filename}): give a writable "
            f"{flags.folder}"
        )
    return err
