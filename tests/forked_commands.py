"""Console commands run as ``python -m <module> ...`` would run them, each in a process of its own forked from
one that paid the imports once.

Every ``python -m isodream_rl.cli ...`` of a test pays 4-5 s of Python, torch, TorchRL and Hydra imports before it
does its work, which for a refused command is one line on stderr. :func:`run_module` sends the command to a
server process (one per test process, started at its first command with :data:`SERVER_ENV`; it imports the
command modules, then never runs torch, Hydra or a thread) that forks a child per command. The child takes the
command's working directory, environment, ``sys.argv`` and stdout/stderr (files, at the file-descriptor level;
stdin is ``/dev/null``), runs the module as ``__main__`` with :mod:`runpy` (Hydra's global state, the loggers and
the signal handlers are the server's, untouched) and exits as the interpreter does, ``atexit`` handlers first
(multiprocessing's joins its workers). So each command is still a process of its own, with its own pid, exit
status, locks and worker processes; what it skips is the interpreter's start and the imports. Tests that signal
a command, or start two together, start real ones (``subprocess.Popen``).
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: the server: reads one JSON request a line on stdin, forks, answers ``{"pid": ...}`` then ``{"status": ...}``
_SERVER = r"""
import gc, json, os, runpy, sys, traceback

started_with = dict(os.environ)
from isodream_rl.process_settings import use_huge_pages

use_huge_pages()  # as isodream_rl.cli does before it imports torch
import isodream_rl.cli  # noqa: E402, F401  (torch, TorchRL, Hydra and the trainers)
import isodream_rl.video_prediction.cli  # noqa: E402, F401

# what the imports set (os.environ.setdefault: isodream_rl.process_settings), as a command's own imports would
set_by_imports = {key: value for key, value in os.environ.items() if key not in started_with}
protocol_in, protocol_out = os.fdopen(os.dup(0), "r"), os.fdopen(os.dup(1), "w")
os.set_inheritable(protocol_in.fileno(), False)
os.set_inheritable(protocol_out.fileno(), False)
devnull = os.open(os.devnull, os.O_RDONLY)
os.dup2(devnull, 0)
os.dup2(2, 1)  # a stray print of the server goes to its stderr, not into the protocol
gc.freeze()  # the imported objects: a child's collections neither scan nor copy them
protocol_out.write("ready\n")
protocol_out.flush()


def run(request):
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update({**set_by_imports, **request["env"]})
    for fd, path in ((1, request["stdout"]), (2, request["stderr"])):
        opened = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(opened, fd)
        os.close(opened)
    protocol_in.close()
    protocol_out.close()
    try:
        if "code" in request:  # python -c CODE ARGS
            sys.argv = ["-c", *request["args"]]
            sys.path[0] = ""
            exec(compile(request["code"], "<string>", "exec"), {"__name__": "__main__"})
        else:  # python -m MODULE ARGS
            sys.argv = [request["module"], *request["args"]]
            sys.path[0] = request["cwd"]
            sys.modules.pop(request["module"], None)  # imported by the server: run afresh as __main__, as -m does
            runpy.run_module(request["module"], run_name="__main__", alter_sys=True)
    except SystemExit as exit_:  # as the interpreter reads SystemExit's code
        code = exit_.code
        if code is None:
            return 0
        if isinstance(code, int):
            return code
        print(code, file=sys.stderr)
        return 1
    except BaseException:
        traceback.print_exc()
        return 1
    return 0


for line in protocol_in:
    request = json.loads(line)
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        code = run(request)
        sys.stdout.flush()
        sys.stderr.flush()
        sys.exit(code)  # the interpreter's exit: atexit handlers, then the status
    protocol_out.write(json.dumps({"pid": pid}) + "\n")
    protocol_out.flush()
    _, status = os.waitpid(pid, 0)
    protocol_out.write(json.dumps({"status": os.waitstatus_to_exitcode(status)}) + "\n")
    protocol_out.flush()
"""

ROOT = Path(__file__).resolve().parents[1]


def _server_env() -> dict[str, str]:
    """The environment the server starts with, which its imports read (its ``sys.path`` too): this test process's
    at import, one torch thread, and this checkout first on ``PYTHONPATH`` (tests name ``env.factory`` functions
    of ``tests.*``); a command's own environment is the ``env`` of :func:`run_module`."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    env.pop("HYDRA_FULL_ERROR", None)
    return env


SERVER_ENV = _server_env()


class _Server:
    """The running server and what it has sent but :meth:`answer` has not returned yet."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", _SERVER], env=SERVER_ENV, stdin=subprocess.PIPE, stdout=subprocess.PIPE
        )
        self.pending = b""
        ready = self.answer(None)
        assert ready == "ready", f"the command server did not start ({ready!r}): see its stderr above"

    def ask(self, request: dict) -> None:
        self.process.stdin.write(json.dumps(request).encode() + b"\n")
        self.process.stdin.flush()

    def answer(self, timeout: float | None) -> str:
        """The next line the server sends; ``TimeoutError`` past ``timeout`` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        fd = self.process.stdout.fileno()
        while b"\n" not in self.pending:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([fd], [], [], wait)[0]:
                raise TimeoutError
            chunk = os.read(fd, 65536)
            if not chunk:
                raise RuntimeError(f"the command server ended (exit status {self.process.wait()})")
            self.pending += chunk
        line, _, self.pending = self.pending.partition(b"\n")
        return line.decode()


_server: _Server | None = None


def run_module(
    module: str | None,
    args: list[str],
    cwd: Path | str,
    env: dict[str, str],
    *,
    code: str | None = None,
    timeout: float | None = None,
) -> subprocess.CompletedProcess:
    """What ``subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True,
    text=True, timeout=timeout)`` returns (``-c code`` for ``module=None``), the process forked from this test
    process's server (module docstring), started at the first command. A command past ``timeout`` is killed
    (SIGKILL) and raises ``subprocess.TimeoutExpired``."""
    global _server
    if _server is None or _server.process.poll() is not None:
        _server = _Server()
    server = _server
    command = [sys.executable, *(["-m", module] if module is not None else ["-c", code]), *args]
    with tempfile.TemporaryDirectory(prefix="forked-command-") as folder:
        out, err = Path(folder, "stdout"), Path(folder, "stderr")
        request = {
            "args": list(args),
            "cwd": str(cwd),
            "env": dict(env),
            "stdout": str(out),
            "stderr": str(err),
        }
        request.update({"code": code} if module is None else {"module": module})
        server.ask(request)
        pid = json.loads(server.answer(None))["pid"]
        try:
            status = json.loads(server.answer(timeout))["status"]
        except TimeoutError:
            os.kill(pid, signal.SIGKILL)
            server.answer(None)
            raise subprocess.TimeoutExpired(
                command,
                timeout,
                output=out.read_text(errors="replace"),
                stderr=err.read_text(errors="replace"),
            ) from None
        return subprocess.CompletedProcess(
            command, status, out.read_text(errors="replace"), err.read_text(errors="replace")
        )
