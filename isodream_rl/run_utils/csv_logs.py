"""CSV logs cut back to a checkpoint, so that a resumed run continues one timeline instead of writing a second.

TorchRL's ``CSVLogger`` appends one ``step,value`` row per call to ``<logs>/<experiment>/scalars/<name>.csv``
and flushes it. A run killed after its last checkpoint leaves rows for steps that the resumed run computes
again, with other values (the same step twice). So a checkpoint records the size of every CSV file as it is
written (:func:`csv_log_sizes`, in the checkpoint's state) and resuming cuts each file back to that size
(:func:`cut_csv_logs`), removing the files made after it. TensorBoard and W&B logs are left as they are.
"""

from __future__ import annotations

from pathlib import Path


def csv_log_sizes(folder: str | Path) -> dict[str, int]:
    """``{path relative to folder: bytes}`` of every ``*.csv`` under ``folder`` (``{}`` when there is none)."""
    folder = Path(folder)
    if not folder.exists():
        return {}
    return {p.relative_to(folder).as_posix(): p.stat().st_size for p in sorted(folder.rglob("*.csv"))}


def cut_csv_logs(folder: str | Path, sizes: dict[str, int]) -> list[Path]:
    """Cut every ``*.csv`` under ``folder`` back to its size in ``sizes`` (what :func:`csv_log_sizes` gave when
    the checkpoint was written); remove the files ``sizes`` does not list. A file that ends without a newline
    (a row cut by a crash, or damaged) gets one, so the next row starts a line of its own.

    Returns:
        the files changed or removed.
    """
    folder = Path(folder)
    changed = []
    for path in sorted(folder.rglob("*.csv")) if folder.exists() else []:
        size = sizes.get(path.relative_to(folder).as_posix())
        if size is None:
            path.unlink()
            changed.append(path)
            continue
        with open(path, "rb+") as f:
            if f.seek(0, 2) > size:
                f.truncate(size)
                changed.append(path)
            if f.seek(0, 2) == 0:
                continue
            f.seek(-1, 2)
            if f.read(1) != b"\n":
                f.write(b"\n")
                changed.append(path)
    return sorted(set(changed))
