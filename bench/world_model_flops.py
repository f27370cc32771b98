"""FLOPs of one world-model update of each Iso-Dream learner, by module: where an update's arithmetic goes.

Builds each learner's world model and loss exactly as ``isodream-train exp=decomposition algo=<algo> size=<size>``
does (:func:`isodream_rl.trainers.world_model_run.world_model_builder`), samples one batch of windows from a few
random-action sprites episodes (``train.batch_size`` x ``train.sequence_length``, the recipe's 8 x 16), and counts
with ``torch.utils.flop_counter.FlopCounterMode``:

* ``gflop_forward``: the loss's forward, with ``forward_by_module`` (GFLOP of each world-model module, the
  encoder, each branch's decoder, the RSSMs, ...; a module's count includes its children's and the
  modules it calls, so the counts overlap; a container's children stand in for it);
* ``gflop_update``: forward and backward (the optimiser step is not counted), with ``update_by_op``
  (convolutions, their backward, matrix products).

FLOPs are exact counts, not timings: they are the same on every machine, and the run can share the cores with
anything. A wall-clock speed is ``bench/update_speed.py``'s and ``bench/world_model_speed.py``'s.

    python bench/world_model_flops.py --json docs/results/world_model_flops.json
    python bench/world_model_flops.py --algos isodream --sizes tiny --json /tmp/flops.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import composed_run_config, provenance  # noqa: E402

from isodream_rl.configs import register_resolvers  # noqa: E402
from isodream_rl.data.sprites_episodes import make_window_buffer  # noqa: E402
from isodream_rl.run_utils.json_io import write_json  # noqa: E402
from isodream_rl.trainers.learners import resolved  # noqa: E402
from isodream_rl.trainers.stepper import loss_sum  # noqa: E402
from isodream_rl.trainers.world_model_run import collect_episodes, world_model_builder  # noqa: E402

#: the learners ``mode=world_model`` trains
ALGOS = ("isodream", "isodream_v2")


def composed(algo: str, size: str, overrides: list[str]):
    """The run configuration of ``isodream-train exp=decomposition env=sprites env.kwargs.task=none algo=<algo>
    size=<size> <overrides>``, with 16-step episodes (enough for one batch of windows)."""
    line = [
        "exp=decomposition",
        "env=sprites",
        "env.kwargs.task=none",
        f"algo={algo}",
        f"size={size}",
        "world_model.episode_length=16",
        *overrides,
    ]
    return resolved(composed_run_config(*line))


def count(algo: str, size: str, overrides: list[str]) -> dict:
    """The FLOPs of one update of ``algo``'s world model at ``size``: forward by module, forward + backward by
    operation."""
    torch.manual_seed(0)
    cfg = composed(algo, size, overrides)
    batch_size, window = cfg.train.batch_size, cfg.train.sequence_length
    data = collect_episodes(cfg, episodes=batch_size, seed=0)
    buffer = make_window_buffer(data, batch_size=batch_size, window=window)
    parts = world_model_builder(algo).alone(cfg, action_dim=data["action"].shape[-1])
    batch = parts.stepper.prepare(buffer.sample().reshape(-1)).reshape(-1, window)

    def total() -> torch.Tensor:
        losses = parts.model_loss(batch)
        return loss_sum(losses[0] if isinstance(losses, tuple) else losses)

    with FlopCounterMode(display=False) as forward:
        with torch.no_grad():
            total()
    with FlopCounterMode(display=False) as update:
        total().backward()
    prefix = type(parts.model_loss).__name__ + ".world_model."
    counts = {
        name[len(prefix) :]: round(sum(ops.values()) / 1e9, 4)
        for name, ops in forward.get_flop_counts().items()
        if name.startswith(prefix)
    }
    # the world model's own modules; a child where its parent is not a module the counter saw (a container)
    by_module = {
        name: gflop
        for name, gflop in counts.items()
        if "." not in name or (name.count(".") == 1 and name.split(".")[0] not in counts)
    }
    by_op = {str(op): round(n / 1e9, 4) for op, n in update.get_flop_counts()["Global"].items()}
    return {
        "algo": algo,
        "size": size,
        "batch_size": batch_size,
        "sequence_length": window,
        "parameters": sum(p.numel() for p in parts.world_model.parameters()),
        "gflop_forward": round(forward.get_total_flops() / 1e9, 4),
        "gflop_update": round(update.get_total_flops() / 1e9, 4),
        "forward_by_module": dict(sorted(by_module.items(), key=lambda item: -item[1])),
        "update_by_op": dict(sorted(by_op.items(), key=lambda item: -item[1])),
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", type=lambda s: s.split(","), default=list(ALGOS))
    parser.add_argument("--sizes", type=lambda s: s.split(","), default=["small", "bench"])
    parser.add_argument("--override", action="append", default=[], help="extra isodream-train override")
    parser.add_argument("--json", type=Path, default=Path("docs/results/world_model_flops.json"))
    args = parser.parse_args(argv)
    unknown = sorted(set(args.algos) - set(ALGOS))
    if unknown:
        parser.error(f"unknown algos {unknown}; mode=world_model trains {list(ALGOS)}")
    torch.set_num_threads(1)
    register_resolvers()
    results = {
        "runs": [count(algo, size, args.override) for size in args.sizes for algo in args.algos],
        "overrides": args.override,
        **provenance("world_model_flops.py", argv, parallel=1),
    }
    for run in results["runs"]:
        top = ", ".join(f"{name} {gflop:g}" for name, gflop in list(run["forward_by_module"].items())[:4])
        print(
            f"{run['algo']:12s} {run['size']:6s} {run['parameters']:>9d} params  update {run['gflop_update']:.2f} "
            f"GFLOP  forward {run['gflop_forward']:.2f} ({top})"
        )
    write_json(args.json, results, indent=2)
    return results


if __name__ == "__main__":
    main()
