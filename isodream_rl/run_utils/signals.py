"""A run's first SIGINT (Ctrl-C) or SIGTERM: "checkpoint, then stop", for every program of the library that trains
(``isodream-train``'s loop, :func:`~isodream_rl.trainers.run_lifecycle.train_with_checkpoints`; ``isodream-video
train``'s)."""

from __future__ import annotations

import logging
import signal

logger = logging.getLogger(__name__)


class StopOnSignal:
    """Turns the first SIGINT/SIGTERM into "checkpoint, then stop" at the end of the current batch.

    A second signal of the same kind gets the default behavior (immediate stop), for a user who insists.
    Use as a context manager around ``trainer.train()``.
    """

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, signum, frame) -> None:
        if self.received is not None:
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)
            return
        self.received = signum
        logger.warning(
            "%s received: saving a checkpoint at the end of this batch, then stopping",
            signal.Signals(signum).name,
        )

    def __enter__(self) -> StopOnSignal:
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
