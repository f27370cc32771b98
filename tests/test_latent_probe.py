"""The latent probe (isodream_rl/recipes/latent_probe.py): sprite centres, ridge R^2, a run on a tiny model."""

import torch
from tensordict import TensorDict

from isodream_rl.modules import IsoDreamWorldModel, WorldModelConfig
from isodream_rl.recipes.latent_probe import main, probe, ridge_cv, ridge_r2, sprite_centres


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


def test_ridge_r2_is_one_for_a_linear_target_and_low_for_noise():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(400, 5, generator=g)
    y = x @ torch.randn(5, 2, generator=g) + 0.3
    assert ridge_r2(x[:200], y[:200], x[200:], y[200:], ridge=1e-3) > 0.999
    noise = torch.randn(400, 2, generator=g)
    assert ridge_r2(x[:200], noise[:200], x[200:], noise[200:], ridge=1.0) < 0.1


def test_probe_scores_every_branch_and_sprite_and_the_cli_writes_json(tmp_path):
    torch.manual_seed(0)
    model = IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=2))
    scores = probe(model, window=8, episodes=4, episode_length=16)
    names = ["agent", "distractor_0", "distractor_1", "distractor_2"]
    assert set(scores) == {f"r2_{b}_{n}" for b in ("control", "free") for n in names}
    assert all(v <= 1.0 for v in scores.values())
    # the latent samples are seeded: the same scores again, whatever the global generator did meanwhile
    torch.rand(7)
    assert probe(model, window=8, episodes=4, episode_length=16) == scores
    path = tmp_path / "model.pt"
    torch.save({"config": model.config.to_dict(), "model": model.state_dict()}, path)
    out = main([str(path), "--episodes", "4", "--window", "8", "--json", str(tmp_path / "p.json")])
    assert set(out) == set(scores) and (tmp_path / "p.json").stat().st_size > 0


def test_the_cli_probes_on_the_scene_the_checkpoint_was_trained_on(tmp_path):
    torch.manual_seed(0)
    model = IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=2))
    scene = {"num_backgrounds": 2, "background_seed": 5, "action_hold": 4, "window": 8, "episode_length": 16}
    path = tmp_path / "model.pt"
    torch.save({"config": model.config.to_dict(), "model": model.state_dict(), "scene": scene}, path)
    expected = probe(model, episodes=4, **scene)
    assert main([str(path), "--episodes", "4"]) == expected
    # a flag overrides the checkpoint's value
    assert main([str(path), "--episodes", "4", "--background-seed", "6"]) == probe(
        model, episodes=4, **{**scene, "background_seed": 6}
    )
    assert probe(model, episodes=4, **{**scene, "background_seed": 6}) != expected
    # the sprite size is part of the scene: a checkpoint trained on larger sprites is probed on them
    bigger = {**scene, "sprite_size": 0.1}
    torch.save({"config": model.config.to_dict(), "model": model.state_dict(), "scene": bigger}, path)
    assert main([str(path), "--episodes", "4"]) == probe(model, episodes=4, **bigger)
    assert probe(model, episodes=4, **bigger) != expected


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
    model = IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=2))
    white_detector_trunk(model)
    scores = probe(model, window=8, episodes=16, episode_length=32, encoder=True)
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
