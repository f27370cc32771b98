"""``isodream_rl.evaluation.decomposition_scores`` on hand-made masks whose scores are known."""

import json
import math

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from isodream_rl.data.sprites_episodes import collect_sprites_episodes, episode_windows
from isodream_rl.evaluation import BRANCHES, CLASSES, branch_assignment, decomposition_scores
from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel

# one 4 x 4 frame: the agent in the top-left 2 pixels, two distractor pixels bottom-right, 12 of background
AGENT = torch.zeros(4, 4, dtype=torch.bool)
AGENT[0, :2] = True
DISTRACTORS = torch.zeros(4, 4, dtype=torch.bool)
DISTRACTORS[3, 2:] = True
BACKGROUND = ~AGENT & ~DISTRACTORS


def make_windows(n: int = 2, t: int = 3) -> TensorDict:
    pixels = torch.randint(
        0, 256, (n, t, 3, 4, 4), dtype=torch.uint8, generator=torch.Generator().manual_seed(0)
    )
    return TensorDict(
        {
            "action": torch.zeros(n, t, 2),
            "is_init": torch.zeros(n, t, 1, dtype=torch.bool),
            "next": {
                "pixels": pixels,
                "mask_agent": AGENT.expand(n, t, 4, 4).clone(),
                "mask_distractors": DISTRACTORS.expand(n, t, 4, 4).clone(),
            },
        },
        [n, t],
    )


class FixedMasks(nn.Module):
    """A stand-in world model: the given masks ``[H, W]`` (per branch) on every step, the true frame plus
    ``offset`` on the agent's pixels as its reconstruction."""

    def __init__(self, truth: TensorDict, masks: dict[str, torch.Tensor], offset: float = 0.0):
        super().__init__()
        self.truth, self.masks, self.offset = truth, masks, offset

    def forward(self, td):
        out = td.clone()
        shape = td.batch_size
        for branch, mask in self.masks.items():
            out["next", f"mask_{branch}"] = mask.float().expand(*shape, 1, 4, 4).clone()
        reco = self.truth["next", "pixels"].float() / 255.0 - 0.5
        out["next", "reco_pixels"] = reco + self.offset * AGENT.float()
        return out


def one_hot(control, free):
    return {"control": control, "free": free, "static": ~control & ~free}


def test_a_perfect_decomposition_scores_one_on_the_diagonal_and_zero_elsewhere():
    windows = make_windows()
    scores = decomposition_scores(FixedMasks(windows, one_hot(AGENT, DISTRACTORS)), windows)
    for branch, name in zip(BRANCHES, CLASSES, strict=True):
        for other in CLASSES:
            assert scores[f"iou_{branch}_vs_{other}"] == (1.0 if other == name else 0.0), (branch, other)
    assert scores["iou_control_vs_agent"] == scores["iou_free_vs_distractors"] == 1.0
    assert scores["iou_static_vs_background"] == 1.0
    assert (scores["background_share_static"], scores["background_share_control"]) == (1.0, 0.0)
    assert scores["reco_mse"] == scores["mse_agent"] == scores["mse_background"] == 0.0


def test_the_target_is_scored_where_the_windows_hold_its_mask():
    windows = make_windows()
    target = torch.zeros(4, 4, dtype=torch.bool)
    target[2, :2] = True  # two background pixels
    free = DISTRACTORS.clone()
    free[2, 0] = True  # the action-free branch takes one target pixel, the static one the other
    model = FixedMasks(windows, one_hot(AGENT, free))
    assert not any("target" in key for key in decomposition_scores(model, windows))
    windows["next", "mask_target"] = target.expand(2, 3, 4, 4).clone()
    scores = decomposition_scores(model, windows)
    assert (scores["target_share_control"], scores["target_share_free"], scores["target_share_static"]) == (
        0.0,
        0.5,
        0.5,
    )
    assert scores["iou_free_vs_target"] == pytest.approx(1 / 4)  # 1 shared pixel, 4 in the union
    assert scores["mse_target"] == 0.0  # drawn exactly (only the agent's pixels are off)
    offset = FixedMasks(windows, one_hot(AGENT, free), offset=0.2)
    target_and_agent = target.clone()
    target_and_agent[0, 0] = True  # over an agent pixel (off by 0.2): one of its 3 pixels has an error
    windows["next", "mask_target"] = target_and_agent.expand(2, 3, 4, 4).clone()
    assert decomposition_scores(offset, windows)["mse_target"] == pytest.approx(0.2**2 / 3)
    windows["next", "mask_target"] = target.expand(2, 3, 4, 4).clone()
    assert scores["iou_static_vs_target"] == pytest.approx(1 / 12)  # static: 11 pixels + 1 of the target's
    windows["next", "mask_target"] = target.float().expand(2, 3, 4, 4).clone()
    with pytest.raises(ValueError, match="mask_target.*bool"):
        decomposition_scores(model, windows)


def test_a_branch_twice_the_size_of_its_class_scores_one_half():
    windows = make_windows()
    control = AGENT.clone()
    control[1, :2] = True  # two background pixels more
    scores = decomposition_scores(FixedMasks(windows, one_hot(control, DISTRACTORS)), windows)
    assert scores["iou_control_vs_agent"] == 0.5
    assert scores["iou_control_vs_background"] == pytest.approx(2 / 14)
    assert scores["background_share_control"] == pytest.approx(2 / 12)
    assert scores["background_share_static"] == pytest.approx(10 / 12)
    assert scores["iou_static_vs_background"] == pytest.approx(10 / 12)


def test_reconstruction_error_is_counted_per_class():
    windows = make_windows()
    scores = decomposition_scores(FixedMasks(windows, one_hot(AGENT, DISTRACTORS), offset=0.1), windows)
    assert scores["mse_agent"] == pytest.approx(0.01)
    assert scores["mse_distractors"] == scores["mse_background"] == 0.0
    assert scores["reco_mse"] == pytest.approx(0.01 * 2 / 16)


def test_the_single_branch_model_is_all_control():
    windows = make_windows()
    scores = decomposition_scores(
        FixedMasks(windows, {"control": torch.ones(4, 4, dtype=torch.bool)}), windows
    )
    assert scores["iou_control_vs_agent"] == pytest.approx(2 / 16)  # the agent's share of the frame
    assert scores["iou_free_vs_distractors"] == 0.0 and scores["iou_static_vs_background"] == 0.0
    assert scores["background_share_control"] == 1.0 and scores["background_share_free"] == 0.0


def test_masks_are_binarised_by_the_largest_branch_unless_a_threshold_is_given():
    output = TensorDict(
        {
            "next": {
                "mask_control": torch.full((1, 1, 1, 2, 2), 0.4),
                "mask_free": torch.full((1, 1, 1, 2, 2), 0.3),
                "mask_static": torch.full((1, 1, 1, 2, 2), 0.3),
            }
        },
        [1, 1],
    )
    largest = branch_assignment(output)
    assert largest["control"].all() and not largest["free"].any() and not largest["static"].any()
    assert not any(mask.any() for mask in branch_assignment(output, threshold=0.5).values())
    assert all(mask.all() for mask in branch_assignment(output, threshold=0.25).values())


def test_a_class_absent_from_every_window_has_no_score():
    windows = make_windows()
    windows["next", "mask_distractors"].zero_()
    scores = decomposition_scores(
        FixedMasks(windows, one_hot(AGENT, torch.zeros(4, 4, dtype=torch.bool))), windows
    )
    assert math.isnan(scores["iou_free_vs_distractors"]) and math.isnan(scores["mse_distractors"])
    assert scores["iou_control_vs_agent"] == 1.0


def test_windows_without_ground_truth_or_of_the_wrong_shape_are_refused():
    windows = make_windows()
    model = FixedMasks(windows, one_hot(AGENT, DISTRACTORS))
    with pytest.raises(ValueError, match="mask_distractors.*return_masks=True"):
        decomposition_scores(model, windows.exclude(("next", "mask_distractors")))
    wrong = windows.clone()
    wrong["next", "mask_agent"] = torch.zeros(2, 3, 4, 5, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"mask_agent.*\[2, 3, 4, 4\]"):
        decomposition_scores(model, wrong)
    wrong = windows.clone()
    wrong["next", "mask_agent"] = wrong["next", "mask_agent"].float()
    with pytest.raises(ValueError, match="bool"):
        decomposition_scores(model, wrong)
    with pytest.raises(ValueError, match=r"\[N, T\].*episode_windows"):
        decomposition_scores(model, windows.reshape(-1))


@pytest.mark.parametrize("branches", [{}, {"free_branch": False, "static_branch": False}])
def test_a_real_world_model_partitions_the_frame_between_its_branches(branches):
    model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2, **branches))
    windows = episode_windows(collect_sprites_episodes(episodes=1, steps=8, seed=0), window=4)
    scores = decomposition_scores(model, windows)
    assert set(scores) == {
        "reco_mse",
        *(f"mse_{c}" for c in CLASSES),
        *(f"iou_{b}_vs_{c}" for b in BRANCHES for c in CLASSES),
        *(f"background_share_{b}" for b in BRANCHES),
    }
    assert sum(scores[f"background_share_{b}"] for b in BRANCHES) == pytest.approx(1.0)
    assert all(0.0 <= scores[f"iou_{b}_vs_{c}"] <= 1.0 for b in BRANCHES for c in CLASSES)


def test_rollout_windows_are_cut_from_an_episode_and_too_short_ones_give_nothing():
    from isodream_rl.envs import make_env
    from isodream_rl.trainers.evaluation import rollout_decomposition

    model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
    rollout = make_env("sprites", seed=0, return_masks=True, max_steps=7).rollout(7)
    assert set(rollout_decomposition(model, rollout, window=3)) >= {"iou_control_vs_agent", "reco_mse"}
    assert rollout_decomposition(model, rollout, window=10)["iou_static_vs_background"] >= 0.0  # one of 7
    assert rollout_decomposition(model, rollout[:1], window=3) == {}


def test_the_rl_run_logs_the_decomposition_of_its_evaluations(tmp_path):
    from isodream_rl.trainers import train
    from tests.conftest import tiny_run_config

    cfg = tiny_run_config(
        tmp_path,
        train__buffer_size=200,
        train__total_steps=30,
        logging__progress_bar=False,
        logging__log_every=10,
        logging__eval_every=20,
        logging__final_eval_episodes=0,
        env__kwargs={"max_steps": 20},
    )
    train(cfg)
    logged = {p.stem for p in (tmp_path / "logs").rglob("*.csv") if p.parent.name == "decomposition"}
    assert {"iou_control_vs_agent", "iou_free_vs_distractors", "background_share_static"} <= logged


def test_a_finished_run_is_scored_again_from_its_checkpoint_with_the_target(tmp_path):
    from isodream_rl.trainers import train
    from isodream_rl.trainers.run import checkpoint_decomposition
    from tests.conftest import tiny_run_config

    cfg = tiny_run_config(
        tmp_path,
        train__buffer_size=200,
        train__total_steps=30,
        logging__progress_bar=False,
        logging__log_every=10,
        logging__eval_every=0,
        logging__final_eval_episodes=1,
        env__kwargs={"max_steps": 20, "task": "reach"},
    )
    train(cfg)
    summary = json.loads((tmp_path / "summary.json").read_text())
    again = checkpoint_decomposition(tmp_path)
    assert again == checkpoint_decomposition(tmp_path)  # the final evaluation's episode, seeded
    scores = again["decomposition"]
    assert set(summary["decomposition"]) == set(scores)  # the same scores as the summary, the target's among them
    assert sum(scores[f"target_share_{b}"] for b in BRANCHES) == pytest.approx(1.0)
    assert again["episode_steps"] == 20 and again["isolation"]["agent_branch"] in BRANCHES
    assert again["checkpoint"].startswith(str(tmp_path / "checkpoints"))
