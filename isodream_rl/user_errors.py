"""How the console commands report a user error: one line on stderr and exit status 2.

``isodream-train``, ``isodream-eval`` and ``isodream-video`` run their work inside :func:`report_user_errors`:
an error the user can fix (an invalid setting, a missing path, an unreadable checkpoint, a resume with other
settings) is printed as ``<command>: <message>`` on one line, and the process exits with status 2. With
``--debug`` (or ``HYDRA_FULL_ERROR=1`` in the environment) the exception propagates with its traceback.

A run that SIGINT (Ctrl-C) or SIGTERM stopped after its checkpoint is no finished run: :func:`exit_stopped` says
where it stopped and how to continue, in one line, and exits with the shell's status of that signal (130, 143).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

#: exit status of a user error (as argparse's)
USER_ERROR = 2
DEBUG_FLAG = "--debug"
#: exit status of a process a signal stopped is this plus the signal's number (the shell's convention)
STOPPED_BY_SIGNAL = 128


class ConfigError(ValueError):
    """An invalid setting of a run (its configuration, its run folder, a command-line flag); the message names the
    setting and what to change."""


def debugging() -> bool:
    """``HYDRA_FULL_ERROR=1`` is set (``--debug`` sets it too): show tracebacks."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1"


def take_debug_flag(argv: list[str]) -> list[str]:
    """``argv`` without ``--debug``; when it was there, set ``HYDRA_FULL_ERROR=1`` (Hydra reads it as well)."""
    if DEBUG_FLAG in argv:
        os.environ["HYDRA_FULL_ERROR"] = "1"
    return [arg for arg in argv if arg != DEBUG_FLAG]


def one_line(err: BaseException) -> str:
    """The exception's message on one line (a multi-line list of problems joined with spaces)."""
    lines = [line.strip().removeprefix("- ") for line in str(err).splitlines() if line.strip()]
    # "invalid training configuration:" then one problem a line: "...: first; second"
    text = (
        lines[0] + " " + "; ".join(lines[1:])
        if len(lines) > 1 and lines[0].endswith(":")
        else " ".join(lines)
    )
    if isinstance(err, KeyError) and text.startswith(("'", '"')):
        text = text[1:-1]
    return text or type(err).__name__


def log_to_stderr() -> None:
    """Warnings of this package (checkpoint fallback, skipped updates, signals, a taken-over lock) on stderr.

    Hydra's logging setup disables the loggers that existed before it ran, ours included; turn them back on.
    """
    for name, item in logging.root.manager.loggerDict.items():
        if name.startswith("isodream_rl") and isinstance(item, logging.Logger):
            item.disabled = False
    package = logging.getLogger("isodream_rl")
    if not package.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        package.addHandler(handler)
        package.setLevel(logging.INFO)
        package.propagate = False


def exit_user_error(prog: str, message: str) -> NoReturn:
    """``<prog>: <message>`` on stderr, then exit status 2."""
    print(f"{prog}: {message}", file=sys.stderr)
    sys.exit(USER_ERROR)


@contextmanager
def report_user_errors(prog: str, errors: tuple[type[BaseException], ...]) -> Iterator[None]:
    """Run the block; an exception of ``errors`` becomes ``<prog>: <message>`` on stderr and exit status 2
    (re-raised when :func:`debugging`)."""
    try:
        yield
    except errors as err:
        if debugging():
            raise
        exit_user_error(prog, one_line(err))


def exit_stopped(prog: str, *, at: str, signum: int, checkpoint: object, resume: str) -> NoReturn:
    """End a run that the signal ``signum`` stopped after writing ``checkpoint``: ``<prog>: stopped at <at> by
    <SIGNAL> (checkpoint <checkpoint>); continue with <resume>`` on stderr and exit status ``128 + signum``
    (130 for SIGINT, 143 for SIGTERM), so that ``isodream-train ... && isodream-eval ...`` or a scheduler does
    not take a stopped run for a finished one.

    Args:
        prog: the command (``"isodream-train"``).
        at: how far the run got, in its own unit (``"1200 env steps"``, ``"40 iterations"``).
        signum: the signal that stopped it.
        checkpoint: the checkpoint it wrote on stopping.
        resume: the setting that continues it (``"resume=true"``, ``"--resume"``).
    """
    name = signal.Signals(signum).name
    print(
        f"{prog}: stopped at {at} by {name} (checkpoint {checkpoint}); continue with {resume}",
        file=sys.stderr,
    )
    sys.exit(STOPPED_BY_SIGNAL + signum)
