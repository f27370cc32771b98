"""The parts of TorchRL's ``Trainer`` state that a resumable run reads and writes, in one place.

``torchrl.trainers.Trainer`` keeps its update count, the frame at which each key was last logged, the values it
logged and its progress bar in private attributes (``_optim_count``, ``_last_log``, ``_log_dict``, ``_pbar``), with
no public accessor: its own checkpointing saves them through its save/load backends, which write the whole
trainer, collector included. A run that keeps its own checkpoint format (``run_utils/checkpoint.py``) and resumes
into a new ``Trainer`` needs them one by one, so every such access goes through the functions below.
``tests/test_trainer_state.py`` builds a real ``Trainer`` and fails if a TorchRL release renames or drops one.
"""

from __future__ import annotations

from typing import Any

from torchrl.trainers import Trainer

__all__ = ["advance_progress_bar", "log_marks", "logged_values", "optim_count", "restore"]


def optim_count(trainer: Trainer) -> int:
    """Optimisation steps the trainer has counted (it logs and checkpoints on this count)."""
    return trainer._optim_count


def log_marks(trainer: Trainer) -> dict[str, int]:
    """Per logged key, the collected-frame count at which it was last written (``log_interval`` is measured
    from there)."""
    return dict(trainer._last_log)


def restore(trainer: Trainer, *, optim_count: int, log_marks: dict[str, int]) -> None:
    """Set the two counters above on a new trainer, as a resumed run had them."""
    trainer._optim_count = optim_count
    trainer._last_log = dict(log_marks)


def logged_values(trainer: Trainer) -> dict[str, list[Any]]:
    """Every value the trainer's hooks logged, per key, in order."""
    return trainer._log_dict


def advance_progress_bar(trainer: Trainer, frames: int) -> None:
    """Move the progress bar by ``frames`` (a resumed run's bar starts at its frame count). The bar exists from
    the ``"setup"`` stage of ``train()`` on, with ``progress_bar=True``."""
    trainer._pbar.update(frames)
