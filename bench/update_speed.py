"""One full update (world model + behaviour) of TorchRL's DreamerV3 against Iso-Dream (on DreamerV3's learner and on
the DreamerV2-style one) and DreamerV2, on one core or on a GPU (``--device cuda``).

Each algorithm is built as an ``isodream-train`` run builds it (``env=<env> size=<size> algo=<algo>
train.device=<device>``, the run's ``make_components``; ``--env`` is ``sprites`` unless given, ``sprites_reach``
builds the quickstart's learner as it trains, without the static branch) and an update is its stepper's ``step``
on one fixed replay sample of the size's ``B`` windows of ``T`` steps (uint8 pixels and the replay buffer's keys,
a window start marked in ``is_init``), put on the device before the timing: the world-model update, imagination from every posterior,
the actor and value updates (and, for DreamerV3, the replay-value term and the slow critic). On a GPU each update
is timed from a ``torch.cuda.synchronize`` to the next (kernels run asynchronously), and the memory it allocates
beyond what was held before it is recorded (``update_memory_gb``). The algorithms take turns, one update each per
round, so that load from other processes hits all of them alike; ``--warmup`` rounds are not timed, then the
median over ``--rounds`` rounds is reported: wall seconds per update, process CPU seconds per update, updates per
second, and the ratio of each algorithm's wall time to Iso-Dream's (``algo=isodream``) and to DreamerV2's. The JSON also records each
algorithm's trained parameters per group (``parameters.world_model``: the world model's count), the CPU's model name
(``/proc/cpuinfo``'s, as ``lscpu`` prints it) and the GPU, the commit, the torch threads and the load average before
and after, and ``THP_MEM_ALLOC_ENABLE`` (PyTorch's huge pages for tensors of 2 MB and more, set to ``1`` unless
exported, as a training run sets it). ``bench/gpu_check.py`` times its updates with :func:`measure`.

``--fast-paths`` picks how the learners with CPU fast paths (those that read ``model.fast_paths``: the default
``algo=isodream`` and its ablations, the DreamerV2-style learner) are built: ``on`` (their default, timed under
their own name), ``off`` (``model.fast_paths=false``, the reference forms, timed as ``<algo>[fast_paths=false]``)
or ``both``, one entry each, taking turns with the others; each entry records its ``algo`` and ``fast_paths``
(``null`` for a learner without the switch). ``ratio_to_isodream`` of ``isodream[fast_paths=false]`` is then the
fast paths' gain.

The rate inside a real run (collection included) is ``bench/update_rate.py``'s.

    python bench/update_speed.py --json docs/results/update_speed.json      # size=bench, 1 thread
    python bench/update_speed.py --algos isodream,torchrl_dreamer_v3 --fast-paths both \
        --json docs/results/update_speed.json                                # the default both ways, size=bench
    python bench/update_speed.py --size quickstart --algos isodream,torchrl_dreamer_v3 --fast-paths both \
        --json docs/results/update_speed_quickstart.json
    python bench/update_speed.py --size quickstart --env sprites_reach --algos isodream --fast-paths both \
        --json /tmp/speed_quickstart.json                                    # as the quickstart trains
    python bench/update_speed.py --size tiny --rounds 2 --warmup 1 --json /tmp/speed.json   # quick check
    python bench/update_speed.py --device cuda --size paper --json /tmp/speed_gpu.json       # on a GPU
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

# Huge pages for CPU tensors >= 2 MB, for every learner timed (PyTorch reads this at its first allocation, hence
# before `import torch`), as a training run has them (isodream_rl.process_settings.use_huge_pages, called by the
# entry points); THP_MEM_ALLOC_ENABLE=0 measures without. Where torch was imported first (this module loaded by
# another), the process keeps what it had, recorded as null.
THP_MEM_ALLOC = None if "torch" in sys.modules else os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import composed_run_config, device_provenance, provenance  # noqa: E402

import isodream_rl.cli  # noqa: E402, F401  (registers the config schema and the TorchRL baselines)
from isodream_rl.run_utils.json_io import write_json  # noqa: E402
from isodream_rl.trainers.config import device_error  # noqa: E402
from isodream_rl.trainers.learners import learner_of  # noqa: E402
from isodream_rl.trainers.registry import make_components  # noqa: E402
from isodream_rl.trainers.run_lifecycle import probe_action_dim  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ALGOS = ("isodream", "isodream_v2", "dreamerv2", "torchrl_dreamer_v3")
#: ``--fast-paths`` choices: the ``model.fast_paths`` values timed for a learner that reads it.
FAST_PATHS = {"on": (True,), "off": (False,), "both": (True, False)}


def run_config(
    algo: str, size: str, *, device: str = "cpu", overrides: tuple[str, ...] = (), env: str = "sprites"
):
    """The ``RunConfig`` that ``isodream-train env=<env> size=<size> algo=<algo> train.device=<device>
    <overrides>`` trains, without its world-model warm-up (``train.world_model_warmup=0``: the size's first updates
    train the world model alone, e.g. 500 of the quickstart's 4900; a timed update is one of the others, world
    model and behaviour)."""
    overrides = [
        f"env={env}",
        f"size={size}",
        f"algo={algo}",
        f"train.device={device}",
        "train.world_model_warmup=0",
        *overrides,
    ]
    return composed_run_config(*overrides)


def has_fast_paths(algo: str) -> bool:
    """Whether the learner of ``algo=<algo>`` reads ``model.fast_paths`` (has CPU fast paths to switch off)."""
    return "model.fast_paths" in learner_of(algo).values


def variants(algos: list[str], fast_paths: str) -> list[tuple[str, str, bool | None]]:
    """``(label, algo, fast_paths)`` of each build to time, in ``algos``' order: a learner with fast paths once per
    value of ``FAST_PATHS[fast_paths]`` (labelled ``<algo>`` when on, ``<algo>[fast_paths=false]`` when off), any
    other once as it is (``fast_paths`` ``None``).

    Raises:
        ValueError: ``fast_paths`` is not a key of :data:`FAST_PATHS`, or an algorithm is listed twice.
    """
    if fast_paths not in FAST_PATHS:
        raise ValueError(f"fast_paths must be one of {sorted(FAST_PATHS)}, got {fast_paths!r}")
    repeated = sorted({algo for algo in algos if algos.count(algo) > 1})
    if repeated:
        raise ValueError(f"algorithms listed more than once: {repeated}")
    out = []
    for algo in algos:
        if not has_fast_paths(algo):
            out.append((algo, algo, None))
            continue
        for value in FAST_PATHS[fast_paths]:
            out.append((algo if value else f"{algo}[fast_paths=false]", algo, value))
    return out


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
    algos: list[str],
    *,
    size: str,
    device: str,
    rounds: int,
    warmup: int,
    scratch: Path,
    fast_paths: str = "on",
    env: str = "sprites",
) -> dict[str, dict]:
    """Time one update of each of ``algos``, built at ``size`` on ``device``, the algorithms taking turns.

    Args:
        algos: ``algo.name`` values (``isodream-train algo=<name>``).
        size: the size group of ``isodream-train``.
        device: where the models and the replay sample are (``"cpu"``, ``"cuda"``).
        rounds: timed updates per algorithm (median reported).
        warmup: untimed updates per algorithm first.
        scratch: folder of the replay buffers' memmap files (the buffers stay empty).
        fast_paths: ``"on"``, ``"off"`` or ``"both"``: the ``model.fast_paths`` values of the learners that read
            it (:func:`variants`).
        env: the env group of ``isodream-train`` (``sprites``; ``sprites_reach``, the quickstart's, builds the
            learner as the quickstart trains it: without the static branch).

    Returns:
        per label (:func:`variants`: the algorithm's name, or ``<algo>[fast_paths=false]``): ``algo``,
        ``fast_paths``, ``batch_size``, ``sequence_length``, ``horizon``, ``parameters`` (per group), ``wall_s`` and
        ``cpu_s`` per timed update, their medians, ``updates_per_s``, ``ratio_to_isodream`` /
        ``ratio_to_dreamerv2`` (where timed) and, on a GPU, ``update_memory_gb`` per timed update and its maximum.

    Raises:
        RuntimeError: an update had a non-finite loss (its time would not be an update's).
    """
    device = torch.device(device)
    entries, steppers, samples = {}, {}, {}
    for label, algo, fast in variants(list(algos), fast_paths):
        overrides = () if fast is None else (f"model.fast_paths={str(fast).lower()}",)
        cfg = run_config(algo, size, device=str(device), overrides=overrides, env=env)
        action_dim = probe_action_dim(cfg)
        components = make_components(cfg, action_dim=action_dim, scratch_dir=Path(scratch) / label)
        steppers[label] = components.stepper
        # on the device already: the timing is the update's, not the host-to-device copy's
        samples[label] = replay_sample(cfg.train.batch_size, cfg.train.sequence_length, action_dim).to(device)
        entries[label] = {
            "algo": algo,
            "fast_paths": fast,
            "batch_size": cfg.train.batch_size,
            "sequence_length": cfg.train.sequence_length,
            "horizon": cfg.algo.horizon,
            "parameters": parameter_counts(components),
            "wall_s": [],
            "cpu_s": [],
            **({"update_memory_gb": []} if device.type == "cuda" else {}),
        }
    for round_index in range(warmup + rounds):
        for label in entries:
            synchronize(device)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
                held = torch.cuda.memory_allocated(device)
            wall, cpu = time.perf_counter(), time.process_time()
            metrics = steppers[label].step(None, samples[label])
            synchronize(device)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            if float(metrics["nonfinite_skipped"]):
                raise RuntimeError(f"{label}: a non-finite update; the timing would not be an update's")
            if round_index >= warmup:
                entries[label]["wall_s"].append(wall)
                entries[label]["cpu_s"].append(cpu)
                if device.type == "cuda":
                    peak = torch.cuda.max_memory_allocated(device) - held
                    entries[label]["update_memory_gb"].append(peak / 2**30)
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
        "--env",
        default="sprites",
        help="the env group of isodream-train: sprites (the default, the committed results') or sprites_reach "
        "(the quickstart's, which builds no static branch)",
    )
    parser.add_argument(
        "--fast-paths",
        choices=sorted(FAST_PATHS),
        default="on",
        help="model.fast_paths of the learners that read it: on (their default), off (the reference forms) or "
        "both (an entry each)",
    )
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
            fast_paths=args.fast_paths,
            env=args.env,
        )
    result = {
        "size": args.size,
        "fast_paths": args.fast_paths,
        "env": args.env,
        "rounds": args.rounds,
        "warmup": args.warmup,
        "torch_threads": torch.get_num_threads(),
        "thp_mem_alloc": THP_MEM_ALLOC,
        "algos": entries,
        "load_average": {
            "before": [round(x, 2) for x in load_before],
            "after": [round(x, 2) for x in os.getloadavg()],
        },
        **provenance("update_speed.py", argv, parallel=1),
        **device_provenance(args.device),
    }
    for label, entry in entries.items():
        ratios = ", ".join(f"{k} {v:.2f}" for k, v in entry.items() if k.startswith("ratio_to_"))
        print(
            f"{label}: {entry['median_wall_s']:.3f} s per update ({entry['updates_per_s']:.2f}/s); {ratios}; "
            f"world model {entry['parameters']['world_model'] / 1e6:.2f} M parameters"
        )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, result, indent=2)
    return result


if __name__ == "__main__":
    main()
