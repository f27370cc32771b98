"""One process per run folder: a lock file holding its owner's pid, released by the kernel however it ends.

``isodream-train`` (``run_dir``) and ``isodream-video train`` (``--out-dir``) hold their folder with
:class:`RunDirLock` while they write to it. A second process on the same folder (a second run started at the
same time, or ``resume=true`` while the first still trains) is refused with :class:`RunDirBusyError` naming the
owner's pid. The lock is an advisory ``flock`` on ``<folder>/run.lock``: the kernel drops it when its process
ends, SIGKILL included, so a lock file a dead process left behind is taken over by the next run (with a
warning naming that pid). POSIX only (``fcntl``), as the rest of the run machinery (signals, memmaps).
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
from pathlib import Path

logger = logging.getLogger(__name__)

LOCK_FILE = "run.lock"
_TRIES = 3


class RunDirBusyError(RuntimeError):
    """The run folder is held by another live process; the message names its pid."""


def _pid_in(fd: int) -> int | None:
    """The pid written in the open lock file ``fd``, or ``None`` (empty or unreadable)."""
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _busy(folder: Path, owner: int | None, setting: str) -> RunDirBusyError:
    who = f"process {owner}" if owner is not None and owner > 0 else "another process"
    return RunDirBusyError(
        f"{setting} {folder} is in use by {who} (lock file {Path(folder) / LOCK_FILE}): wait for that run to end "
        f"or stop it, then try again, or give another {setting}"
    )


def lock_owner(folder: str | Path) -> int | None:
    """The pid of the live process holding ``folder``'s lock, ``-1`` when it holds it but wrote no pid yet, or
    ``None`` when no process holds it; reads only (no lock file is made)."""
    try:
        fd = os.open(Path(folder) / LOCK_FILE, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = _pid_in(fd)
        return -1 if pid is None else pid
    finally:
        os.close(fd)  # also releases the shared lock, when it was taken
    return None


class RunDirLock:
    """Hold ``folder`` for this process: ``with RunDirLock(run_dir): ...``.

    Re-entrant within a process: a folder this process holds already is held once more, and released when the
    last holder releases it (``isodream-train`` takes it in its Hydra callback, before Hydra writes into the
    folder, and again around the run).

    Args:
        folder: the run folder; made (with its parents) when missing, and removed again on release when this
            lock made it and it is still empty.
        setting: how the user names the folder, for the error message (``"run_dir"``, ``"--out-dir"``).

    Raises:
        RunDirBusyError: another live process holds the folder (on entering).
        OSError: the folder or its lock file cannot be made (a file in the way, a read-only disk).

    Examples:
        >>> import tempfile
        >>> folder = tempfile.mkdtemp()
        >>> with RunDirLock(folder):
        ...     lock_owner(folder) == os.getpid()
        True
        >>> lock_owner(folder) is None
        True
    """

    #: ``{resolved folder: [lock file descriptor, holders]}`` of the folders this process holds
    _held: dict[Path, list[int]] = {}

    def __init__(self, folder: str | Path, *, setting: str = "run_dir") -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self.setting = setting
        self._key: Path | None = None
        self._made_folder = False

    def acquire(self) -> RunDirLock:
        """Take the lock (see the class); ``self``."""
        if self._key is not None:
            return self
        key = self.folder.resolve()
        if key in self._held:
            self._held[key][1] += 1
            self._key = key
            return self
        self._made_folder = not self.folder.exists()
        self.folder.mkdir(parents=True, exist_ok=True)
        tries = 0
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = _pid_in(fd)
                os.close(fd)
                tries += 1
                if tries < _TRIES:  # lock_owner's brief shared lock, taken by a process that only looks
                    time.sleep(0.05)
                    continue
                self._remove_made_folder()
                raise _busy(self.folder, owner, self.setting) from None
            try:
                same_file = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same_file = False
            if same_file:
                break
            # the previous owner removed the file between our open and our lock: lock the new one
            os.close(fd)
        previous = _pid_in(fd)
        if previous is not None and previous != os.getpid():
            logger.warning(
                "taking over %s: it names process %d, which holds it no longer (it ended)",
                self.path,
                previous,
            )
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._held[key] = [fd, 1]
        self._key = key
        return self

    def release(self) -> None:
        """Let go of the folder; the last holder in this process removes the lock file and drops the lock (a
        no-op when not held)."""
        if self._key is None:
            return
        entry = self._held[self._key]
        entry[1] -= 1
        key, self._key = self._key, None
        if entry[1] > 0:
            return
        del self._held[key]
        try:
            self.path.unlink()  # before unlocking: a process waiting on this file sees it gone and retries
        except OSError:
            pass
        os.close(entry[0])
        self._remove_made_folder()

    def _remove_made_folder(self) -> None:
        if self._made_folder:
            try:
                self.folder.rmdir()  # only when empty: nothing was written
            except OSError:
                pass

    def __enter__(self) -> RunDirLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
