"""One full update (world model + behaviour) of TorchRL's DreamerV3 against Iso-Dream (on DreamerV3's learner and on
the DreamerV2-style one) and DreamerV2, on one core or on a GPU (``--device cuda``).

Each algorithm is built as an ``isodream-train`` run builds it (``env=sprites size=<size> algo=<algo>
train.device=<device>``, the run's ``make_components``) and an update is its stepper's ``step`` on one fixed replay
sample of the size's ``B`` windows of ``T`` steps (uint8 pixels and the replay buffer's keys, a window start marked
in ``is_init``), put on the device before the timing: the world-model update, imagination from every posterior,
the actor and value updates (and, for DreamerV3, the replay-value term and the slow critic). On a GPU each update
is timed from a ``torch.cuda.synchronize`` to the next (kernels run asynchronously), and the memory it allocates
beyond what was held before it is recorded (``update_memory_gb``). The algorithms take turns, one update each per
round, so that load from other processes hits all of them alike; ``--warmup`` rounds are not timed, then the
median over ``--rounds`` rounds is reported: wall seconds per update, process CPU seconds per update, updates per
second, and the ratio of each algorithm's wall time to Iso-Dream's (``algo=isodream``) and to DreamerV2's. The JSON also records each
algorithm's trained parameters per group, the CPU (and the GPU), the commit, the torch threads and the load average
before and after. ``bench/gpu_check.py`` times its updates with :func:`measure`.

The rate inside a real run (collection included) is ``bench/update_rate.py``'s.

    python bench/update_speed.py --json docs/results/update_speed.json      # size=bench, 1 thread
    python bench/update_speed.py --size tiny --rounds 2 --warmup 1 --json /tmp/speed.json   # quick check
    python bench/update_speed.py --device cuda --size paper --json /tmp/speed_gpu.json       # on a GPU
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import device_provenance, provenance  # noqa: E402

import isodream_rl.cli  # noqa: E402, F401  (registers the config schema and the TorchRL baselines)
from isodream_rl.trainers.config import device_error  # noqa: E402
from isodream_rl.trainers.registry import make_components  # noqa: E402
from isodream_rl.trainers.run_lifecycle import probe_action_dim  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "isodream_rl" / "configs"
ALGOS = ("isodream", "isodream_v2", "dreamerv2", "torchrl_dreamer_v3")


def run_config(algo: str, size: str, *, device: str = "cpu"):
    """The ``RunConfig`` that ``isodream-train env=sprites size=<size> algo=<algo> train.device=<device>`` trains."""
    overrides = ["env=sprites", f"size={size}", f"algo={algo}", f"train.device={device}"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    return OmegaConf.to_object(cfg)


def replay_sample(batch_size: int, length: int, action_dim: int) -> TensorDict:
    """A flat ``[B * T]`` replay sample with the replay buffer's keys; one episode start inside each window."""
    n = batch_size * length
    step = torch.arange(n) % length
    return TensorDict(
        {
            "action": torch.rand(n, action_dim) * 2 - 1,
            "is_init": ((step == 0) | (step == length // 2))[:, None],
            ("next", "pixels"): torch.randint(0, 256, (n, 3, 64, 64), dtype=torch.uint8),
            ("next", "reward"): torch.randn(n, 1),
            ("next", "done"): (step == length // 2 - 1)[:, None],
            ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
            ("next", "truncated"): (step == length // 2 - 1)[:, None],
        },
        [n],
    )


def parameter_counts(components) -> dict[str, int]:
    """Trained parameters per group (a slow value copy is not counted)."""
    if hasattr(components, "learner"):  # a DreamerV3 learner: Iso-Dream's and TorchRL's
        groups = components.learner.parameter_groups()
    elif hasattr(
        components.behavior.actor_loss, "parameter_groups"
    ):  # the DreamerV2-style Iso-Dream, DreamerV2
        groups = components.behavior.actor_loss.parameter_groups()
    else:  # TorchRL's Dreamer
        groups = {name: list(module.parameters()) for name, module in components.modules().items()}
    return {name: sum(p.numel() for p in params) for name, params in groups.items()}


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued kernels (a GPU's run asynchronously: a timing must end after them)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(
    algos: list[str], *, size: str, device: str, rounds: int, warmup: int, scratch: Path
) -> dict[str, dict]:
    """Time one update of each of ``algos``, built at ``size`` on ``device``, the algorithms taking turns.

    Args:
        algos: ``algo.name`` values (``isodream-train algo=<name>``).
        size: the size group of ``isodream-train``.
        device: where the models and the replay sample are (``"cpu"``, ``"cuda"``).
        rounds: timed updates per algorithm (median reported).
        warmup: untimed updates per algorithm first.
        scratch: folder of the replay buffers' memmap files (the buffers stay empty).

    Returns:
        per algorithm: ``batch_size``, ``sequence_length``, ``horizon``, ``parameters`` (per group), ``wall_s`` and
        ``cpu_s`` per timed update, their medians, ``updates_per_s``, ``ratio_to_isodream`` /
        ``ratio_to_dreamerv2`` (where timed) and, on a GPU, ``update_memory_gb`` per timed update and its maximum.

    Raises:
        RuntimeError: an update had a non-finite loss (its time would not be an update's).
    """
    device = torch.device(device)
    entries, steppers, samples = {}, {}, {}
    for algo in algos:
        cfg = run_config(algo, size, device=str(device))
        action_dim = probe_action_dim(cfg)
        components = make_components(cfg, action_dim=action_dim, scratch_dir=Path(scratch) / algo)
        steppers[algo] = components.stepper
        # on the device already: the timing is the update's, not the host-to-device copy's
        samples[algo] = replay_sample(cfg.train.batch_size, cfg.train.sequence_length, action_dim).to(device)
        entries[algo] = {
            "batch_size": cfg.train.batch_size,
            "sequence_length": cfg.train.sequence_length,
            "horizon": cfg.algo.horizon,
            "parameters": parameter_counts(components),
            "wall_s": [],
            "cpu_s": [],
            **({"update_memory_gb": []} if device.type == "cuda" else {}),
        }
    for round_index in range(warmup + rounds):
        for algo in algos:
            synchronize(device)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
                held = torch.cuda.memory_allocated(device)
            wall, cpu = time.perf_counter(), time.process_time()
            metrics = steppers[algo].step(None, samples[algo])
            synchronize(device)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            if float(metrics["nonfinite_skipped"]):
                raise RuntimeError(f"{algo}: a non-finite update; the timing would not be an update's")
            if round_index >= warmup:
                entries[algo]["wall_s"].append(wall)
                entries[algo]["cpu_s"].append(cpu)
                if device.type == "cuda":
                    peak = torch.cuda.max_memory_allocated(device) - held
                    entries[algo]["update_memory_gb"].append(peak / 2**30)
    for entry in entries.values():
        entry["median_wall_s"] = statistics.median(entry["wall_s"])
        entry["median_cpu_s"] = statistics.median(entry["cpu_s"])
        entry["updates_per_s"] = 1.0 / entry["median_wall_s"]
        if "update_memory_gb" in entry:
            entry["max_update_memory_gb"] = max(entry["update_memory_gb"])
    for entry in entries.values():
        for reference in ("isodream", "dreamerv2"):
            if reference in entries:
                entry[f"ratio_to_{reference}"] = entry["median_wall_s"] / entries[reference]["median_wall_s"]
    return entries


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", type=lambda s: s.split(","), default=list(ALGOS))
    parser.add_argument("--size", default="bench", help="the size group of isodream-train")
    parser.add_argument(
        "--rounds", type=int, default=10, help="timed updates per algorithm (median reported)"
    )
    parser.add_argument("--warmup", type=int, default=2, help="untimed updates per algorithm first")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu", help="where the models and the sample are (cpu, cuda)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    args = parser.parse_args(argv)
    unusable = device_error(args.device, setting="--device")
    if unusable:
        parser.error(unusable)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as scratch:
        entries = measure(
            args.algos,
            size=args.size,
            device=args.device,
            rounds=args.rounds,
            warmup=args.warmup,
            scratch=Path(scratch),
        )
    result = {
        "size": args.size,
        "env": "sprites",
        "rounds": args.rounds,
        "warmup": args.warmup,
        "torch_threads": torch.get_num_threads(),
        "algos": entries,
        "load_average": {
            "before": [round(x, 2) for x in load_before],
            "after": [round(x, 2) for x in os.getloadavg()],
        },
        **provenance("update_speed.py", argv, parallel=1),
        **device_provenance(args.device),
    }
    for algo, entry in entries.items():
        ratios = ", ".join(f"{k} {v:.2f}" for k, v in entry.items() if k.startswith("ratio_to_"))
        print(f"{algo}: {entry['median_wall_s']:.3f} s per update ({entry['updates_per_s']:.2f}/s); {ratios}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
