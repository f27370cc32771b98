"""Where a setting comes from may move, its value may not: the configurations that README and bench commands
compose keep the values recorded in ``tests/data/composed_settings.json``.

The record was composed before the settings got one home each (the typed ``model`` section, the loss-weight
table, the branch switches of ``ALGO_BRANCHES``, the ``bench`` size preset, the ``domain`` groups). Each entry
is one command line's ``RunConfig`` as flat ``section.field`` keys, its ``model`` section as the world model it
builds (``_world_model.*``: ``make_world_model_config``) plus the behavior widths. A setting added since then
is not in the record and is not compared; the five curriculum options of the world-model mode removed since
(``world_model.static_mask_bias_schedule``, ``lambda_reco_pyramid``, ``pyramid_levels``, ``reco_pyramid_from``,
``ramp_updates``) were taken out of it with them. Two moved on purpose: ``exp=world_model`` names its
algo ``isodream_v2`` (the DreamerV2-style learner, ``isodream`` before that became DreamerV3's learner), and
``size=quickstart`` became the README's learning run (``env=sprites_reach``: no distractors, sprite size 0.15, one
background; 25000 env steps, a 500-update world-model warm-up, evaluation every 2500). The ``algo=isodream`` lines
compose the same values, now read by DreamerV3's learner (``_world_model.*`` is what ``make_world_model_config``,
the DreamerV2-style world model, makes of them), except the DreamerV2-style learner's settings, which it never read:
since each learner has its own table they are left out of its configuration (and out of those lines of the record;
``size=quickstart``'s exploration noise 0.3 among them). A configuration is compared at the values its learner
reads (:func:`~isodream_rl.trainers.learners.resolved`).
"""

import dataclasses
import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import isodream_rl.cli  # noqa: F401  (registers the config schema and the DMC envs)
from isodream_rl.cli_overrides import CONFIGS
from isodream_rl.trainers.isodream_v2 import make_world_model_config
from isodream_rl.trainers.learners import resolved

RECORD = json.loads((Path(__file__).parent / "data" / "composed_settings.json").read_text())
BEHAVIOR_WIDTHS = ("actor_units", "value_units", "attention_dim")


def _flat(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value and not f"{prefix}{key}".startswith("env.kwargs"):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def settings(line: str) -> dict:
    """The flat settings of ``isodream-train <line>``, as the record holds them."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = resolved(OmegaConf.to_object(compose(config_name="config", overrides=line.split())))
    tree = dataclasses.asdict(cfg)
    tree["model"] = {name: tree["model"][name] for name in BEHAVIOR_WIDTHS}
    tree["_world_model"] = make_world_model_config(cfg, action_dim=1).to_dict()
    return json.loads(json.dumps(_flat(tree)))


@pytest.mark.parametrize("line", sorted(RECORD))
def test_every_recorded_command_composes_the_recorded_values(line):
    now = settings(line)
    changed = {
        key: (value, now.get(key, "<gone>")) for key, value in RECORD[line].items() if now.get(key) != value
    }
    assert not changed, f"isodream-train {line}: (recorded, now) {changed}"
