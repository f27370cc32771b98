"""The world-model recipe (``isodream-demo``), at a tiny size: it trains, scores the masks and writes its outputs."""

import argparse
import json

import pytest
import torch

from isodream_rl.recipes.sprites_data import collect_sprites_episodes
from isodream_rl.recipes.world_model_demo import main, parse_schedule, ramp_weight, schedule_value

# two updates on two short episodes: the arguments every tiny demo run here shares
TINY_RUN = ("--steps", "2", "--episodes", "2", "--episode-length", "16", "--window", "8", "--batch-size", "2")


def test_demo_writes_picture_scores_checkpoint_and_csv(tmp_path):
    summary = main(
        [
            "--steps",
            "3",
            "--episodes",
            "2",
            "--episode-length",
            "16",
            "--window",
            "8",
            "--batch-size",
            "2",
            "--size",
            "tiny",
            "--eval-every",
            "2",
            "--precision",
            "fp32",
            "--adam-eps",
            "1e-7",
            "--out",
            str(tmp_path),
        ]
    )
    assert (tmp_path / "branches.png").stat().st_size > 0
    saved_model = torch.load(tmp_path / "world_model.pt", map_location="cpu")
    assert saved_model["step"] == 3 and set(saved_model) == {"config", "model", "optimizer", "step", "scene"}
    assert saved_model["scene"] == {
        "num_backgrounds": 8,
        "background_seed": 0,
        "action_hold": 8,
        "sprite_size": 0.06,
        "num_distractors": 3,
        "distractor_colours": None,
        "agent_colour": "white",
        "window": 8,
        "episode_length": 16,
    }
    assert saved_model["optimizer"]["param_groups"][0]["eps"] == 1e-7
    assert not list(tmp_path.glob("*.tmp")), "a temporary checkpoint was left behind"
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["updates"] == 3 and 0.0 <= saved["iou_control_vs_agent"] <= 1.0
    for name in (
        "iou_free_vs_distractors",
        "free_covers_distractor_2",
        "reco_error_distractor_0",
        "reco_error_agent",
        "free_on_background",
        "control_on_background",
    ):
        assert 0.0 <= saved[name] <= 3.0 and 0.0 <= saved[f"train_{name}"] <= 3.0, name
    # the final latent probe: every branch x sprite, an R^2 (at most 1), in the summary and the CSV log
    probes = {k for k in saved if k.startswith("probe_r2_")}
    sprites = ("agent", "distractor_0", "distractor_1", "distractor_2")
    layers = ("control", "free", "trunk", "embed_control", "embed_free")
    assert probes == {f"probe_r2_{b}_{n}" for b in layers for n in sprites}
    assert all(saved[k] <= 1.0 for k in probes)
    assert list(tmp_path.rglob("probe_r2_free_agent.csv"))
    assert summary["png"] == str(tmp_path / "branches.png")
    assert list(tmp_path.rglob("*.csv")), "the CSV logger wrote nothing"


def test_held_random_actions_make_the_agent_travel():
    jitter = collect_sprites_episodes(episodes=4, steps=32, seed=3)
    held = collect_sprites_episodes(episodes=4, steps=32, seed=3, action_hold=8)
    actions = held["action"].reshape(4, 4, 8, 2)
    assert (actions == actions[:, :, :1]).all(), "an action must stay for action_hold steps"
    assert not (actions[:, 1:, 0] == actions[:, :-1, 0]).all()

    def travel(data):  # mean distance between the agent's centre at steps 0 and 15 of each episode
        mask = data["next", "mask_agent"].reshape(4, 32, 64, 64).float()
        grid = torch.arange(64.0)
        ys = (mask.sum(-1) * grid).sum(-1) / mask.sum((-1, -2))
        xs = (mask.sum(-2) * grid).sum(-1) / mask.sum((-1, -2))
        return torch.hypot(ys[:, 15] - ys[:, 0], xs[:, 15] - xs[:, 0]).mean()

    assert travel(held) > 1.5 * travel(jitter)
    with pytest.raises(ValueError, match="action_hold"):
        collect_sprites_episodes(episodes=1, steps=8, action_hold=0)


def test_late_term_weight_waits_then_ramps_up():
    weights = [ramp_weight(2.0, step, 100) for step in (0, 99, 100, 150, 200, 300)]
    assert weights == pytest.approx([0.0, 0.0, 0.0, 1.0, 2.0, 2.0])
    assert ramp_weight(2.0, 0, 0) == 2.0
    # a late start with a ramp of its own length (--ramp-updates), and a step switch-on
    weights = [ramp_weight(2.0, step, 4000, 1000) for step in (3999, 4000, 4500, 5000, 9000)]
    assert weights == pytest.approx([0.0, 0.0, 1.0, 2.0, 2.0])
    assert [ramp_weight(2.0, step, 10, 0) for step in (9, 10)] == [0.0, 2.0]


def test_demo_logs_the_pyramid_term_once_it_starts(tmp_path):
    args = ["--steps", "41", "--episodes", "2", "--episode-length", "16", "--window", "8"]
    args += ["--batch-size", "2", "--size", "tiny", "--eval-every", "41", "--precision", "fp32"]
    args += ["--probe-episodes", "0", "--out", str(tmp_path)]
    main([*args, "--lambda-reco-pyramid", "1", "--reco-pyramid-from", "30", "--ramp-updates", "5"])

    (csv,) = tmp_path.rglob("loss_model_reco_pyramid.csv")
    logged = {
        int(float(step)): float(value)
        for step, value in (line.split(",")[:2] for line in csv.read_text().split())
    }
    # logged every 20 updates; its weight is zero up to update 30, then ramps up over 5 updates
    assert logged[0] == 0.0 and logged[20] == 0.0 and logged[40] > 0.0


def test_demo_runs_the_single_branch_ablation_scored_by_disc_reconstruction(tmp_path):
    small = list(TINY_RUN)
    summary = main(
        [*small, "--size", "tiny", "--eval-every", "2", "--precision", "fp32", "--out", str(tmp_path)]
        + ["--model", "dreamerv2"]
    )
    assert "iou_free_vs_distractors" not in summary and "free_covers_distractor_0" not in summary
    # probed like the full model, on its one state
    assert {k for k in summary if k.startswith("probe_")} == {
        f"probe_r2_{b}_{n}"
        for b in ("control", "trunk", "embed_control")
        for n in ("agent", "distractor_0", "distractor_1", "distractor_2")
    }
    assert 0.0 <= summary["reco_error_distractor_0"] <= 3.0
    saved = torch.load(tmp_path / "world_model.pt", map_location="cpu")
    assert saved["config"]["free_branch"] is False and saved["config"]["static_branch"] is False


def test_demo_composes_with_the_authors_sigmoid_masks(tmp_path):
    small = list(TINY_RUN)
    small += ["--size", "tiny", "--eval-every", "2", "--precision", "fp32", "--probe-episodes", "0"]
    summary = main([*small, "--mask-mode", "sigmoid", "--out", str(tmp_path)])
    assert 0.0 <= summary["iou_free_vs_distractors"] <= 1.0
    saved = torch.load(tmp_path / "world_model.pt", map_location="cpu")
    assert saved["config"]["mask_mode"] == "sigmoid"
    # the background has no logit in sigmoid mode: a bias for it is an error, not silently dropped
    with pytest.raises(SystemExit, match="static-mask-bias"):
        main([*small, "--mask-mode", "sigmoid", "--static-mask-bias", "3", "--out", str(tmp_path / "b")])


def test_demo_resumes_from_its_checkpoint_and_rejects_other_settings(tmp_path):
    small = ["--episodes", "2", "--episode-length", "16", "--window", "8", "--batch-size", "2"]
    small += ["--size", "tiny", "--eval-every", "2", "--precision", "fp32"]
    main([*small, "--steps", "2", "--out", str(tmp_path / "a")])
    checkpoint = str(tmp_path / "a" / "world_model.pt")
    before = torch.load(checkpoint, map_location="cpu")
    summary = main([*small, "--steps", "4", "--resume", checkpoint, "--out", str(tmp_path / "b")])
    after = torch.load(tmp_path / "b" / "world_model.pt", map_location="cpu")
    assert summary["updates"] == 4 and after["step"] == 4
    # Adam's step counters continue from the saved ones
    assert all(s["step"] == 4 for s in after["optimizer"]["state"].values())
    assert all(s["step"] == 2 for s in before["optimizer"]["state"].values())
    with pytest.raises(ValueError, match="static_mask_bias"):
        main(
            [
                *small,
                "--steps",
                "4",
                "--resume",
                checkpoint,
                "--static-mask-bias",
                "1",
                "--out",
                str(tmp_path / "c"),
            ]
        )
    with pytest.raises(SystemExit, match="already at update 2"):
        main([*small, "--steps", "2", "--resume", checkpoint, "--out", str(tmp_path / "d")])


def test_demo_scene_with_two_distractors_is_scored_and_probed_on_two(tmp_path):
    summary = main(
        [*TINY_RUN, "--size", "tiny", "--precision", "fp32", "--distractors", "2", "--out", str(tmp_path)]
    )
    assert "free_covers_distractor_1" in summary and "free_covers_distractor_2" not in summary
    assert "probe_r2_free_distractor_1" in summary and "probe_r2_free_distractor_2" not in summary
    saved = torch.load(tmp_path / "world_model.pt", map_location="cpu", weights_only=False)
    assert saved["scene"]["num_distractors"] == 2


def test_demo_scene_takes_distractor_colours_and_refuses_a_count_that_disagrees(tmp_path):
    main(
        [*TINY_RUN, "--size", "tiny", "--probe-episodes", "0", "--out", str(tmp_path)]
        + ["--distractor-colours", "cyan,magenta"]
    )
    saved = torch.load(tmp_path / "world_model.pt", map_location="cpu", weights_only=False)
    assert (
        saved["scene"]["distractor_colours"] == ("cyan", "magenta") and saved["scene"]["num_distractors"] == 2
    )
    agent_cyan = ["--agent-colour", "cyan"]
    main([*TINY_RUN, "--size", "tiny", "--probe-episodes", "0", "--out", str(tmp_path), *agent_cyan])
    saved = torch.load(tmp_path / "world_model.pt", map_location="cpu", weights_only=False)
    assert saved["scene"]["agent_colour"] == "cyan"
    with pytest.raises(SystemExit, match="names 2 colours"):
        main(
            [*TINY_RUN, "--distractors", "3", "--distractor-colours", "cyan,magenta", "--out", str(tmp_path)]
        )
    with pytest.raises(SystemExit, match="unknown"):
        main([*TINY_RUN, "--distractor-colours", "cyan,teal", "--out", str(tmp_path)])


def _static_mask_bias(path) -> torch.Tensor:
    model = torch.load(path, map_location="cpu")["model"]
    (bias,) = [
        v for k, v in model.items() if k.startswith("static_decoder.") and k.endswith("bias") and v[3] > 1
    ]
    return bias


def test_demo_raises_the_background_prior_on_schedule_and_across_a_resume(tmp_path):
    # lr 0: the parameters move only by the raise, so the bias shows exactly how much of it was applied
    small = [*TINY_RUN[2:], "--size", "tiny", "--eval-every", "2", "--precision", "fp32", "--lr", "0"]
    raise_ = ["--static-mask-bias-schedule", "1:0,3:2"]
    main([*small, "--steps", "4", "--out", str(tmp_path / "plain")])
    main([*small, *raise_, "--steps", "4", "--out", str(tmp_path / "raised")])
    plain = _static_mask_bias(tmp_path / "plain" / "world_model.pt")
    raised = _static_mask_bias(tmp_path / "raised" / "world_model.pt")
    assert torch.allclose(raised - plain, torch.tensor([0.0, 0.0, 0.0, 2.0]))
    # half-way (updates 0, 1, 2 ran: 1.0 of the raise at update 2), then resumed: 2.0 in all, not more
    main([*small, *raise_, "--steps", "3", "--out", str(tmp_path / "half")])
    half = _static_mask_bias(tmp_path / "half" / "world_model.pt")
    assert torch.allclose(half - plain, torch.tensor([0.0, 0.0, 0.0, 1.0]))
    checkpoint = str(tmp_path / "half" / "world_model.pt")
    main([*small, *raise_, "--steps", "4", "--resume", checkpoint, "--out", str(tmp_path / "rest")])
    assert torch.allclose(_static_mask_bias(tmp_path / "rest" / "world_model.pt"), raised)
    with pytest.raises(SystemExit, match="static-mask-bias-schedule"):
        main([*small, *raise_, "--mask-mode", "sigmoid", "--out", str(tmp_path / "sigmoid")])


class _MasksFromTruth(torch.nn.Module):
    """A stand-in world model whose masks are built from the ground truth: ``free`` on the distractors plus
    the left half of the frame, ``control`` on the agent; the composite is the true frame."""

    def __init__(self, truth):
        super().__init__()
        self.truth = truth

    def forward(self, td):
        nxt = self.truth["next"]
        shape = nxt["mask_agent"].shape
        left = torch.zeros(shape, dtype=torch.bool)
        left[..., : shape[-1] // 2] = True
        free = (nxt["mask_distractors"].bool() | left).float()
        out = td.clone()
        out["next", "mask_free"] = free
        out["next", "mask_control"] = nxt["mask_agent"].float()
        out["next", "reco_pixels"] = nxt["pixels"].float() / 255.0 - 0.5
        return out


def test_evaluate_scores_the_share_of_background_each_mask_holds():
    from types import SimpleNamespace

    from isodream_rl.recipes.sprites_data import episode_windows
    from isodream_rl.recipes.world_model_demo import evaluate

    data = collect_sprites_episodes(episodes=1, steps=16, seed=0)
    truth = episode_windows(data, window=8)
    scores, _ = evaluate(SimpleNamespace(world_model=_MasksFromTruth(truth)), data, window=8, device="cpu")
    background = ~truth["next", "mask_agent"].bool() & ~truth["next", "mask_distractors"].bool()
    left = background[..., :32].sum() / background.sum()  # the background pixels in the left half
    assert scores["control_on_background"] == 0.0
    assert scores["free_on_background"] == pytest.approx(float(left), abs=1e-6)
    assert 0.3 < scores["free_on_background"] < 0.7
    assert all(scores[f"free_covers_distractor_{i}"] == 1.0 for i in range(3))
    assert scores["reco_error_agent"] == pytest.approx(0.0, abs=1e-6)


def test_schedule_is_piecewise_linear_from_zero_and_held_after_its_last_point():
    raise_ = parse_schedule("2500:0,3500:3")
    assert [schedule_value(raise_, s) for s in (0, 2500, 3000, 3500, 9000)] == [0.0, 0.0, 1.5, 3.0, 3.0]
    dip = parse_schedule("0:-3,1000:-3,2000:0")
    assert [schedule_value(dip, s) for s in (0, 999, 1500, 2000, 5000)] == [-3.0, -3.0, -1.5, 0.0, 0.0]
    assert [schedule_value(parse_schedule("100:2"), s) for s in (0, 50, 100)] == [0.0, 1.0, 2.0]
    assert schedule_value((), 10) == 0.0
    assert schedule_value(dip, -1) == 0.0  # before update 0: nothing applied yet
    for bad in ("3500:3,2500:0", "1:2,1:3", "-1:0", "a:b", "100"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_schedule(bad)


def test_demo_eval_every_zero_scores_once_at_the_end(tmp_path, capsys):
    small = ["--steps", "3", *TINY_RUN[2:], "--size", "tiny", "--precision", "fp32", "--probe-episodes", "0"]
    summary = main([*small, "--eval-every", "0", "--out", str(tmp_path)])
    evaluations = [line for line in capsys.readouterr().out.splitlines() if line.startswith("update ")]
    assert len(evaluations) == 1 and evaluations[0].startswith("update 3:")
    assert summary["updates"] == 3 and (tmp_path / "branches.png").exists()
    with pytest.raises(SystemExit):
        main([*small, "--eval-every", "-1", "--out", str(tmp_path / "b")])
    assert "--eval-every must be >= 0" in capsys.readouterr().err
