"""The latent probe (isodream_rl/evaluation/latent_probe.py; its command, isodream_rl/cli.py:probe_run): sprite
centres, ridge R^2, tiny models and the checkpoints of both modes of isodream-train."""

import pytest
import torch
from tensordict import TensorDict

from isodream_rl.cli import probe_run
from isodream_rl.evaluation.latent_probe import probe, ridge_cv, ridge_r2, sprite_centres
from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel
from isodream_rl.trainers import CheckpointError, train
from isodream_rl.trainers.world_model_run import load_world_model, probe_scene
from tests.test_cli import composed
from tests.test_world_model_mode import composed as composed_world_model


def test_sprite_centres_are_pixel_centroids_in_unit_coordinates():
    agent = torch.zeros(2, 64, 64, dtype=torch.bool)
    agent[0, 10:13, 20:23] = True  # centre (11, 21)
    ids = torch.zeros(2, 64, 64, dtype=torch.uint8)
    ids[0, 63, 0] = 1
    ids[1, 0, 63] = 2
    centres, visible = sprite_centres(TensorDict({"mask_agent": agent, "distractor_ids": ids}, [2]), 2)
    torch.testing.assert_close(centres[0, 0], torch.tensor([11 / 63, 21 / 63]))
    torch.testing.assert_close(centres[0, 1], torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(centres[1, 2], torch.tensor([0.0, 1.0]))
    assert visible.tolist() == [[True, True, False], [False, False, True]]
    target = torch.zeros(2, 64, 64, dtype=torch.bool)
    target[1, 30:33, 40:43] = True  # centre (31, 41), the second frame only
    truth = TensorDict({"mask_agent": agent, "distractor_ids": ids, "mask_target": target}, [2])
    centres, visible = sprite_centres(truth, 2)
    torch.testing.assert_close(centres[1, 3], torch.tensor([31 / 63, 41 / 63]))
    assert visible[:, 3].tolist() == [False, True]


def test_ridge_r2_is_one_for_a_linear_target_and_low_for_noise():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(400, 5, generator=g)
    y = x @ torch.randn(5, 2, generator=g) + 0.3
    assert ridge_r2(x[:200], y[:200], x[200:], y[200:], ridge=1e-3) > 0.999
    noise = torch.randn(400, 2, generator=g)
    assert ridge_r2(x[:200], noise[:200], x[200:], noise[200:], ridge=1.0) < 0.1


def test_probe_scores_every_branch_and_sprite_with_seeded_samples():
    torch.manual_seed(0)
    model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
    scores = probe(model, window=8, episodes=4, episode_length=16)
    names = ["agent", "distractor_0", "distractor_1", "distractor_2"]
    assert set(scores) == {f"r2_{b}_{n}" for b in ("control", "free") for n in names}
    assert all(v <= 1.0 for v in scores.values())
    # the latent samples are seeded: the same scores again, whatever the global generator did meanwhile
    torch.rand(7)
    assert probe(model, window=8, episodes=4, episode_length=16) == scores
    # the reach task's target is probed too: where the reward is
    reach = probe(model, window=8, episodes=4, episode_length=16, num_distractors=1, task="reach")
    assert set(reach) == {
        f"r2_{b}_{n}" for b in ("control", "free") for n in ("agent", "distractor_0", "target")
    }


def test_the_cli_probes_a_world_model_run_on_its_scene_and_writes_json(tmp_path):
    cfg = composed_world_model(
        "train.seed=3",
        "+env.kwargs.sprite_size=0.1",
        f"run_dir={tmp_path}",
    )
    train(cfg)
    model, saved = load_world_model(tmp_path)
    scene = probe_scene(saved)
    assert scene == {
        "task": "none",
        "num_backgrounds": 8,
        "background_seed": 3,
        "sprite_size": 0.1,
        "action_hold": 8,
        "window": 8,
        "episode_length": 16,
    }
    expected = probe(model, episodes=4, seed=1003, **scene)
    out = probe_run([str(tmp_path), "--episodes", "4", "--json", str(tmp_path / "p.json")])
    assert out == expected and (tmp_path / "p.json").stat().st_size > 0
    # one checkpoint folder of the run reads the same
    assert probe_run([str(tmp_path / "checkpoints" / "step_00000002"), "--episodes", "4"]) == expected
    torch.save({"config": {}, "model": {}}, tmp_path / "world_model.pt")
    with pytest.raises(CheckpointError, match="no longer"):
        probe_run([str(tmp_path / "world_model.pt")])


def test_the_cli_probes_the_world_model_of_a_reinforcement_learning_run(tmp_path):
    # the DreamerV2-style learner: the probe reads its world model (the default's is DreamerV3's)
    overrides = ["algo=isodream_v2", "size=tiny", "train.threads=1", "train.total_steps=20"]
    overrides += ["train.prefill_steps=10", "logging.progress_bar=false"]
    overrides += ["train.frames_per_batch=10", "logging.final_eval_episodes=0", f"run_dir={tmp_path}"]
    train(composed(*overrides))
    scores = probe_run([str(tmp_path), "--episodes", "2"])  # windows of train.sequence_length (10) steps
    assert "r2_free_agent" in scores and all(v <= 1.0 for v in scores.values())


def white_detector_trunk(model):
    """Set the trunk to one channel that fires on white pixels only (the agent's fill), pooled: a bump at
    the agent's position, whose centre is linear in the map (the agent always has the same size)."""
    first, second = model.encoder.trunk[0], model.encoder.trunk[2]
    with torch.no_grad():
        for conv in (first, second):
            conv.weight.zero_()
            conv.bias.zero_()
        first.weight[0] = 1.0 / 16  # mean of R + G + B over the 4x4 patch: 1.5 on white, <= 0.6 elsewhere
        first.bias[0] = -1.2
        second.weight[0, 0] = 1.0 / 16


def test_encoder_probe_reads_positions_off_the_trunk_and_picks_its_ridge():
    torch.manual_seed(0)
    model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
    white_detector_trunk(model)
    # a pool of 8 backgrounds, as the world-model recipe's: the white detector stays quiet on their textures
    scores = probe(model, window=8, episodes=16, episode_length=32, encoder=True, num_backgrounds=8)
    names = ["agent", "distractor_0", "distractor_1", "distractor_2"]
    layers = ("control", "free", "trunk", "embed_control", "embed_free")
    assert set(scores) == {f"r2_{b}_{n}" for b in layers for n in names}
    # the trunk sees the agent and nothing else; the features are aligned with the frames they came from
    assert scores["r2_trunk_agent"] > 0.8, scores
    assert max(scores[f"r2_trunk_distractor_{i}"] for i in range(3)) < 0.3, scores
    # 80 features, 100 samples: a noiseless linear target takes the smallest penalty, noise a large one
    x = torch.randn(100, 80, generator=torch.Generator().manual_seed(0))
    assert ridge_cv(x, x[:, :2].sum(1, keepdim=True)) == 1.0
    assert ridge_cv(x, torch.randn(100, 1, generator=torch.Generator().manual_seed(1))) >= 1e3
