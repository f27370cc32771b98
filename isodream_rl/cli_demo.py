"""``isodream-demo [overrides]``: ``isodream-train exp=world_model [overrides]``, the world-model recipe.

The world model alone on random-action episodes of the sprites scene, scored against the ground-truth masks
(:mod:`isodream_rl.trainers.world_model_run`). Another recorded recipe replaces the default one
(``isodream-demo exp=world_model_three_yellow``); overrides are ``isodream-train``'s
(``world_model.updates=5000 train.seed=1``). An unknown key is refused by ``isodream-train``'s check of the
overrides; an unknown flag (``--steps``) is refused here, in one line.
"""

from __future__ import annotations

import sys

from isodream_rl import cli
from isodream_rl.cli_overrides import unknown_flag
from isodream_rl.user_errors import USER_ERROR


def main(argv: list[str] | None = None) -> None:
    """Run ``isodream-train`` with ``exp=world_model`` unless ``argv`` (default: the command line) names an
    exp.

    An unknown flag is one line on stderr and exit status 2 (Hydra's own report of it is its usage text).
    """
    args = sys.argv[1:] if argv is None else list(argv)
    flag = unknown_flag(args)
    if flag is not None:
        print(
            f"isodream-demo: unknown flag {flag}; it takes isodream-train's overrides "
            "(key=value, e.g. world_model.updates=5000; isodream-train --help lists them)",
            file=sys.stderr,
        )
        sys.exit(USER_ERROR)
    if not any(arg.startswith(("exp=", "+exp=")) for arg in args):
        args.insert(0, "exp=world_model")
    sys.argv = [sys.argv[0], *args]
    cli.train()


if __name__ == "__main__":
    main()
