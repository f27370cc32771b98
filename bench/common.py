"""What every bench JSON records about where and from what it was made (the CPU, the commit and, where it says, the
device), and the reader of a run's CSV logs."""

from __future__ import annotations

import csv
import platform
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cpu_name() -> str:
    """The CPU model from ``/proc/cpuinfo`` (the platform's name elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def git_commit() -> str:
    """The checkout's commit, with ``-dirty`` when the work tree has uncommitted changes."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain"], cwd=ROOT, capture_output=True, text=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("-dirty" if dirty.strip() else "")


def provenance(script: str, argv: list[str] | None, *, parallel: int) -> dict:
    """Where a bench result comes from: commit, CPU, one torch thread per run, runs at a time and the command
    (``python bench/<script> <argv>``; ``argv=None`` reads ``sys.argv``)."""
    import sys

    return {
        "commit": git_commit(),
        "cpu": cpu_name(),
        "threads_per_run": 1,
        "parallel_runs": parallel,
        "command": f"python bench/{script} " + " ".join(argv if argv is not None else sys.argv[1:]),
    }


def device_provenance(device: str) -> dict:
    """What a bench JSON records about the device it ran on: the device, torch's version and, on a GPU, its name and
    the CUDA version torch was built with."""
    import torch

    device = torch.device(device)
    out = {"device": str(device), "torch": torch.__version__}
    if device.type == "cuda":
        out.update(gpu=torch.cuda.get_device_name(device), cuda=torch.version.cuda)
    return out


def read_scalar(run_dir: Path, name: str) -> list[tuple[int, float]]:
    """``(env step, value)`` rows of an ``isodream-train`` run's CSV log of scalar ``name`` (empty if absent)."""
    path = Path(run_dir) / "logs" / "train" / "scalars" / f"{name}.csv"
    if not path.exists():
        return []
    with path.open() as f:
        return [(int(float(row[0])), float(row[1])) for row in csv.reader(f) if len(row) >= 2]


def training_command(run_dir: Path) -> str:
    """``isodream-train`` with the overrides Hydra recorded for the run in ``run_dir`` (``.hydra/overrides.yaml``),
    ``run_dir=...`` left out (the folder is the user's).

    Raises:
        SystemExit: ``run_dir`` has no ``.hydra/overrides.yaml`` (not an ``isodream-train`` run folder).
    """
    import yaml

    path = Path(run_dir) / ".hydra" / "overrides.yaml"
    if not path.exists():
        raise SystemExit(
            f"{path} is missing: {run_dir} is not an isodream-train run folder (no Hydra overrides)"
        )
    overrides = yaml.safe_load(path.read_text()) or []
    return " ".join(["isodream-train", *(o for o in overrides if not o.startswith("run_dir="))])


def composed_run_config(*overrides: str):
    """The ``RunConfig`` that ``isodream-train <overrides>`` trains (Hydra's composition of the package's configs,
    as the command line does it)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import isodream_rl.cli  # noqa: F401  (registers the configuration schema)

    with initialize_config_dir(config_dir=str(ROOT / "isodream_rl" / "configs"), version_base="1.3"):
        return OmegaConf.to_object(compose(config_name="config", overrides=list(overrides)))
