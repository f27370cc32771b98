"""How long the README's test command takes: runs ``python -m pytest`` (the project's settings: two xdist workers)
and writes its wall-clock time, the counts of its closing line, the CPU and the commit to ``--json``.

    python bench/test_time.py                       # writes docs/results/test_time.json

Run it on an otherwise idle machine: the time is the machine's, with nothing else competing for its cores.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance  # noqa: E402

from isodream_rl.run_utils.json_io import dumps_json, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def counts(output: str) -> dict[str, int]:
    """``passed`` / ``failed`` / ``skipped`` / ``errors`` of pytest's closing line (0 where absent)."""
    lines = [line for line in output.splitlines() if re.search(r"\d+ (passed|failed)", line)]
    found = {key: 0 for key in ("passed", "failed", "skipped", "errors")}
    for number, key in re.findall(r"(\d+) (passed|failed|skipped|errors?)", lines[-1] if lines else ""):
        found["errors" if key.startswith("error") else key] = int(number)
    return found


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "results" / "test_time.json")
    args = parser.parse_args(argv)
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    env.setdefault("SDL_VIDEODRIVER", "offscreen")
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "pytest"], cwd=ROOT, env=env, capture_output=True, text=True, check=False
    )
    wall_s = time.monotonic() - start
    result = {
        "test_command": "python -m pytest",
        "wall_s": round(wall_s, 1),
        "returncode": done.returncode,
        **counts(done.stdout + done.stderr),
        **provenance("test_time.py", argv, parallel=2),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, result, indent=2)
    print(dumps_json(result, indent=2))
    return result


if __name__ == "__main__":
    main()
