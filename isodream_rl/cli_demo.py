"""``isodream-demo [overrides]``: ``isodream-train exp=world_model [overrides]``, the world-model recipe.

The world model alone on random-action episodes of the sprites scene, scored against the ground-truth masks
(:mod:`isodream_rl.trainers.world_model_run`). Another recorded recipe replaces the default one
(``isodream-demo exp=world_model_three_yellow``); overrides are ``isodream-train``'s
(``world_model.updates=5000 train.seed=1``). The flags this command took before it became an alias
(``--steps`` ...) are translated in docs/results/world_model_demo.md.
"""

from __future__ import annotations

import sys

from isodream_rl import cli


def main(argv: list[str] | None = None) -> None:
    """Run ``isodream-train`` with ``exp=world_model`` unless ``argv`` (default: the command line) names an
    exp."""
    args = sys.argv[1:] if argv is None else list(argv)
    former = [arg for arg in args if arg.startswith("--") and arg.lstrip("-").split("=")[0] in FORMER_FLAGS]
    if former:
        sys.exit(
            f"isodream-demo: {former[0]} is a flag of its former command line; it takes isodream-train's "
            "overrides now (docs/results/world_model_demo.md translates each flag)"
        )
    if not any(arg.startswith(("exp=", "+exp=")) for arg in args):
        args.insert(0, "exp=world_model")
    sys.argv = [sys.argv[0], *args]
    cli.train()


#: the former flags (translated in docs/results/world_model_demo.md), refused with that pointer
FORMER_FLAGS = frozenset(
    """
    steps batch-size window size model episodes episode-length backgrounds action-hold sprite-size distractors
    distractor-colours agent-colour mask-mode static-mask-bias static-mask-bias-schedule inverse-input
    decoder-input free-decoder-input clamp-gradient free-branch-loss lambda-kl-free lambda-reco-pyramid
    pyramid-levels reco-pyramid-from ramp-updates free-nats lambda-inverse lr adam-eps precision device
    eval-every probe-episodes seed out resume
    """.split()
)


if __name__ == "__main__":
    main()
