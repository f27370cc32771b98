"""``mode=world_model`` (``isodream-train exp=world_model``, alias ``isodream-demo``) at a tiny size: it
trains the world model alone, of either Iso-Dream learner (the recipes' ``algo=isodream_v2``, the default's
``algo=isodream``), scores the masks, writes its run folder, resumes and reads it back."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import isodream_rl.cli
from isodream_rl.data.sprites_episodes import collect_sprites_episodes, episode_windows, model_input
from isodream_rl.envs.sprites import DISTRACTOR_COLOURS
from isodream_rl.evaluation import decomposition_scores
from isodream_rl.evaluation.branches import score_branches
from isodream_rl.evaluation.latent_probe import probe
from isodream_rl.modules.isodream.world_model import IsoDreamConfig, IsoDreamWorldModel
from isodream_rl.modules.isodream_v2 import IsoDreamV2WorldModel
from isodream_rl.trainers import (
    CheckpointError,
    CheckpointManager,
    ConfigError,
    IsoDreamOptimizationStepper,
    validate_config,
    world_model_run,
)
from isodream_rl.trainers import run as run_module
from isodream_rl.trainers.learners import WORLD_MODEL_LEARNERS, resolved
from isodream_rl.trainers.world_model_run import collect_episodes, load_world_model
from tests.conftest import cli_process, load_bench

CONFIGS = Path(isodream_rl.cli.__file__).parent / "configs"
# two updates of 2 windows x 8 steps on two short episodes, no probe: what every tiny run here shares
TINY = [
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


def composed(*overrides):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return OmegaConf.to_object(compose(config_name="config", overrides=[*TINY, *overrides]))


def train(run_dir, *overrides):
    return run_module.train(composed(f"run_dir={run_dir}", *overrides), probe=probe)


#: ``(step, value)`` rows of a run's CSV log (``bench/common.py``'s reader)
read_scalar = load_bench("common").read_scalar


def latest_state(run_dir) -> dict:
    return CheckpointManager(Path(run_dir) / "checkpoints").load_latest()[0]


def test_writes_pictures_scores_probe_checkpoint_and_logs_in_the_run_folder(tmp_path):
    result = train(
        tmp_path,
        "world_model.updates=3",
        "logging.eval_every=2",
        "world_model.probe_episodes=4",
        "train.adam_eps=1e-7",
    )
    assert result.updates == 3 and result.env_steps == 32
    assert sorted(p.name for p in (tmp_path / "pictures").iterdir()) == [
        "branches_00000002.png",
        "branches_00000003.png",
    ]
    state = latest_state(tmp_path)
    assert result.checkpoint == tmp_path / "checkpoints" / "step_00000003"
    assert state["stepper"]["updates"] == 3 and set(state["models"]) == {"world_model"}
    assert state["stepper"]["optimizers"]["world_model"]["param_groups"][0]["eps"] == 1e-7
    assert (
        state["config"]["mode"] == "world_model" and state["config"]["env"]["kwargs"]["num_backgrounds"] == 8
    )
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved == result.summary
    assert saved["updates"] == 3 and 0.0 <= saved["iou_control_vs_agent"] <= 1.0
    for name in (
        "iou_free_vs_distractors",
        "free_covers_distractor_2",
        "reco_error_distractor_0",
        "reco_error_agent",
        "background_share_free",
        "background_share_control",
        "iou_static_vs_background",
    ):
        assert 0.0 <= saved[name] <= 3.0 and 0.0 <= saved[f"train_{name}"] <= 3.0, name
    # the final latent probe: every branch x sprite, an R^2 (at most 1), in the summary and the log
    probes = {k for k in saved if k.startswith("probe_r2_")}
    sprites = ("agent", "distractor_0", "distractor_1", "distractor_2")
    layers = ("control", "free", "trunk", "embed_control", "embed_free")
    assert probes == {f"probe_r2_{b}_{n}" for b in layers for n in sprites}
    assert all(saved[k] <= 1.0 for k in probes)
    scalars = tmp_path / "logs"
    assert list(scalars.rglob("probe_r2_free_agent.csv")) and list(scalars.rglob("loss_model_reco.csv"))
    # the held-out scores under an RL run's names, at each evaluation; the loss's reco_mse (the training
    # batch's, at each logged update) alone in its own file
    held_out = read_scalar(tmp_path, "eval/decomposition/iou_control_vs_agent")
    assert [step for step, _ in held_out] == [2, 3]
    assert held_out[-1][1] == pytest.approx(saved["iou_control_vs_agent"], abs=1e-3)  # the summary rounds
    assert read_scalar(tmp_path, "eval/decomposition/train_reco_error_agent")[-1][1] == pytest.approx(
        saved["train_reco_error_agent"], abs=1e-3
    )
    assert [step for step, _ in read_scalar(tmp_path, "reco_mse")] == [0, 2]
    assert saved["png"] == str(tmp_path / "pictures" / "branches_00000003.png")
    with pytest.raises(CheckpointError, match="no policy"):
        run_module.evaluate_checkpoint(tmp_path)


def test_the_world_model_exp_holds_the_demos_defaults():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = OmegaConf.to_object(compose(config_name="config", overrides=["exp=world_model"]))
    assert cfg.mode == "world_model" and cfg.run_dir == "runs/world_model"
    assert (cfg.train.batch_size, cfg.train.sequence_length, cfg.train.world_model_lr) == (8, 16, 1e-3)
    assert (cfg.model.size, cfg.algo.name, cfg.model.world_model_fields()) == ("small", "isodream_v2", {})
    wm = cfg.world_model
    assert (wm.updates, wm.episodes, wm.episode_length, wm.held_out_episodes) == (3000, 60, 96, 4)
    assert (wm.action_hold, wm.probe_episodes) == (8, 32)
    assert cfg.env.kwargs == {"task": "none", "max_steps": 200, "num_backgrounds": 8, "background_seed": 0}
    assert (cfg.logging.log_every, cfg.logging.eval_every) == (20, 200)
    # the demo's loss: reward head on [s, h] at weight 1 (the sprites RL preset's are (s, z) and 2)
    algo = resolved(cfg).algo
    assert (algo.reward_uses_free, algo.lambda_reward, algo.lambda_inverse) == (False, 1.0, 30.0)


def test_trains_the_world_model_of_either_iso_dream_learner_and_refuses_the_others_naming_those_it_trains():
    """Without an exp, the default algo (Iso-Dream on DreamerV3's learner) is taken; TorchRL's baselines, whose world
    models have no branches, are refused in one line naming the algos it trains."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = OmegaConf.to_object(
            compose(config_name="config", overrides=["mode=world_model", "train.sequence_length=16"])
        )
    assert cfg.algo.name == "isodream"
    validate_config(cfg)
    assert (
        set(world_model_run.WORLD_MODEL_BUILDERS) == set(WORLD_MODEL_LEARNERS) == {"isodream", "isodream_v2"}
    )
    valid = (
        "algo=isodream, algo=isodream_no_inverse, algo=isodream_no_attention, algo=isodream_no_static, "
        "algo=isodream_v2, algo=isodream_paper, algo=dreamerv2"
    )
    for algo, learner in (
        ("torchrl_dreamer_v3", "TorchRL's DreamerV3"),
        ("torchrl_dreamer", "TorchRL's Dreamer"),
    ):
        cfg.algo.name = algo
        with pytest.raises(ConfigError) as err:
            validate_config(cfg)
        (line,) = [line for line in str(err.value).splitlines() if "mode=world_model" in line]
        assert f"not algo={algo}'s ({learner}: no branches): pick one of {valid}" in line, line


def test_the_recipes_take_the_defaults_world_model_without_the_dreamerv2_style_learners_settings():
    """``exp=world_model`` and ``exp=decomposition`` pick ``algo=isodream_v2`` and set two of its own settings;
    ``algo=isodream`` takes the rest of the recipe without them (the default does not read them)."""
    for exp in ("world_model", "decomposition"):
        v2, default = composed(f"exp={exp}"), composed(f"exp={exp}", "algo=isodream")
        validate_config(default)
        assert (v2.algo.name, v2.algo.lambda_reward, default.algo.lambda_reward) == ("isodream_v2", 1.0, None)
        assert (v2.algo.reward_uses_free, default.algo.reward_uses_free) == (False, False)
        assert (default.train.world_model_lr, default.train.batch_size) == (v2.train.world_model_lr, 2)
    decomposition = composed("exp=decomposition", "algo=isodream")
    assert decomposition.algo.free_branch_loss is None and decomposition.run_dir.endswith("-isodream")
    assert composed("exp=decomposition").algo.free_branch_loss == "kl"


def test_the_defaults_world_model_trains_alone_is_scored_resumes_and_reads_back(tmp_path):
    """``algo=isodream``: its world model with its own loss and ``DreamerV3Optimizer`` (no actor, no critic), scored
    on held-out episodes as the DreamerV2-style one is, probed, checkpointed, resumed, and read back as an
    ``IsoDreamWorldModel``."""
    result = train(tmp_path, "algo=isodream", "world_model.probe_episodes=4")
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary == result.summary and result.updates == 2 and summary["stopped_by"] == "updates"
    assert (summary["algo"], summary["learner"], summary["precision"]) == ("isodream", "isodream", "fp32")
    for name in (
        "iou_control_vs_agent",
        "iou_free_vs_distractors",
        "iou_static_vs_background",
        "background_share_free",
        "free_covers_distractor_2",
        "reco_error_agent",
    ):
        assert 0.0 <= summary[name] <= 3.0 and 0.0 <= summary[f"train_{name}"] <= 3.0, name
    # its images are scored in the pixel range of the scores ([-0.5, 0.5]), not in its loss's ([0, 1])
    assert summary["reco_mse"] < 0.15
    # the latent probe reads both branches' halves of its packed latent and its encoder's one embedding
    sprites = ("agent", "distractor_0", "distractor_1", "distractor_2")
    assert {k for k in summary if k.startswith("probe_")} == {
        f"probe_r2_{b}_{n}" for b in ("control", "free", "trunk") for n in sprites
    }
    assert summary["png"] == str(tmp_path / "pictures" / "branches_00000002.png")
    assert (tmp_path / "pictures" / "branches_00000002.png").stat().st_size > 0
    state = latest_state(tmp_path)
    assert set(state["models"]) == {"world_model"} and set(state["stepper"]["optimizers"]) == {"world_model"}
    # the world model's optimiser of an algo=isodream run: DreamerV3's (adaptive gradient clipping, lr warm-up)
    group = state["stepper"]["optimizers"]["world_model"]["param_groups"][0]
    assert (group["agc"], group["warmup_steps"]) == (0.3, 1000)
    assert any(key.startswith("control_prior.") for key in state["models"]["world_model"])
    assert state["config"]["algo"]["name"] == "isodream" and state["config"]["algo"]["lambda_reward"] is None
    model, cfg = load_world_model(tmp_path)
    assert isinstance(model, IsoDreamWorldModel) and cfg.algo.name == "isodream"
    assert all(torch.equal(v, state["models"]["world_model"][k]) for k, v in model.state_dict().items())
    resumed = train(
        tmp_path, "algo=isodream", "world_model.probe_episodes=4", "world_model.updates=3", "resume=true"
    )
    assert resumed.resumed_from == tmp_path / "checkpoints" / "step_00000002" and resumed.updates == 3
    assert latest_state(tmp_path)["stepper"]["updates"] == 3 and resumed.summary["learner"] == "isodream"


def test_a_run_saved_when_isodream_named_the_dreamerv2_style_learner_reads_back_and_resumes_as_isodream_v2(
    tmp_path,
):
    """A ``mode=world_model`` run saved as ``algo=isodream`` before that name became the default (its weights the
    DreamerV2-style learner's) loads as ``IsoDreamV2WorldModel`` and resumes as ``algo=isodream_v2``; resumed as
    ``algo=isodream`` it is refused in one line that says so."""
    train(tmp_path)  # exp=world_model: algo=isodream_v2
    checkpoints = CheckpointManager(tmp_path / "checkpoints")
    state, _ = checkpoints.load_latest()
    state["config"]["algo"]["name"] = "isodream"  # as such a run saved it
    checkpoints.save(2, state)
    model, cfg = load_world_model(tmp_path)
    assert isinstance(model, IsoDreamV2WorldModel) and cfg.algo.name == "isodream_v2"
    with pytest.raises(
        CheckpointError, match="its weights are the DreamerV2-style learner's.*algo=isodream_v2"
    ):
        train(tmp_path, "algo=isodream", "world_model.updates=3", "resume=true")
    assert train(tmp_path, "world_model.updates=3", "resume=true").updates == 3


def test_the_defaults_images_are_scored_and_drawn_in_the_pixel_range_of_the_scores():
    """``IsoDreamWorldModel`` draws in its loss's units (pixels / 255); the scores and the branch pictures read
    ``[-0.5, 0.5]``: ``score_branches`` shifts every image it returns, as ``decomposition_scores`` does."""
    model = IsoDreamWorldModel(IsoDreamConfig(action_dim=2, hidden=16, image_depth=2, units=16))
    data = collect_sprites_episodes(episodes=1, steps=8, seed=0)
    torch.manual_seed(0)
    scores, out = score_branches(model, data, window=8)
    torch.manual_seed(0)
    with torch.no_grad():
        raw = model(model_input(episode_windows(data, window=8)))
    for key in (("next", "reco_pixels"), ("next", "reco_control"), ("next", "reco_free"), "background"):
        torch.testing.assert_close(out[key], raw[key] - 0.5)
    torch.manual_seed(0)
    assert decomposition_scores(model, episode_windows(data, window=8))["reco_mse"] == pytest.approx(
        scores["reco_mse"]
    )


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


def test_the_single_branch_baseline_is_scored_by_disc_reconstruction_and_probed(tmp_path):
    result = train(
        tmp_path, "exp=world_model_dreamerv2", "world_model.episodes=2", "world_model.probe_episodes=4"
    )
    summary = result.summary
    assert summary["algo"] == "dreamerv2"
    # its one image is the control branch: it holds every pixel, the branches it lacks none
    assert summary["iou_free_vs_distractors"] == 0.0 and summary["background_share_control"] == 1.0
    assert "free_covers_distractor_0" not in summary
    # probed like the full model, on its one state
    assert {k for k in summary if k.startswith("probe_")} == {
        f"probe_r2_{b}_{n}"
        for b in ("control", "trunk", "embed_control")
        for n in ("agent", "distractor_0", "distractor_1", "distractor_2")
    }
    assert 0.0 <= summary["reco_error_distractor_0"] <= 3.0
    assert latest_state(tmp_path)["config"]["algo"]["free_branch"] is False


def test_composes_with_the_authors_sigmoid_masks_and_refuses_a_background_bias_there(tmp_path):
    summary = train(tmp_path, "model.mask_mode=sigmoid").summary
    assert 0.0 <= summary["iou_free_vs_distractors"] <= 1.0
    assert latest_state(tmp_path)["config"]["model"]["mask_mode"] == "sigmoid"
    # the background has no logit in sigmoid mode: a bias for it is an error, not silently dropped
    with pytest.raises(ConfigError, match="static_mask_bias"):
        train(tmp_path / "b", "model.mask_mode=sigmoid", "model.static_mask_bias=3")


def test_resumes_from_its_checkpoint_and_refuses_other_settings(tmp_path):
    train(tmp_path)
    before = latest_state(tmp_path)
    result = train(tmp_path, "world_model.updates=4", "resume=true")
    after = latest_state(tmp_path)
    assert result.resumed_from == tmp_path / "checkpoints" / "step_00000002" and result.updates == 4
    # Adam's step counters continue from the saved ones
    assert all(s["step"] == 2 for s in before["stepper"]["optimizers"]["world_model"]["state"].values())
    assert all(s["step"] == 4 for s in after["stepper"]["optimizers"]["world_model"]["state"].values())
    # another world model, or other data (the episodes are made again from the settings), is refused
    with pytest.raises(ConfigError, match="static_mask_bias"):
        train(tmp_path, "world_model.updates=6", "resume=true", "model.static_mask_bias=1")
    with pytest.raises(ConfigError, match="sprite_size"):
        train(tmp_path, "world_model.updates=6", "resume=true", "+env.kwargs.sprite_size=0.1")
    # a finished run is left as it is
    assert train(tmp_path, "world_model.updates=4", "resume=true").updates == 4
    with pytest.raises(CheckpointError, match="no checkpoint"):
        train(tmp_path / "empty", "resume=true")


def test_scene_comes_from_env_kwargs_and_a_wrong_one_is_a_config_error(tmp_path):
    summary = train(tmp_path, "+env.kwargs.num_distractors=2", "world_model.probe_episodes=4").summary
    assert "free_covers_distractor_1" in summary and "free_covers_distractor_2" not in summary
    assert "probe_r2_free_distractor_1" in summary and "probe_r2_free_distractor_2" not in summary
    with pytest.raises(ConfigError, match="distractor_colours"):
        train(tmp_path / "b", "+env.kwargs.distractor_colours=[cyan,magenta]")


def test_a_sprites_run_that_probes_needs_the_probe_and_leaves_no_run_without_it(tmp_path):
    with pytest.raises(ConfigError, match="latent probe"):
        run_module.train(composed(f"run_dir={tmp_path}", "world_model.probe_episodes=4"))
    assert not (tmp_path / "checkpoints").exists() and not (tmp_path / "run_config.json").exists()


def test_the_three_yellow_discs_recipe_draws_three_yellow_discs():
    cfg = composed("exp=world_model_three_yellow")
    data = collect_episodes(cfg, episodes=1, seed=0)
    discs = data["next", "pixels"].permute(0, 2, 3, 1)[data["next", "distractor_ids"] > 0]  # [pixels, RGB]
    assert (discs == torch.tensor(DISTRACTOR_COLOURS["yellow"], dtype=torch.uint8)).all(-1).all()


def test_how_often_it_evaluates_does_not_change_the_training(tmp_path):
    train(tmp_path / "often", "world_model.updates=3", "logging.eval_every=1")
    train(tmp_path / "once", "world_model.updates=3", "logging.eval_every=0")
    often, once = (latest_state(tmp_path / name)["models"]["world_model"] for name in ("often", "once"))
    assert all(torch.equal(often[k], once[k]) for k in often)
    assert (
        len(list((tmp_path / "once" / "pictures").iterdir())) == 1
    )  # eval_every=0: after the last update only


@pytest.mark.parametrize(
    "env", [["env=highway", "++env.kwargs.view=top_down", "env.kwargs.vehicles_count=5"], ["env=gym"]]
)
def test_any_env_of_the_env_group_trains_and_is_scored_where_it_has_ground_truth(tmp_path, env):
    overrides = [
        "mode=world_model",
        "algo=isodream_v2",
        *env,
        "size=tiny",
        "train.threads=1",
        "logging.progress_bar=false",
    ]
    overrides += ["world_model.updates=2", "world_model.episodes=1", "world_model.held_out_episodes=1"]
    overrides += ["world_model.episode_length=10", f"run_dir={tmp_path}"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        result = run_module.train(OmegaConf.to_object(compose(config_name="config", overrides=overrides)))
    assert result.updates == 2 and set(result.summary) >= {"reco_mse", "train_reco_mse"}
    assert not any(k.startswith("probe_") for k in result.summary)
    if env[0] == "env=highway":  # the ego and the other vehicles, scored like the sprites scene
        assert 0.0 <= result.summary["iou_control_vs_agent"] <= 1.0
        assert 0.0 <= result.summary["train_background_share_static"] <= 1.0
    else:  # a gymnasium env has no ground truth
        assert not any(k.startswith(("iou_", "background_share_")) for k in result.summary)


class _UpdateClock:
    """A clock on which an update takes ``update_s`` seconds and each reading ``read_s`` more: a wall-clock budget
    runs out after a known number of updates, whatever the machine's speed."""

    def __init__(self, *, update_s: float, read_s: float) -> None:
        self.now, self.update_s, self.read_s = 0.0, update_s, read_s

    def __call__(self) -> float:
        self.now += self.read_s
        return self.now

    def timed(self, step):
        def timed_step(*args, **kwargs):
            self.now += self.update_s
            return step(*args, **kwargs)

        return timed_step


def test_stops_once_its_wall_clock_budget_is_spent_and_summarises(tmp_path, monkeypatch):
    clock = _UpdateClock(update_s=10.0, read_s=0.1)
    monkeypatch.setattr(world_model_run, "wall_clock", clock)
    monkeypatch.setattr(IsoDreamOptimizationStepper, "step", clock.timed(IsoDreamOptimizationStepper.step))
    # a budget of 30 s: spent by the third update (10 s each)
    summary = train(tmp_path, "world_model.updates=100000", "world_model.max_minutes=0.5").summary
    assert summary["stopped_by"] == "max_minutes" and 1 <= summary["updates"] < 100000
    assert summary["updates"] == 3
    assert latest_state(tmp_path)["stepper"]["updates"] == summary["updates"]
    assert "iou_control_vs_agent" in summary and summary["png"].endswith(f"{summary['updates']:08d}.png")
    # resumed with a budget of its own (one it has spent already): scored as it is, not trained further
    again = train(tmp_path, "world_model.updates=100000", "world_model.max_minutes=0.5", "resume=true")
    assert again.summary["stopped_by"] == "max_minutes" and again.updates == summary["updates"]
    assert again.summary["seconds"] > summary["seconds"]
    with pytest.raises(ConfigError, match="max_minutes"):
        train(tmp_path / "b", "world_model.max_minutes=-1")


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
        out["next", "mask_static"] = (1.0 - free - out["next", "mask_control"]).clamp(min=0.0)
        out["next", "reco_pixels"] = nxt["pixels"].float() / 255.0 - 0.5
        return out


def test_scores_the_share_of_background_each_mask_holds():
    data = collect_sprites_episodes(episodes=1, steps=16, seed=0)
    truth = episode_windows(data, window=8)
    scores, _ = score_branches(_MasksFromTruth(truth), data, window=8)
    background = ~truth["next", "mask_agent"].bool() & ~truth["next", "mask_distractors"].bool()
    left = background[..., :32].sum() / background.sum()  # the background pixels in the left half
    assert scores["background_share_control"] == 0.0
    assert scores["background_share_free"] == pytest.approx(float(left), abs=1e-6)
    assert scores["background_share_static"] == pytest.approx(1.0 - float(left), abs=1e-6)
    assert 0.3 < scores["background_share_free"] < 0.7
    assert all(scores[f"free_covers_distractor_{i}"] == 1.0 for i in range(3))
    assert scores["reco_error_agent"] == pytest.approx(0.0, abs=1e-6)
    assert scores["reco_mse"] == pytest.approx(0.0, abs=1e-6)


def test_isodream_demo_is_isodream_train_exp_world_model(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="0")
    args = [a for a in TINY if a != "exp=world_model"] + ["run_dir=demo"]
    out = subprocess.run(
        [sys.executable, "-m", "isodream_rl.cli_demo", *args],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "run finished: 32 env steps, 2 updates" in out.stdout
    assert f"summary:     {Path('demo') / 'summary.json'}" in out.stdout
    assert json.loads((tmp_path / "demo" / "summary.json").read_text())["mode"] == "world_model"
    # an unknown flag, and an unknown key, are refused in one line
    for wrong, says in ((["--steps", "5"], "unknown flag --steps"), (["steps=5"], "'steps' is no setting")):
        refused = subprocess.run(
            [sys.executable, "-m", "isodream_rl.cli_demo", *wrong],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert refused.returncode == 2 and says in refused.stderr, refused.stderr[-3000:]
        assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr


def test_sigterm_saves_a_checkpoint_and_stops_before_the_summary(tmp_path):
    args = [*TINY, "world_model.updates=100000", "logging.log_every=1", "run_dir=run"]
    proc = cli_process(args, tmp_path)
    try:
        deadline = time.monotonic() + 50
        while not list((tmp_path / "run" / "logs").rglob("loss_model_reco.csv")):  # the first update is done
            assert proc.poll() is None and time.monotonic() < deadline, "the run did not start"
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM and "SIGTERM received" in stderr, stderr[-3000:]
    updates = latest_state(tmp_path / "run")["stepper"]["updates"]
    assert 0 < updates < 100000 and f"stopped at {updates} updates by SIGTERM" in stderr
    assert "run finished" not in stdout
    assert not (tmp_path / "run" / "summary.json").exists()
