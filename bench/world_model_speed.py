"""One world-model update of Iso-Dream against TorchRL's Dreamer, interleaved in one process.

Ours: :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ModelLoss` over the three-branch
:class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel`. TorchRL: ``DreamerModelLoss`` over ``ObsEncoder``,
``RSSMPrior``/``RSSMPosterior`` in ``RSSMRollout``, ``ObsDecoder`` and an MLP reward head, at equal sizes
(same cnn depth, deter, stoch, hidden, MLP units; each of our branch encoders/decoders has TorchRL's
channel widths). An update is forward + backward + gradient clipping + Adam step on a ``[B, T]`` batch of
64x64 frames. Each variant is timed in turn, round-robin, so that load from other processes hits all of
them alike; the median over ``--steps`` updates after ``--warmup`` is reported, with FLOPs counted by
``torch.utils.flop_counter`` and the achieved GFLOP/s.

Variants: precision fp32/bf16 (autocast) x memory format NCHW/channels-last, on both sides.

``ratio`` = ours / TorchRL at fp32, both channels-last (equal precision and layout);
``ratio_vs_torchrl_default`` = ours fp32 (our default, channels-last) / TorchRL fp32 NCHW (as TorchRL
users run it); ``ratio_bf16`` = both bf16 channels-last; ``ratio_fast_vs_default`` = ours in its fastest
mode / TorchRL fp32 NCHW.

    python bench/world_model_speed.py --json docs/results/world_model_speed.json
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import time
from pathlib import Path

# Huge pages for CPU tensors >= 2 MB, on both sides (PyTorch reads this at its first allocation, hence before
# `import torch`); as isodream_rl's own entry points do. THP_MEM_ALLOC_ENABLE=0 measures without.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import torch  # noqa: E402
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torch.utils.flop_counter import FlopCounterMode
from torchrl.data import Unbounded
from torchrl.modules import (
    MLP,
    ObsDecoder,
    ObsEncoder,
    RSSMPosterior,
    RSSMPrior,
    RSSMRollout,
    WorldModelWrapper,
)
from torchrl.objectives import DreamerModelLoss

from isodream_rl.modules import SIZE_PRESETS
from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel
from isodream_rl.objectives.isodream_v2 import IsoDreamV2ModelLoss
from isodream_rl.run_utils.json_io import dumps_json, write_json


def torchrl_dreamer(size: dict, action_dim: int, channels_last: bool) -> DreamerModelLoss:
    depth, stoch, deter, hidden, units = (
        size[k] for k in ("depth", "state_dim", "belief_dim", "hidden_dim", "units")
    )
    encoder = ObsEncoder(channels=depth, num_layers=4, in_channels=3)
    decoder = ObsDecoder(channels=depth, num_layers=4, latent_dim=stoch + deter)
    if channels_last:
        encoder.to(memory_format=torch.channels_last)
        decoder.to(memory_format=torch.channels_last)
    prior = RSSMPrior(
        Unbounded(shape=(action_dim,)),
        hidden_dim=hidden,
        rnn_hidden_dim=deter,
        state_dim=stoch,
        action_dim=action_dim,
    )
    posterior = RSSMPosterior(
        hidden_dim=hidden, state_dim=stoch, rnn_hidden_dim=deter, obs_embed_dim=32 * depth
    )
    transition = TensorDictSequential(
        TensorDictModule(encoder, in_keys=[("next", "pixels")], out_keys=[("next", "encoded_latents")]),
        RSSMRollout(
            TensorDictModule(
                prior,
                in_keys=["state", "belief", "action"],
                out_keys=[("next", "prior_mean"), ("next", "prior_std"), "_", ("next", "belief")],
            ),
            TensorDictModule(
                posterior,
                in_keys=[("next", "belief"), ("next", "encoded_latents")],
                out_keys=[("next", "posterior_mean"), ("next", "posterior_std"), ("next", "state")],
            ),
        ),
        TensorDictModule(
            decoder, in_keys=[("next", "state"), ("next", "belief")], out_keys=[("next", "reco_pixels")]
        ),
    )
    reward = TensorDictModule(
        MLP(in_features=stoch + deter, out_features=1, depth=2, num_cells=units, activation_class=nn.ELU),
        in_keys=[("next", "state"), ("next", "belief")],
        out_keys=[("next", "reward")],
    )
    return DreamerModelLoss(WorldModelWrapper(transition, reward), free_nats=1.0)


def make_batch(
    batch: int, time_: int, action_dim: int, size: dict, *, float_pixels: bool, channels_last: bool
):
    pixels = torch.randint(0, 256, (batch, time_, 3, 64, 64), dtype=torch.uint8)
    td = TensorDict(
        {
            "action": torch.rand(batch, time_, action_dim) * 2 - 1,
            "is_init": torch.zeros(batch, time_, 1, dtype=torch.bool),
            ("next", "reward"): torch.randn(batch, time_, 1),
        },
        [batch, time_],
    )
    if float_pixels:  # TorchRL's Dreamer reads float pixels in [0, 1] (its ToTensorImage transform)
        pixels = pixels.float() / 255
        td["state"] = torch.zeros(batch, time_, size["state_dim"])
        td["belief"] = torch.zeros(batch, time_, size["belief_dim"])
    if channels_last:
        pixels = (
            pixels.reshape(-1, 3, 64, 64).contiguous(memory_format=torch.channels_last).reshape(pixels.shape)
        )
    td["next", "pixels"] = pixels
    return td


class Variant:
    def __init__(self, name, loss, batch, precision, params_fn):
        self.name, self.loss, self.batch, self.precision = name, loss, batch, precision
        self.optimizer = torch.optim.Adam(params_fn(), lr=3e-4, eps=1e-5)
        self.times: list[float] = []
        self.flops = 0

    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast("cpu", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def step(self) -> float:
        start = time.perf_counter()
        with self._autocast():
            losses, _ = self.loss(self.batch.clone(False))
        total = sum(v for k, v in losses.items() if k.startswith("loss_"))
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(self.loss.parameters(), 100.0)
        self.optimizer.step()
        return time.perf_counter() - start

    def count_flops(self):
        with FlopCounterMode(display=False) as counter:
            self.step()
        self.flops = counter.get_total_flops()

    def profile(self) -> dict[str, float]:
        """Milliseconds of one profiled update by kind of operation (``torch.profiler`` self CPU time)."""
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            self.step()
        kinds = dict.fromkeys(PROFILE_KINDS, 0.0)
        for event in prof.key_averages():
            kinds[profile_kind(event.key)] += event.self_cpu_time_total / 1e3
        return {k: round(v, 1) for k, v in kinds.items()}


PROFILE_KINDS = ("convolution_and_relu", "matmul", "optimizer", "other")


def profile_kind(name: str) -> str:
    """Bucket of a profiler event: convolutions with their ReLUs, matrix products, the optimiser, the rest.

    Case-insensitive, so autograd's ``evaluate_function: ConvolutionBackward0`` / ``ReluBackward0`` wrappers
    land with the operations they wrap.
    """
    name = name.lower()
    if "conv" in name or "threshold" in name or "relu" in name or "clamp_min" in name:
        return "convolution_and_relu"
    if name in ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm"):
        return "matmul"
    if "optimizer" in name or "_foreach" in name or name in ("aten::addcdiv_", "aten::lerp_", "aten::sqrt"):
        return "optimizer"
    return "other"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--time", type=int, default=50)
    p.add_argument("--size", default="paper", choices=sorted(SIZE_PRESETS))
    p.add_argument("--action-dim", type=int, default=2)
    p.add_argument("--steps", type=int, default=10, help="timed updates per variant (median reported)")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument(
        "--bf16-steps",
        type=int,
        default=None,
        help="timed updates of the bf16 variants (default: --steps); on CPUs without native bf16 an update "
        "takes 10x longer, and fewer rounds keep the run short",
    )
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--variants", default="all", help="comma list, or 'all'")
    p.add_argument("--json", default=None, help="write the results here")
    p.add_argument(
        "--profile",
        action="store_true",
        help="also profile one update of each channels-last variant (time by kind of operation)",
    )
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    size = SIZE_PRESETS[args.size]
    B, T, A = args.batch_size, args.time, args.action_dim

    def ours(precision, channels_last):
        cfg = IsoDreamV2Config.from_preset(
            args.size, action_dim=A, precision=precision, channels_last=channels_last
        )
        loss = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(cfg))
        batch = make_batch(B, T, A, size, float_pixels=False, channels_last=False)
        # our model applies its own autocast (GRU and losses stay fp32), so the outer one is off
        return Variant(
            f"ours_{precision}_{'cl' if channels_last else 'nchw'}", loss, batch, "fp32", loss.parameters
        )

    def theirs(precision, channels_last):
        loss = torchrl_dreamer(size, A, channels_last)
        batch = make_batch(B, T, A, size, float_pixels=True, channels_last=channels_last)
        return Variant(
            f"torchrl_{precision}_{'cl' if channels_last else 'nchw'}",
            loss,
            batch,
            precision,
            loss.parameters,
        )

    builders = {
        "ours_fp32_cl": lambda: ours("fp32", True),
        "ours_fp32_nchw": lambda: ours("fp32", False),
        "ours_bf16_cl": lambda: ours("bf16", True),
        "torchrl_fp32_nchw": lambda: theirs("fp32", False),
        "torchrl_fp32_cl": lambda: theirs("fp32", True),
        "torchrl_bf16_cl": lambda: theirs("bf16", True),
    }
    load_before = os.getloadavg()
    names = list(builders) if args.variants == "all" else args.variants.split(",")
    variants = [builders[n]() for n in names]
    for v in variants:
        v.count_flops()
        for _ in range(args.warmup):
            v.step()
    bf16_steps = args.steps if args.bf16_steps is None else min(args.bf16_steps, args.steps)
    for i in range(args.steps):
        timed = [v for v in variants if "bf16" not in v.name or i < bf16_steps]
        for v in timed:
            v.times.append(v.step())
        print(
            f"round {i + 1}/{args.steps}: " + ", ".join(f"{v.name} {1e3 * v.times[-1]:.0f} ms" for v in timed)
        )

    profiles = {}
    if args.profile:
        for v in variants:
            if v.name.endswith("_cl"):
                profiles[v.name] = v.profile()
                print(f"profile {v.name}: {profiles[v.name]}")

    results = {}
    for v in variants:
        ms = 1e3 * statistics.median(v.times)
        results[v.name] = {
            "ms": round(ms, 1),
            "gflop": round(v.flops / 1e9, 3),
            "gflop_per_s": round(v.flops / ms / 1e6, 1),
        }
    ms = {k: r["ms"] for k, r in results.items()}
    flops = {v.name: v.flops for v in variants}

    def ratio(a, b):
        return round(ms[a] / ms[b], 3) if a in ms and b in ms else None

    ours_ms = {k: v for k, v in ms.items() if k.startswith("ours")}
    fastest = min(ours_ms, key=ours_ms.get) if ours_ms else None
    out = {
        "ours_ms": ms.get("ours_fp32_cl"),
        "torchrl_ms": ms.get("torchrl_fp32_cl"),
        "ratio": ratio("ours_fp32_cl", "torchrl_fp32_cl"),
        "ratio_vs_torchrl_default": ratio("ours_fp32_cl", "torchrl_fp32_nchw"),
        "ratio_bf16": ratio("ours_bf16_cl", "torchrl_bf16_cl"),
        "ratio_fast_vs_default": ratio(fastest, "torchrl_fp32_nchw") if fastest else None,
        "fastest_ours": fastest,
        # from the exact counts (the per-variant GFLOP are rounded)
        "flops_ratio": round(flops["ours_fp32_cl"] / flops["torchrl_fp32_cl"], 3)
        if "ours_fp32_cl" in flops and "torchrl_fp32_cl" in flops
        else None,
        "variants": results,
        # --profile: ms of one profiled update by kind of operation (self CPU time, profiler overhead included)
        **({"profile_ms": profiles} if profiles else {}),
        # 1/5/15-minute load averages before and after the run (other processes share the cores)
        "load_average": {
            "before": [round(x, 2) for x in load_before],
            "after": [round(x, 2) for x in os.getloadavg()],
        },
        "config": {
            "batch_size": B,
            "time": T,
            "size": args.size,
            **size,
            "action_dim": A,
            "steps": args.steps,
            "bf16_steps": bf16_steps,
            "warmup": args.warmup,
            "threads": torch.get_num_threads(),
            "thp_mem_alloc": os.environ["THP_MEM_ALLOC_ENABLE"],
            "torch": torch.__version__,
            "cpu": platform.processor() or platform.machine(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            # native bf16 on the CPU: without either, bf16 autocast is emulated and slower than fp32
            "cpu_avx512_bf16": getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: None)(),
            "cpu_amx": getattr(torch.cpu, "_is_amx_tile_supported", lambda: None)(),
        },
    }
    print(dumps_json(out, indent=2))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, out, indent=2)
    return out


if __name__ == "__main__":
    main()
