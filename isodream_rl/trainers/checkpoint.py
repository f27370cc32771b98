"""Atomic, rotating training checkpoints with a fallback when the newest one is unreadable.

Layout: ``<run_dir>/checkpoints/step_<updates:08d>/`` holds ``state.pt`` (models, optimisers, counters,
RNG states, config) and ``replay/`` (the replay buffer, ``ReplayBuffer.dumps``). A checkpoint is written to
``<name>.tmp`` first and renamed when complete, so a crash mid-write never leaves a half checkpoint under a
final name. TorchRL's ``Trainer(save_trainer_file=...)`` writes one file in place and has no fallback, and
its ``Checkpoint`` API does not save RNG states of numpy/python or skip unreadable versions, hence this module.
"""

from __future__ import annotations

import logging
import os
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

logger = logging.getLogger(__name__)

_PREFIX = "step_"
_STATE_FILE = "state.pt"
_REPLAY_DIR = "replay"


class CheckpointError(RuntimeError):
    """No readable checkpoint where one was required."""


def rng_state() -> dict[str, Any]:
    """The torch, numpy and python RNG states."""
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


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
            if p.is_dir() and p.name.startswith(_PREFIX) and not p.name.endswith(".tmp")
        ]
        return sorted(found, key=lambda p: int(p.name[len(_PREFIX) :]))

    def save(self, step: int, state: dict[str, Any], *, replay_buffer=None) -> Path:
        """Write checkpoint ``step`` atomically and delete all but the newest ``keep``.

        Args:
            step: the update counter, used in the folder name.
            state: a ``torch.save``-able dict.
            replay_buffer: a TorchRL replay buffer saved with ``dumps``, or ``None``.

        Returns:
            the checkpoint folder.
        """
        final = self.directory / f"{_PREFIX}{step:08d}"
        tmp = final.with_name(final.name + ".tmp")
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        torch.save(state, tmp / _STATE_FILE)
        if replay_buffer is not None:
            replay_buffer.dumps(tmp / _REPLAY_DIR)
        with open(tmp / _STATE_FILE, "rb") as f:
            os.fsync(f.fileno())
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        for old in self.checkpoints()[: -self.keep]:
            shutil.rmtree(old, ignore_errors=True)
        return final

    def load_latest(self, *, replay_buffer=None) -> tuple[dict[str, Any], Path]:
        """Load the newest readable checkpoint, falling back to older ones.

        An unreadable ``state.pt`` (truncated, corrupted) is reported with a warning naming the checkpoint and
        the error, and the previous one is tried. Unreadable replay data of an otherwise readable checkpoint
        raises :class:`CheckpointError` naming the folder to delete.

        Args:
            replay_buffer: filled with ``loads`` from the checkpoint's replay data when given.

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
                state = torch.load(path / _STATE_FILE, map_location="cpu", weights_only=False)
                if not isinstance(state, dict):
                    raise TypeError(f"expected a dict, got {type(state).__name__}")
            except Exception as err:  # any unreadable file: try the previous checkpoint
                failures.append(f"{path.name}: {type(err).__name__}: {err}")
                logger.warning(
                    "checkpoint %s is unreadable (%s: %s); falling back to the previous one",
                    path,
                    type(err).__name__,
                    err,
                )
                continue
            if replay_buffer is not None and (path / _REPLAY_DIR).exists():
                # A half-loaded memmap storage cannot take a second attempt: stop with the fix instead.
                try:
                    replay_buffer.loads(path / _REPLAY_DIR)
                except Exception as err:
                    raise CheckpointError(
                        f"the replay buffer of {path} is unreadable ({type(err).__name__}: {err}); delete "
                        f"{path} to resume from the previous checkpoint"
                    ) from err
            return state, path
        raise CheckpointError(f"no readable checkpoint in {self.directory}:\n  " + "\n  ".join(failures))
