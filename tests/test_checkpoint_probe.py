"""``checkpoint_probe``: the latent probe of a finished RL run's checkpoint, and ``bench/rescore_decomposition.py
--probe`` that writes it next to the decomposition."""

import json
import math
from pathlib import Path

import pytest

from isodream_rl.run_utils.checkpoint import CheckpointManager
from isodream_rl.trainers import ConfigError, train
from isodream_rl.trainers.run import checkpoint_probe
from tests.conftest import load_bench
from tests.test_isodream import isodream_run_config

SPRITES = ("agent", "distractor_0", "distractor_1", "target")  # the reach task: its target too


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A tiny finished run of the default (``algo=isodream``, windows of 8) on sprites with two distractors."""
    run_dir = tmp_path_factory.mktemp("run")
    cfg = isodream_run_config(run_dir, total_steps=40)
    cfg.env.kwargs = {"task": "reach", "max_steps": 20, "num_distractors": 2, "sprite_size": 0.15}
    train(cfg)
    return run_dir


def saved_again(run_dir: Path, into: Path, **sections) -> Path:
    """``into``: a run folder whose one checkpoint is ``run_dir``'s newest with ``sections`` (``{"env": {...}}``)
    updated in its configuration."""
    state, _ = CheckpointManager(run_dir / "checkpoints").load_latest(required_keys=("config", "models"))
    config = state["config"]
    for section, values in sections.items():
        config[section] = {**config[section], **values}
    CheckpointManager(into / "checkpoints").save(1, {"config": config, "models": state["models"]})
    return into


def test_each_branch_is_probed_for_every_sprite_of_the_runs_scene(finished_run):
    out = checkpoint_probe(finished_run, episodes=4)
    keys = {f"r2_{branch}_{sprite}" for branch in ("control", "free") for sprite in SPRITES}
    assert set(out["probe"]) == keys
    assert all(math.isfinite(value) for value in out["probe"].values())
    assert out["checkpoint"].startswith(str(finished_run / "checkpoints"))


def test_a_scene_without_distractors_probes_the_agent_and_the_target(finished_run, tmp_path):
    run_dir = saved_again(finished_run, tmp_path, env={"kwargs": {"task": "reach", "num_distractors": 0}})
    out = checkpoint_probe(run_dir, episodes=2, window=16)
    assert set(out["probe"]) == {f"r2_{b}_{s}" for b in ("control", "free") for s in ("agent", "target")}
    assert all(math.isfinite(value) for value in out["probe"].values())


@pytest.mark.parametrize(
    ("section", "change", "named"),
    [
        (
            "algo",
            {"name": "torchrl_dreamer_v3"},
            "algo=torchrl_dreamer_v3 (TorchRL's DreamerV3) has no Iso-Dream",
        ),
        ("env", {"name": "dmc_walker_walk", "kwargs": {}}, "env=dmc_walker_walk is not the sprites scene"),
    ],
)
def test_a_run_without_an_iso_dream_world_model_on_sprites_is_refused_in_one_line(
    finished_run, tmp_path, section, change, named
):
    run_dir = saved_again(finished_run, tmp_path, **{section: change})
    with pytest.raises(ConfigError) as err:
        checkpoint_probe(run_dir, episodes=2)
    assert named in str(err.value) and str(err.value).startswith(f"{run_dir} cannot be probed")
    assert "\n" not in str(err.value)


def test_the_rescore_bench_writes_the_probe_next_to_the_decomposition(finished_run, tmp_path):
    out = tmp_path / "rescore.json"
    bench = load_bench("rescore_decomposition")
    bench.main(["--runs", f"tiny={finished_run}", "--json", str(out), "--probe", "--probe-episodes", "2"])
    run = json.loads(out.read_text())["runs"]["tiny"]
    assert "iou_free_vs_distractors" in run["decomposition"]
    assert set(run["probe"]) == {
        f"r2_{branch}_{sprite}" for branch in ("control", "free") for sprite in SPRITES
    }
