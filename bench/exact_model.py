"""The behavior learner on the exact sprites model: does it learn, and does it recover from an early model error?

Each variant trains the learning bench's behavior (``size=bench`` widths: 128-unit actor and value, horizon 15,
the library's learning rates) on :class:`~isodream_rl.evaluation.ExactSpritesModel` with
:func:`~isodream_rl.trainers.exact_model.train_behavior_on_exact_model`, in two cases:

- ``learn``: the exact model from the first update;
- ``no_reach``: imagination without the reach event (no reach reward, no respawn: only the progress term), as a
  young world model that has not yet learnt the rare reaches; the evaluation keeps them;
- ``recover_no_reach``: both: the early error, then imagination without reaches;
- ``recover``: a reward error of 0.3 per unit action along +x for the first 250 updates, then the exact model
  (the young world model's systematic mistake; the aim is a 200-step return of at least half the scripted
  controller's by update 750).

The variants set ``algo`` fields of the library's defaults (:data:`VARIANTS`): ``isodream`` is the default's
learner, DreamerV3's (:mod:`isodream_rl.evaluation.exact_sprites_behavior`: its actor and two-hot critic on ``[s, h]``,
``DreamerV3ActorLoss`` (REINFORCE, percentile return normalisation, entropy 3e-4) and ``DreamerV3ValueLoss``
(slow critic), the exact continuation ``1 - 1/333``, ``DreamerV3Optimizer`` at the run's learning rates with its
1000-update warm-up; it reads neither ``algo.gamma`` nor the loc penalty); ``isodream_v2`` and the others are the
DreamerV2-style learner (``algo=isodream_v2``) with some of its settings changed.

Every ``--eval-every`` updates the deterministic policy plays 16 episodes of 200 steps on the exact model. Writes
``--json`` (default ``docs/results/exact_model.json``): per variant, case and seed the curve (``updates``,
``returns``, ``reaches``, ``cosine`` of the action with the direction to the target, ``entropy``,
``grad_norm_actor``, ``mean_abs_action``), the scripted and best-constant returns, the normalised final score;
plus a picture (``--png``, the JSON's path with ``.png``). Runs one variant at a time on one torch thread.

The committed JSONs name the variants as they were named when measured: ``exact_model_isodream_v2.json`` (made at
d35c722) calls ``isodream_v2`` ``default`` (it was ``algo=isodream`` then), ``exact_model_isodream.json`` calls
``isodream`` ``isodream_v3``. ``exact_model_isodream_v2.json`` also holds two variants whose code was removed after
they did not help:
``return_norm`` (the lambda-returns divided by DreamerV3's 5th-95th percentile span, TorchRL's
``PercentileValueNorm``, entropy 3e-3) and ``reinforce_return_norm`` (``IsoDreamV2ActorLoss(gradient="reinforce")``
with advantages normalised the same way, entropy 3e-4), both without the loc penalty.

    python bench/exact_model.py                                  # the committed results
    python bench/exact_model.py --variants isodream_v2 --cases recover --seeds 0 --json /tmp/e.json
    python bench/exact_model.py --variants isodream --cases learn,recover --seeds 0 --json /tmp/v3.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance  # noqa: E402

from isodream_rl.run_utils.json_io import write_json  # noqa: E402
from isodream_rl.trainers import RunConfig
from isodream_rl.trainers.exact_model import train_behavior_on_exact_model

ROOT = Path(__file__).resolve().parents[1]

#: the DreamerV2-style learner, whose settings the variants below it change
_V2 = {"name": "isodream_v2"}
#: name -> ``algo`` fields set on the library's defaults.
VARIANTS: dict[str, dict] = {
    "isodream": {"name": "isodream"},
    "isodream_v2": _V2,
    "paper": {**_V2, "actor_loc_penalty": 0.0},
    "loc_penalty_0.03": {**_V2, "actor_loc_penalty": 0.03},
    "loc_penalty_0.3": {**_V2, "actor_loc_penalty": 0.3},
    "gamma_0.95": {**_V2, "gamma": 0.95},
    "gamma_0.9": {**_V2, "gamma": 0.9},
}
#: name -> (reward error, updates with the error, extra ExactSpritesModel arguments)
CASES = {
    "learn": (0.0, 0, {}),
    "recover": (0.3, 250, {}),
    "no_reach": (0.0, 0, {"imagine_reaches": False}),
    "recover_no_reach": (0.3, 250, {"imagine_reaches": False}),
}


def bench_config(changes: dict) -> RunConfig:
    """The learning bench's behavior settings on ``[s, h]`` (the exact model has no noncontrollable branch)."""
    cfg = RunConfig()
    cfg.algo.policy_input = "controllable"
    cfg.model.actor_units = cfg.model.value_units = 128
    for name, value in changes.items():
        setattr(cfg.algo, name, value)
    return cfg


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(CASES)
    fig, axes = plt.subplots(1, len(cases), figsize=(5.5 * len(cases), 4), dpi=110, squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, case in zip(axes[0], cases):
        scripted = None
        for k, (variant, entry) in enumerate(results["variants"].items()):
            for i, run in enumerate(entry.get(case, {}).values()):
                scripted = run["scripted_return"]
                ax.plot(
                    run["updates"],
                    run["returns"],
                    color=colours[k % len(colours)],
                    linestyle="-" if i == 0 else "--",
                    label=variant if i == 0 else None,
                )
        if scripted is not None:
            ax.axhline(scripted, color="grey", linestyle=":", label="scripted")
        if case == "recover":
            ax.axvline(CASES[case][1], color="black", linewidth=0.8)
        ax.set_title(f"{case}" + (" (error 0.3 until the black line)" if case == "recover" else ""))
        ax.set_xlabel("behavior updates")
        ax.set_ylabel("200-step return (mode action)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", type=lambda s: s.split(","), default=list(VARIANTS))
    parser.add_argument("--cases", type=lambda s: s.split(","), default=list(CASES))
    parser.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1])
    parser.add_argument(
        "--single-seed-variants",
        type=lambda s: s.split(","),
        default=["loc_penalty_0.03", "loc_penalty_0.3"],
    )
    parser.add_argument("--updates", type=int, default=750)
    parser.add_argument("--eval-every", type=int, default=50)
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "results" / "exact_model.json")
    parser.add_argument("--png", type=Path, default=None)
    args = parser.parse_args(argv)
    unknown = [v for v in args.variants if v not in VARIANTS] + [c for c in args.cases if c not in CASES]
    if unknown:
        parser.error(f"unknown variants or cases {unknown}; variants: {list(VARIANTS)}, cases: {list(CASES)}")
    torch.set_num_threads(1)
    results = {"variants": {}, **provenance("exact_model.py", argv, parallel=1)}
    results.update(updates=args.updates, eval_every=args.eval_every, cases={c: CASES[c] for c in args.cases})
    for variant in args.variants:
        entry = results["variants"].setdefault(variant, {"algo": VARIANTS[variant]})
        seeds = args.seeds[:1] if variant in args.single_seed_variants else args.seeds
        for case in args.cases:
            error, error_updates, model_kwargs = CASES[case]
            for seed in seeds:
                run = train_behavior_on_exact_model(
                    bench_config(VARIANTS[variant]),
                    updates=args.updates,
                    reward_error=error,
                    error_updates=error_updates,
                    eval_every=args.eval_every,
                    seed=seed,
                    model_kwargs=model_kwargs,
                ).as_dict()
                run["normalised_final"] = (run["returns"][-1] - run["constant_return"]) / (
                    run["scripted_return"] - run["constant_return"]
                )
                entry.setdefault(case, {})[str(seed)] = run
                print(
                    f"{variant} {case} seed {seed}: final return {run['returns'][-1]:.1f} "
                    f"(normalised {run['normalised_final']:.2f}), {run['wall_s']:.0f} s",
                    flush=True,
                )
                args.json.parent.mkdir(parents=True, exist_ok=True)
                write_json(args.json, results, indent=1)
    plot(results, args.png or args.json.with_suffix(".png"))
    return results


if __name__ == "__main__":
    main()
