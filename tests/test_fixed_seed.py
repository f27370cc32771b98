"""A fixed-seed run gives the same losses and weights as the recorded ones: a refactor that changes what a run
computes fails here.

Five tiny runs composed through the CLI's config (``size=tiny`` and a few cadence overrides, nothing that names a
model field, so moving a setting to another home keeps the run the same): ``mode=rl`` (60 env steps: 4 updates
after the prefill) with the default, Iso-Dream on DreamerV3's learner (``algo=isodream``), with TorchRL's DreamerV3
(``algo=torchrl_dreamer_v3``, which shares that learner's pieces), with Iso-Dream on the DreamerV2-style learner
(``algo=isodream_v2``, recorded when it was ``algo=isodream``) and with the DreamerV2 baseline, and
``mode=world_model`` (3 updates). Each records the last update's ``loss_*`` terms and gradient norms
(``grad_norm_*``, taken before any clipping: DreamerV3's learning rate warms up from 0, so its weights barely move
in 4 updates and the gradients are what shows a change of the backward pass) and the sum of |w| per model.
Recorded in ``tests/data/fixed_seed.json`` by::

    python tests/test_fixed_seed.py --write

The tolerances (relative 1e-4 on the losses, 1e-6 on the weight sums, which move little in 3-4 updates) absorb the float differences between CPUs (AVX2 against AVX512 kernels); a change
of what a run computes moves the values by far more.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import isodream_rl.cli
from isodream_rl.run_utils.checkpoint import CheckpointManager
from isodream_rl.trainers import run as run_module

RECORD = Path(__file__).parent / "data" / "fixed_seed.json"
CONFIGS = Path(isodream_rl.cli.__file__).parent / "configs"
RL = [
    "size=tiny",
    "train.total_steps=60",
    "train.prefill_steps=50",
    "train.frames_per_batch=10",
    "train.threads=1",
    "logging.log_every=1",
    "logging.final_eval_episodes=0",
    "logging.progress_bar=false",
]
RUNS = {
    "rl_isodream": ["algo=isodream", *RL],
    "rl_torchrl_dreamer_v3": ["algo=torchrl_dreamer_v3", *RL],
    "rl_isodream_v2": ["algo=isodream_v2", *RL],
    "rl_dreamerv2": ["algo=dreamerv2", *RL],
    "world_model": [
        "exp=world_model",
        "size=tiny",
        "world_model.updates=3",
        "world_model.episodes=2",
        "world_model.episode_length=16",
        "world_model.probe_episodes=0",
        "train.sequence_length=8",
        "train.batch_size=2",
        "logging.log_every=1",
        "logging.progress_bar=false",
    ],
}


def run(name: str, run_dir: Path) -> dict:
    """The run's last logged losses and gradient norms and, per model, the sum of |w| over its weights after
    training."""
    torch.manual_seed(0)
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = OmegaConf.to_object(
            compose(config_name="config", overrides=[*RUNS[name], f"run_dir={run_dir}"])
        )
    result = run_module.train(cfg)
    state = CheckpointManager(run_dir / "checkpoints").load_latest()[0]
    weights = {
        model: float(sum(t.double().abs().sum() for t in tensors.values() if t.is_floating_point()))
        for model, tensors in state["models"].items()
        if isinstance(tensors, dict)
    }
    losses = {key: value for key, value in result.metrics.items() if key.startswith(("loss_", "grad_norm_"))}
    return {"updates": result.updates, "losses": losses, "weights": weights}


@pytest.mark.parametrize("name", sorted(RUNS))
def test_a_fixed_seed_run_gives_the_recorded_losses_and_weights(name, tmp_path):
    recorded = json.loads(RECORD.read_text())[name]
    got = run(name, tmp_path)
    assert got["updates"] == recorded["updates"]
    assert set(got["losses"]) == set(recorded["losses"]) and got["losses"]
    assert set(got["weights"]) == set(recorded["weights"]) and got["weights"]
    for kind in ("losses", "weights"):
        for key, value in recorded[kind].items():
            rel = 1e-4 if kind == "losses" else 1e-6
            assert got[kind][key] == pytest.approx(value, rel=rel, abs=1e-6), f"{name}: {kind} {key}"


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_fixed_seed.py --write")
    import tempfile

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        record = {name: run(name, Path(tmp) / name) for name in sorted(RUNS)}
    RECORD.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    print(json.dumps(record, indent=1))
