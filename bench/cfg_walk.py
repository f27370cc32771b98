"""Where a setting comes from: the walk of the training configuration through the package during one run.

Runs a tiny ``isodream-train`` run (``size=tiny``, sprites, 60 env steps; ``--mode world_model``: the world model
alone) under a profiler and records every call of a function of ``isodream_rl`` that is handed the configuration
or one of its sections (an argument that is a ``RunConfig`` or one of its section dataclasses). From the calls in
the order they happen:

- ``stays``: the distinct functions the configuration passes through;
- ``files``: the distinct files of those functions;
- ``returns``: how often the walk, moving from one function to the next, enters a file it had already left;
- ``climbs``: how often a configuration-reading function calls one (directly or through functions that do not
  read it) in a higher layer of the package (the layers of ``tests/test_structure.py``).

    python bench/cfg_walk.py --json docs/results/cfg_walk.json
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1] / "tests"))
from common import provenance  # noqa: E402

from isodream_rl.run_utils.json_io import write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RL = [
    "size=tiny",
    "train.total_steps=60",
    "train.prefill_steps=50",
    "train.frames_per_batch=10",
    "logging.final_eval_episodes=0",
    "logging.progress_bar=false",
]
WORLD_MODEL = [
    "exp=world_model",
    "size=tiny",
    "world_model.updates=2",
    "world_model.episodes=2",
    "world_model.episode_length=16",
    "world_model.probe_episodes=0",
    "train.sequence_length=8",
    "train.batch_size=2",
    "logging.progress_bar=false",
]


def layer_of(path: str, package_dir: Path, layers) -> int | None:
    parts = Path(path).resolve().relative_to(package_dir).with_suffix("").parts
    top = parts[0] if parts else "__init__"
    for index, layer in enumerate(layers):
        if top in layer:
            return index
    return None


def walk(overrides: list[str]) -> dict:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf
    from test_structure import LAYERS

    import isodream_rl
    import isodream_rl.cli
    from isodream_rl.trainers import config as config_module
    from isodream_rl.trainers import run as run_module

    package_dir = Path(isodream_rl.__file__).resolve().parent
    section_types = tuple(
        {
            type(getattr(config_module.RunConfig(), f.name))
            for f in dataclasses.fields(config_module.RunConfig)
        }
        - {str, int, float, bool}
    ) + (config_module.RunConfig,)
    reads: list[tuple[str, str]] = []  # (file, function) of every read of a configuration field, in order
    originals = {}

    def recording(cls):
        original = cls.__getattribute__

        def __getattribute__(self, name):
            if not name.startswith("__"):
                caller = sys._getframe(1).f_code
                if caller.co_filename.startswith(str(package_dir)):
                    reads.append((caller.co_filename, caller.co_qualname))
            return original(self, name)

        originals[cls] = original
        cls.__getattribute__ = __getattribute__

    configs = Path(isodream_rl.cli.__file__).parent / "configs"
    with tempfile.TemporaryDirectory() as tmp:
        with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
            cfg = OmegaConf.to_object(
                compose(config_name="config", overrides=[*overrides, f"run_dir={tmp}/run"])
            )
        for cls in section_types:
            recording(cls)
        try:
            run_module.train(cfg)
        finally:
            for cls, original in originals.items():
                cls.__getattribute__ = original
    # the walk: the functions in the order they read, a function counted again when the walk comes back to it
    walk_ = [read for i, read in enumerate(reads) if i == 0 or read != reads[i - 1]]
    left, current, returns, climbs = set(), None, 0, 0
    for file, _ in walk_:
        if file != current:
            returns += file in left
            if current is not None:
                left.add(current)
                before, after = layer_of(current, package_dir, LAYERS), layer_of(file, package_dir, LAYERS)
                climbs += before is not None and after is not None and after > before
            current = file
    rel = lambda f: str(Path(f).resolve().relative_to(package_dir.parent))  # noqa: E731
    return {
        "stays": len(walk_),
        "functions": len(set(walk_)),
        "files": len({file for file, _ in walk_}),
        "returns": returns,
        "climbs": climbs,
        "walk": [f"{rel(file)}:{name}" for file, name in walk_],
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    import logging

    logging.disable(logging.INFO)
    result = {"rl": walk(RL), "world_model": walk(WORLD_MODEL), **provenance("cfg_walk.py", argv, parallel=1)}
    for mode in ("rl", "world_model"):
        r = result[mode]
        print(
            f"{mode}: {r['stays']} stays ({r['functions']} functions) in {r['files']} files, {r['returns']} returns, "
            f"{r['climbs']} climbs"
        )
    if args.json:
        write_json(args.json, result, indent=1)


if __name__ == "__main__":
    main()
