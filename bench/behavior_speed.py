"""One actor + value update of Iso-Dream against TorchRL's Dreamer, and Iso-Dream's acting latency.

Update. Ours: :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ActorLoss` + :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ValueLoss`
over :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2Imagination` (horizon ``L``, attention window ``tau``) of the
three-branch :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel`. TorchRL: ``DreamerActorLoss`` (TD(lambda)
value estimator) + ``DreamerValueLoss`` over a ``DreamerEnv`` built from ``RSSMPrior`` and an MLP reward
head, with ``DreamerActor`` and an MLP value. Both at equal sizes: the same RSSM (stoch, deter, hidden) and
MLP/head widths (``units``; actor 4 layers, value 3, reward 2, as the authors and TorchRL). An update is
imagination from ``N = B * T`` start states for ``L`` steps, the actor loss, the value loss on the
(detached) imagined trajectory, backward and one Adam step for the actor and one for the value network.
Our rollout also runs the noncontrollable branch ``tau - 1`` steps beyond ``L`` for the attention window
(``--policy-input attention``) and reads it in the reward head (every mode but ``controllable``).

Each variant is timed in turn, round-robin, so that load from other processes hits all of them alike; the
median over ``--steps`` updates after ``--warmup`` is reported. Variants: precision fp32/bf16 on both
sides (ours: ``IsoDreamV2Config(precision=...)``, whose autocast covers every behavior MLP; TorchRL: an
outer CPU bf16 autocast around the losses).

Acting: one env step of :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2Policy` (encode a 64x64 frame, filter both
branches, imagine the ``tau - 1`` future noncontrollable states, attention, actor sample) on the fp32
model, at batch 1 and 8, median wall-clock ms over ``--acting-steps`` calls (process CPU ms also given).

``ratio`` = ours / TorchRL at fp32 (equal precision); ``ratio_bf16`` = both bf16.

    python bench/behavior_speed.py --threads 1 --json docs/results/behavior_speed.json
    python bench/behavior_speed.py --size tiny --batch-size 2 --time 4 --steps 2 --warmup 1  # quick check
"""

from __future__ import annotations

import argparse
import contextlib
import platform
import statistics
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential, TensorDictModule
from torch import nn
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.modules import MLP, DreamerActor, RSSMPrior, SafeSequential, TanhNormal, WorldModelWrapper
from torchrl.objectives import DreamerActorLoss, DreamerValueLoss
from torchrl.objectives.utils import ValueEstimators

from isodream_rl.modules import SIZE_PRESETS, PolicyInput
from isodream_rl.modules.isodream_v2 import (
    IsoDreamV2Actor,
    IsoDreamV2Config,
    IsoDreamV2Policy,
    IsoDreamV2Value,
    IsoDreamV2WorldModel,
)
from isodream_rl.objectives.isodream_v2 import IsoDreamV2ActorLoss, IsoDreamV2Imagination, IsoDreamV2ValueLoss
from isodream_rl.run_utils.json_io import dumps_json, write_json

LR = 8e-5
GAMMA, LMBDA = 0.99, 0.95


class _ConcatMLP(nn.Module):
    """An MLP on ``[state, belief]``: TorchRL's ``MLP`` takes one input tensor."""

    def __init__(self, mlp: nn.Module):
        super().__init__()
        self.mlp = mlp

    def forward(self, state: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([state, belief], dim=-1))


def torchrl_behavior(size: dict, action_dim: int, horizon: int):
    """TorchRL's Dreamer actor and value losses at ``size``; returns ``(actor_loss, value_loss)``."""
    stoch, deter, hidden, units = (size[k] for k in ("state_dim", "belief_dim", "hidden_dim", "units"))
    action_spec = Bounded(-1, 1, (action_dim,))
    prior = RSSMPrior(
        action_spec, hidden_dim=hidden, rnn_hidden_dim=deter, state_dim=stoch, action_dim=action_dim
    )
    transition = SafeSequential(
        TensorDictModule(prior, in_keys=["state", "belief", "action"], out_keys=["_", "_", "state", "belief"])
    )

    def head(depth: int, out_key: str) -> TensorDictModule:
        mlp = MLP(
            in_features=stoch + deter, out_features=1, depth=depth, num_cells=units, activation_class=nn.ELU
        )
        return TensorDictModule(_ConcatMLP(mlp), in_keys=["state", "belief"], out_keys=[out_key])

    env = DreamerEnv(
        WorldModelWrapper(transition, head(2, "reward")),
        prior_shape=torch.Size([stoch]),
        belief_shape=torch.Size([deter]),
    )
    env.action_spec = action_spec
    env.observation_spec = Composite(state=Unbounded((stoch,)), belief=Unbounded((deter,)))
    env.reward_spec = Unbounded((1,))
    actor = ProbabilisticTensorDictSequential(
        TensorDictModule(
            DreamerActor(out_features=action_dim, depth=4, num_cells=units),
            in_keys=["state", "belief"],
            out_keys=["loc", "scale"],
        ),
        ProbabilisticTensorDictModule(
            in_keys=["loc", "scale"],
            out_keys=["action"],
            distribution_class=TanhNormal,
            distribution_kwargs={"tanh_loc": True},
            default_interaction_type="random",
        ),
    )
    value = head(3, "state_value")
    actor_loss = DreamerActorLoss(actor, value, env, imagination_horizon=horizon)
    actor_loss.make_value_estimator(ValueEstimators.TDLambda, gamma=GAMMA, lmbda=LMBDA)
    return actor_loss, DreamerValueLoss(value)


class Variant:
    """One side at one precision: its losses, optimisers, start batch and timings."""

    def __init__(self, name: str, step_fn, precision: str):
        self.name, self._step_fn, self.precision = name, step_fn, precision
        self.times: list[float] = []

    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast("cpu", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def step(self) -> float:
        start = time.perf_counter()
        with self._autocast():
            self._step_fn()
        return time.perf_counter() - start


def ours_variant(
    args, size: dict, precision: str
) -> tuple[Variant, IsoDreamV2WorldModel, PolicyInput, IsoDreamV2Actor]:
    cfg = IsoDreamV2Config.from_preset(
        args.size,
        action_dim=args.action_dim,
        reward_uses_free=args.policy_input != "controllable",
        precision=precision,
    )
    wm = IsoDreamV2WorldModel(cfg)
    pin = PolicyInput.for_world_model(wm, mode=args.policy_input, window=args.tau, width=args.attention_width)
    imagination = IsoDreamV2Imagination(wm, pin, horizon=args.horizon, attention_window=args.attention_window)
    value_loss = IsoDreamV2ValueLoss(
        IsoDreamV2Value(in_features=pin.out_features, num_cells=size["units"]), imagination
    )
    actor = IsoDreamV2Actor(in_features=pin.out_features, action_dim=args.action_dim, num_cells=size["units"])
    actor_loss = IsoDreamV2ActorLoss(actor, imagination, value_loss, gamma=GAMMA, lmbda=LMBDA)
    groups = actor_loss.parameter_groups()
    opt_actor, opt_value = torch.optim.Adam(groups["actor"], lr=LR), torch.optim.Adam(groups["value"], lr=LR)
    n = args.batch_size * args.time
    start = TensorDict(
        {("next", k): torch.randn(n, v.shape[-1]) for k, v in wm.initial_state((1,)).items()}, [n]
    )

    def step():
        losses, imagined = actor_loss(start)
        value_losses, _ = value_loss(imagined)
        opt_actor.zero_grad(set_to_none=True)
        opt_value.zero_grad(set_to_none=True)
        # the value loss reads the detached trajectory, so one backward gives each group its own gradient
        (losses["loss_actor"] + value_losses["loss_value"]).backward()
        opt_actor.step()
        opt_value.step()

    # the world model applies its own autocast (the GRU and the losses stay fp32), so the outer one is off
    return Variant(f"ours_{precision}", step, "fp32"), wm, pin, actor


def torchrl_variant(args, size: dict, precision: str) -> Variant:
    actor_loss, value_loss = torchrl_behavior(size, args.action_dim, args.horizon)
    n = args.batch_size * args.time
    start = TensorDict(
        {"state": torch.randn(n, size["state_dim"]), "belief": torch.randn(n, size["belief_dim"])}, [n]
    )
    actor_loss(start[:2])  # initialise any lazy modules before the optimisers collect the parameters
    opt_actor = torch.optim.Adam(actor_loss.actor_model.parameters(), lr=LR)
    opt_value = torch.optim.Adam(value_loss.value_model.parameters(), lr=LR)

    def step():
        losses, imagined = actor_loss(start)
        opt_actor.zero_grad(set_to_none=True)
        losses["loss_actor"].backward()
        opt_actor.step()
        value_losses, _ = value_loss(imagined.detach())
        opt_value.zero_grad(set_to_none=True)
        value_losses["loss_value"].backward()
        opt_value.step()

    return Variant(f"torchrl_{precision}", step, precision)


def acting_latency(policy: IsoDreamV2Policy, batches: list[int], steps: int, warmup: int) -> dict:
    """Median wall and process-CPU ms of one ``policy`` call per batch size, timed round-robin."""
    inputs = {}
    for n in batches:
        td = policy.make_tensordict_primer().primers.zero().expand(n).clone()
        td.update(
            {
                "pixels": torch.randint(0, 256, (n, 3, 64, 64), dtype=torch.uint8),
                "is_init": torch.zeros(n, 1, dtype=torch.bool),
            }
        )
        inputs[n] = td
    wall: dict[int, list[float]] = {n: [] for n in batches}
    cpu: dict[int, list[float]] = {n: [] for n in batches}
    for i in range(warmup + steps):
        for n in batches:
            w, c = time.perf_counter(), time.process_time()
            policy(inputs[n])
            if i >= warmup:
                wall[n].append(1e3 * (time.perf_counter() - w))
                cpu[n].append(1e3 * (time.process_time() - c))
    return {
        f"batch{n}": {
            "ms": round(statistics.median(wall[n]), 2),
            "cpu_ms": round(statistics.median(cpu[n]), 2),
        }
        for n in batches
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--time", type=int, default=50, help="T; imagination starts from B * T states")
    p.add_argument("--size", default="paper", choices=sorted(SIZE_PRESETS))
    p.add_argument("--action-dim", type=int, default=2)
    p.add_argument("--horizon", type=int, default=15, help="imagination horizon L")
    p.add_argument("--tau", type=int, default=5, help="attention window tau")
    p.add_argument("--policy-input", default="attention", choices=["attention", "controllable", "concat"])
    p.add_argument("--attention-window", default="start", choices=["start", "per_step"])
    p.add_argument("--attention-width", type=int, default=500, help="the attention's projection width")
    p.add_argument("--precisions", default="fp32,bf16", help="comma list of fp32, bf16")
    p.add_argument("--steps", type=int, default=10, help="timed updates per variant (median reported)")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--acting-steps", type=int, default=100, help="timed policy calls per batch size")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--json", default=None, help="write the results here")
    args = p.parse_args(argv)
    precisions = args.precisions.split(",")
    if not set(precisions) <= {"fp32", "bf16"} or not precisions:
        p.error(f"--precisions takes fp32 and/or bf16, got {args.precisions!r}")
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    size = SIZE_PRESETS[args.size]

    variants, acting_model = [], None
    for precision in precisions:
        ours, wm, pin, actor = ours_variant(args, size, precision)
        if precision == "fp32" or acting_model is None:
            acting_model = (precision, wm, pin, actor)
        variants += [ours, torchrl_variant(args, size, precision)]
    for v in variants:
        for _ in range(args.warmup):
            v.step()
    for i in range(args.steps):
        for v in variants:
            v.times.append(v.step())
        print(
            f"round {i + 1}/{args.steps}: "
            + ", ".join(f"{v.name} {1e3 * v.times[-1]:.0f} ms" for v in variants),
            flush=True,
        )

    acting_precision, wm, pin, actor = acting_model
    acting = acting_latency(IsoDreamV2Policy(wm, actor, pin), [1, 8], args.acting_steps, warmup=5)

    results = {
        v.name: {
            "ms": round(1e3 * statistics.median(v.times), 1),
            "all_ms": [round(1e3 * t) for t in v.times],
        }
        for v in variants
    }
    ms = {k: r["ms"] for k, r in results.items()}

    def ratio(a, b):
        return round(ms[a] / ms[b], 3) if a in ms and b in ms else None

    out = {
        "ours_ms": ms.get("ours_fp32"),
        "torchrl_ms": ms.get("torchrl_fp32"),
        "ratio": ratio("ours_fp32", "torchrl_fp32"),
        "ratio_bf16": ratio("ours_bf16", "torchrl_bf16"),
        "acting_ms_batch1": acting["batch1"]["ms"],
        "acting_ms_batch8": acting["batch8"]["ms"],
        "variants": results,
        "acting": {**acting, "precision": acting_precision},
        "config": {
            "batch_size": args.batch_size,
            "time": args.time,
            "starts": args.batch_size * args.time,
            "horizon": args.horizon,
            "tau": args.tau,
            "policy_input": args.policy_input,
            "attention_window": args.attention_window,
            "attention_width": args.attention_width,
            "size": args.size,
            **size,
            "action_dim": args.action_dim,
            "steps": args.steps,
            "warmup": args.warmup,
            "acting_steps": args.acting_steps,
            "threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "cpu": platform.processor() or platform.machine(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        },
    }
    print(dumps_json(out, indent=2))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, out, indent=2)
    return out


if __name__ == "__main__":
    main()
