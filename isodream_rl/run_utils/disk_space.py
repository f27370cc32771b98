"""A full disk ends a run with one line, never with SIGBUS: free space is checked before memory-mapped writes.

TorchRL's replay storage (``LazyMemmapStorage``) and its ``dumps``/``loads`` write through memory maps. A page
written to a full disk there is not an ``OSError`` but a SIGBUS that kills the process without a word (exit
135), possibly in the middle of a checkpoint. So before each such write the space it needs is checked
(:func:`require_free_space`: raises ``OSError(ENOSPC)``, which the checkpoint code and
:func:`~isodream_rl.trainers.run_dir.hold_run_dir` turn into "free disk space, then resume=true"), and the
replay memory's files are allocated whole once they exist (:class:`ReplayReservation`), so that the pages the
buffer fills later are already on disk. Plain file writes (``state.pt``, the CSV logs) fail with ``OSError``
by themselves.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

from tensordict import TensorDictBase

#: room kept free beyond what a write needs (metadata, the logs, the next small files)
MARGIN = 4 << 20


class DiskFullError(RuntimeError):
    """A run stopped because its disk is full; the message says what is kept and how to continue."""


def _existing(path: Path) -> Path:
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def folder_bytes(folder: str | Path, *, pattern: str = "*") -> int:
    """The apparent size of the files under ``folder`` matching ``pattern`` (0 when it does not exist)."""
    folder = Path(folder)
    return sum(p.stat().st_size for p in folder.rglob(pattern) if p.is_file()) if folder.exists() else 0


def require_free_space(needs: dict[str | Path, int], *, what: str) -> None:
    """Check that each disk has room for the bytes to be written under the paths of ``needs`` (paths on one disk
    add up), plus :data:`MARGIN`.

    Args:
        needs: ``{path: bytes}``; a path need not exist yet (its nearest existing folder's disk counts).
        what: the write, for the message (``"the replay data of checkpoint step_00000010"``).

    Raises:
        OSError: ``ENOSPC``, saying how much is needed and how much is free.
    """
    per_disk: dict[int, tuple[Path, int]] = {}
    for path, size in needs.items():
        existing = _existing(Path(path))
        device = existing.stat().st_dev
        _, total = per_disk.get(device, (existing, 0))
        per_disk[device] = (existing, total + int(size))
    for existing, size in per_disk.values():
        free = shutil.disk_usage(existing).free
        if size and free < size + MARGIN:
            raise OSError(
                errno.ENOSPC,
                f"No space left on device: {what} needs {size / 2**20:.1f} MB on the disk of {existing}, "
                f"{free / 2**20:.1f} MB are free",
            )


class ReplayReservation:
    """``batch_process`` hooks around ``ReplayBufferTrainer.extend``: allocate the replay memory on disk once.

    Before the first write into a storage not made yet, the free space for its whole capacity is checked
    (:func:`require_free_space`); after it, the storage's memmap files are allocated whole
    (``os.posix_fallocate``), so the steps written later never meet a full disk through a memory map. A storage
    filled from a checkpoint (a resumed run) is dense already.

    Args:
        storage: the replay buffer's ``LazyMemmapStorage`` (its ``scratch_dir`` holds the files).
    """

    def __init__(self, storage) -> None:
        self.storage = storage
        self.scratch_dir = Path(storage.scratch_dir)
        self.done = False

    def before(self, batch: TensorDictBase) -> None:
        if self.done or self.storage.initialized:
            return
        per_step = batch.bytes() / max(1, batch.numel())
        require_free_space(
            {self.scratch_dir: int(per_step * self.storage.max_size)},
            what="the replay memory (train.buffer_size)",
        )

    def after(self, batch: TensorDictBase) -> None:
        if self.done:
            return
        self.done = True
        for path in sorted(self.scratch_dir.rglob("*.memmap")):
            fd = os.open(path, os.O_RDWR)
            try:
                os.posix_fallocate(fd, 0, os.fstat(fd).st_size)
            except OSError as err:
                # a file system that cannot allocate ahead: the check before the first write stands
                if err.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
                    raise OSError(
                        err.errno,
                        f"{err.strerror}: allocating the replay memory (train.buffer_size)",
                        str(path),
                    ) from err
            finally:
                os.close(fd)

    def register(self, trainer, extend) -> None:
        """Register ``before``, ``extend`` (the replay hook's) and ``after``, in that order."""
        trainer.register_op("batch_process", self.before)
        trainer.register_op("batch_process", extend)
        trainer.register_op("batch_process", self.after)
