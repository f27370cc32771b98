"""Atomic, verified, rotating training checkpoints with a fallback when the newest one is unreadable.

Layout: ``<run_dir>/checkpoints/step_<updates:08d>/`` holds ``state.pt`` (models, optimisers, counters,
RNG states, config), ``replay/`` (the replay buffer, ``ReplayBuffer.dumps``) and ``manifest.json``: the size and
SHA-256 of every other file of the checkpoint, written last. A checkpoint is written to ``<name>.tmp`` first,
verified, and renamed when complete, so a crash or a full disk mid-write never leaves a half checkpoint under a
final name; older checkpoints are deleted only after the new one is verified.

Loading checks the manifest (every file present, of its size and checksum, no file missing from it; a
checkpoint without one is unverified), then the keys the caller needs in ``state.pt``; any failure makes that
checkpoint unreadable and the previous one is tried, with a warning. Loading never writes to a checkpoint: the
replay data are copied before TorchRL's ``loads`` opens them (it extends a short memmap file in place). The
manifest's checksums and the flushes add to each checkpoint a cost that grows with the replay buffer, and the
verification at load a smaller one (measured in docs/recipes/index.md, "Run folders, checkpoints, resume and
faults").

The replay data are written and read through memory maps, where a full disk is a SIGBUS, not an ``OSError``:
the free space they need is checked first (:mod:`~isodream_rl.run_utils.disk_space`), so a full disk is a
:class:`CheckpointError` saying to free space and resume.

TorchRL's ``Trainer(save_trainer_file=...)`` writes one file in place and has no fallback, and its ``Checkpoint``
API does not save RNG states of numpy/python or skip unreadable versions, hence this module.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import random
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from isodream_rl.run_utils.disk_space import folder_bytes, require_free_space

logger = logging.getLogger(__name__)

_PREFIX = "step_"
_STATE_FILE = "state.pt"
_REPLAY_DIR = "replay"
MANIFEST_FILE = "manifest.json"
_LOADING = ".loading-"
_CHUNK = 8 << 20


class CheckpointError(RuntimeError):
    """No readable checkpoint where one was required."""


def rng_state() -> dict[str, Any]:
    """The torch, numpy and python RNG states, and each GPU's (``"cuda"``) in a process that uses CUDA."""
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned. The GPUs' states are restored where as many GPUs are visible: a
    GPU run's checkpoint continues on a CPU-only machine (or another GPU count) with that machine's own."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    cuda = state.get("cuda")
    if cuda is not None and torch.cuda.is_available() and torch.cuda.device_count() == len(cuda):
        torch.cuda.set_rng_state_all(cuda)


def file_digest(path: Path) -> str:
    """The SHA-256 of a file, read in 8 MB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _files(folder: Path) -> list[Path]:
    """The files under ``folder`` but the manifest, relative, sorted."""
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST_FILE)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_manifest(folder: Path) -> dict[str, dict[str, Any]]:
    """Flush every file of ``folder`` to disk, then write ``manifest.json`` with their sizes and SHA-256 (last,
    and flushed too); the manifest's entries."""
    entries = {}
    for relative in _files(folder):
        path = folder / relative
        _fsync(path)
        entries[relative.as_posix()] = {"size": path.stat().st_size, "sha256": file_digest(path)}
    manifest = folder / MANIFEST_FILE
    manifest.write_text(json.dumps({"files": entries}, indent=1))
    _fsync(manifest)
    for directory in {folder, *(p.parent for p in folder.rglob("*") if p.is_file())}:
        _fsync(directory)
    return entries


def verify(folder: Path, *, checksums: bool = True) -> None:
    """Check ``folder`` against its manifest: every file listed, present, of its size and (``checksums``) its
    SHA-256, and none unlisted.

    Raises:
        CheckpointError: naming the first difference.
    """
    manifest = folder / MANIFEST_FILE
    try:
        entries = json.loads(manifest.read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f"its manifest is unreadable ({type(err).__name__}: {err})") from err
    found = {relative.as_posix() for relative in _files(folder)}
    if found - set(entries):
        raise CheckpointError(f"files not in its manifest: {sorted(found - set(entries))}")
    for name, entry in entries.items():
        path = folder / name
        if name not in found:
            raise CheckpointError(f"{name} is missing")
        size = path.stat().st_size
        if size != entry["size"]:
            raise CheckpointError(f"{name} has {size} bytes, the manifest says {entry['size']} (truncated?)")
        if checksums and file_digest(path) != entry["sha256"]:
            raise CheckpointError(f"{name} does not match its checksum (corrupted)")


class CheckpointManager:
    """Writes and reads checkpoints of one run.

    Args:
        directory: the checkpoint folder (``<run_dir>/checkpoints``).
        keep: how many of the newest checkpoints to keep (>= 2 so that a corrupted newest one has a fallback).

    Examples:
        >>> import tempfile, torch
        >>> manager = CheckpointManager(tempfile.mkdtemp(), keep=2)
        >>> path = manager.save(3, {"weights": torch.ones(2)})
        >>> manager.load_latest()[0]["weights"]
        tensor([1., 1.])
    """

    def __init__(self, directory: str | Path, *, keep: int = 2) -> None:
        if keep < 2:
            raise ValueError(f"keep must be >= 2 (a fallback for a corrupted newest checkpoint), got {keep}")
        self.directory = Path(directory)
        self.keep = keep

    def checkpoints(self) -> list[Path]:
        """Complete checkpoints, oldest first."""
        if not self.directory.exists():
            return []
        found = [
            p
            for p in self.directory.iterdir()
            if p.is_dir() and p.name.startswith(_PREFIX) and p.name[len(_PREFIX) :].isdigit()
        ]
        return sorted(found, key=_step_of)

    def save(self, step: int, state: dict[str, Any], *, replay_buffer=None) -> Path:
        """Write checkpoint ``step`` atomically, verify it, then delete the checkpoints it supersedes.

        Written to ``step_<step>.tmp``: ``state.pt``, the replay data, then the manifest, all flushed to disk;
        the folder is renamed to its final name once its files match the manifest. Then the checkpoints above
        ``step`` (left by a run that resumed from an earlier one, as the newer ones were unreadable) and all but
        the newest ``keep`` are deleted.

        Args:
            step: the update counter, used in the folder name.
            state: a ``torch.save``-able dict.
            replay_buffer: a TorchRL replay buffer saved with ``dumps``, or ``None``.

        Returns:
            the checkpoint folder.

        Raises:
            CheckpointError: the write failed (a full disk, an unwritable folder); the folder being written is
                removed and the earlier checkpoints are kept.
        """
        final = self.directory / f"{_PREFIX}{step:08d}"
        tmp = final.with_name(final.name + ".tmp")
        self.directory.mkdir(parents=True, exist_ok=True)
        self.remove_leftovers()
        try:
            tmp.mkdir()
            torch.save(state, tmp / _STATE_FILE)
            if replay_buffer is not None:
                # dumps writes through memory maps: a full disk there is a SIGBUS, not an OSError
                require_free_space(
                    {tmp: _replay_bytes(replay_buffer)}, what=f"the replay data of {final.name}"
                )
                replay_buffer.dumps(tmp / _REPLAY_DIR)
            write_manifest(tmp)
            verify(tmp, checksums=False)
        except BaseException as err:
            shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(err, (OSError, CheckpointError)):
                earlier = self.checkpoints()
                then = (
                    f"the earlier checkpoints are kept (the newest: {earlier[-1].name}): free disk space (or fix "
                    "the folder's permissions) and continue with resume=true"
                    if earlier
                    else "no checkpoint was written before: free disk space (or fix the folder's permissions) and "
                    "start again with overwrite=true"
                )
                raise CheckpointError(
                    f"writing checkpoint {final} failed ({type(err).__name__}: {err}); {then}"
                ) from err
            raise
        replaced = None
        if final.exists():  # the same update saved again (e.g. a signal right after a periodic save)
            replaced = final.with_name(final.name + ".old.tmp")
            os.replace(final, replaced)
        os.replace(tmp, final)
        _fsync(self.directory)
        if replaced is not None:
            shutil.rmtree(replaced, ignore_errors=True)
        self._rotate(final)
        return final

    def remove_leftovers(self) -> None:
        """Delete the half-written ``step_*.tmp`` folders and replay copies a killed or failed process left
        behind. Only the process that holds the run folder (:class:`~isodream_rl.run_utils.run_lock.RunDirLock`) may: for
        another, they are writes in progress."""
        if not self.directory.exists():
            return
        for stale in [*self.directory.glob(f"{_PREFIX}*.tmp"), *self.directory.glob(f"{_LOADING}*")]:
            shutil.rmtree(stale, ignore_errors=True)

    def _rotate(self, newest: Path) -> None:
        older = [p for p in self.checkpoints() if _step_of(p) < _step_of(newest)]
        newer = [p for p in self.checkpoints() if _step_of(p) > _step_of(newest)]
        for path in newer:
            logger.warning(
                "deleting %s: this run continued from an earlier checkpoint and wrote %s", path, newest
            )
            shutil.rmtree(path, ignore_errors=True)
        for path in older[: max(0, len(older) - (self.keep - 1))]:
            shutil.rmtree(path, ignore_errors=True)

    def load(self, path: str | Path, *, required_keys: Sequence[str] = ()) -> dict[str, Any]:
        """The state of checkpoint ``path`` after checking it against its manifest and for ``required_keys``.

        Every checkpoint this library writes has its manifest, written last: one without it is unverified (its
        manifest deleted, or a copy cut short) and is not read.

        Raises:
            CheckpointError: the checkpoint is unreadable: no manifest, a file missing, truncated or corrupted,
                ``state.pt`` not a dict, or a required key missing.
        """
        path = Path(path)
        if not (path / MANIFEST_FILE).exists():
            raise CheckpointError(f"it has no {MANIFEST_FILE}, so its files cannot be verified")
        verify(path)
        try:
            state = torch.load(path / _STATE_FILE, map_location="cpu", weights_only=False)
        except Exception as err:
            raise CheckpointError(f"{_STATE_FILE} is unreadable ({type(err).__name__}: {err})") from err
        if not isinstance(state, dict):
            raise CheckpointError(f"{_STATE_FILE} holds a {type(state).__name__}, not a dict")
        missing = [key for key in required_keys if key not in state]
        if missing:
            raise CheckpointError(f"{_STATE_FILE} has no {missing} (keys: {sorted(state)})")
        return state

    def load_latest(
        self, *, replay_buffer=None, required_keys: Sequence[str] = ()
    ) -> tuple[dict[str, Any], Path]:
        """Load the newest readable checkpoint, falling back to older ones.

        A checkpoint that fails :meth:`load` (a file missing, truncated or corrupted, a required key missing) is
        reported with a warning naming it and the fault, and the previous one is tried.

        Args:
            replay_buffer: filled from the chosen checkpoint's replay data when given (:meth:`load_replay`).
            required_keys: keys ``state.pt`` must hold.

        Returns:
            ``(state, path)``.

        Raises:
            CheckpointError: no checkpoint, none readable, or unreadable replay data.
        """
        candidates = self.checkpoints()
        if not candidates:
            raise CheckpointError(f"no checkpoint in {self.directory}")
        failures = []
        for path in reversed(candidates):
            try:
                state = self.load(path, required_keys=required_keys)
            except CheckpointError as err:
                failures.append(f"{path.name}: {err}")
                logger.warning(
                    "checkpoint %s is unreadable (%s); falling back to the previous one", path, err
                )
                continue
            if replay_buffer is not None:
                self.load_replay(path, replay_buffer)
            return state, path
        raise CheckpointError(f"no readable checkpoint in {self.directory}:\n  " + "\n  ".join(failures))

    def load_replay(self, path: str | Path, replay_buffer) -> None:
        """Fill ``replay_buffer`` from the replay data of checkpoint ``path`` (verified by :meth:`load`), read
        from a copy: TorchRL's ``loads`` may write to the files it opens.

        Raises:
            CheckpointError: the replay data do not load, or the disk has no room for the copy and the buffer's
                memory (checked first: both are written through memory maps); a half-filled buffer cannot take
                a second attempt.
        """
        source = Path(path) / _REPLAY_DIR
        if not source.exists():
            return
        size = folder_bytes(source)
        needs = {self.directory: size}
        scratch_dir = getattr(getattr(replay_buffer, "storage", None), "scratch_dir", None)
        if scratch_dir:
            needs[scratch_dir] = size
        what = f"resuming from {Path(path).name} (a copy of its replay data, then the replay memory)"
        try:
            require_free_space(needs, what=what)
        except OSError as err:
            raise CheckpointError(
                f"{err.strerror}; the checkpoints are intact: free disk space, then continue with resume=true"
            ) from err
        with tempfile.TemporaryDirectory(dir=self.directory, prefix=_LOADING) as scratch:
            copy = Path(scratch) / _REPLAY_DIR
            try:
                shutil.copytree(source, copy)
                replay_buffer.loads(copy)
            except Exception as err:
                if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
                    raise CheckpointError(
                        f"resuming from {path} failed ({err}); the checkpoints are intact: free disk space, "
                        "then continue with resume=true"
                    ) from err
                raise CheckpointError(
                    f"the replay buffer of {path} is unreadable ({type(err).__name__}: {err}); delete "
                    f"{path} to resume from the previous checkpoint"
                ) from err


def _replay_bytes(replay_buffer) -> int:
    """What ``replay_buffer.dumps`` writes: its storage's memmap files at their full size, or 0 when the storage
    keeps no files."""
    scratch_dir = getattr(getattr(replay_buffer, "storage", None), "scratch_dir", None)
    return folder_bytes(scratch_dir, pattern="*.memmap") if scratch_dir else 0


def _step_of(path: Path) -> int:
    return int(path.name[len(_PREFIX) :])
