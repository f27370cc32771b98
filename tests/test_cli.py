"""The real CLI (``python -m isodream_rl.cli``) with tiny overrides, SheepRL-style, and its config errors."""

import json
import re
import tempfile
from dataclasses import fields as dataclasses_fields
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import isodream_rl.cli  # noqa: F401  (registers the config schema)
from isodream_rl.trainers import AlgoConfig, ConfigError, RunConfig, validate_config
from isodream_rl.trainers.config import ALGO_NAMES
from isodream_rl.trainers.learners import ISODREAM_V2_ALGOS, TORCHRL_BASELINES, resolved
from tests.conftest import cli_run

CONFIGS = Path(isodream_rl.cli.__file__).parent / "configs"
ENVS = sorted(p.stem for p in (CONFIGS / "env").glob("*.yaml"))
ALGOS = sorted(p.stem for p in (CONFIGS / "algo").glob("*.yaml"))
SIZES = sorted(p.stem for p in (CONFIGS / "size").glob("*.yaml"))
EXPS = sorted(p.stem for p in (CONFIGS / "exp").glob("*.yaml"))
TINY = ["size=tiny", "train.threads=1", "logging.progress_bar=false"]


def run_cli(args, cwd, timeout=300):
    """``python -m isodream_rl.cli *args`` in ``cwd``, forked from a process that paid the imports once
    (``tests/conftest.py:cli_run``)."""
    return cli_run(args, cwd, timeout=timeout)


def composed(*overrides) -> RunConfig:
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return OmegaConf.to_object(compose(config_name="config", overrides=list(overrides)))


def test_groups_hold_the_presets_the_paper_needs():
    assert {"isodream", "isodream_paper", "dreamerv2", "isodream_no_inverse"} <= set(ALGOS)
    assert set(ALGOS) == set(ALGO_NAMES)  # the names the schema declares are the preset files
    assert set(SIZES) == {"paper", "small", "quickstart", "tiny", "bench"}
    assert {"sprites", "highway", "dmc_walker_walk"} <= set(ENVS)


@pytest.mark.parametrize("env", ENVS)
@pytest.mark.parametrize("algo", ALGOS)
def test_every_env_algo_preset_composes_to_a_valid_config(env, algo):
    cfg = composed(f"env={env}", f"algo={algo}", "size=tiny")
    validate_config(cfg)
    # every env preset names its env, but for gym's, an example id: the group is for any gymnasium id; and
    # sprites_reach, the plain sprites task of the quickstart
    assert cfg.env.name == {"gym": "Pendulum-v1", "sprites_reach": "sprites"}.get(env, env)
    assert cfg.algo.name == algo


#: The exp files whose runs a bench records (not docs/results/world_model_demo.json): the bench.
BENCH_RECIPES = {"decomposition": "bench/decomposition.py"}
RESULTS = CONFIGS.parents[1] / "docs" / "results"


@pytest.mark.parametrize("exp", EXPS)
def test_every_exp_composes_to_a_valid_config_and_its_results_page_names_the_recorded_runs(exp):
    cfg = composed(f"exp={exp}")
    validate_config(cfg)
    assert (
        cfg.algo.name in ISODREAM_V2_ALGOS
    )  # the exp names its algo, the recorded one (algo=isodream: the default's)
    header = (CONFIGS / "exp" / f"{exp}.yaml").read_text()
    # settings only: no run names or scores in the file, at most a pointer to the results page
    assert not re.search(r"\bruns? [A-Z]+[0-9]+\b|Recorded|R²", header), header
    if exp in BENCH_RECIPES:
        assert cfg.mode == "world_model" and cfg.run_dir.startswith(f"runs/{exp}")
        assert BENCH_RECIPES[exp] in header and (CONFIGS.parents[1] / BENCH_RECIPES[exp]).exists()
        return
    assert cfg.mode == "world_model" and cfg.run_dir.startswith("runs/world_model")
    assert "see docs/results/world_model_demo.md" in header
    recorded = json.loads((RESULTS / "world_model_demo.json").read_text())["runs"]
    page = (RESULTS / "world_model_demo.md").read_text()
    rows = [line for line in page.splitlines() if line.startswith("|") and re.search(rf"exp={exp}[` ]", line)]
    assert len(rows) == 1, rows  # the page's table of recipes: one row per exp, the runs in its last cell
    runs = re.findall(r"\b[A-Z]+[0-9]+\w*", rows[0].rstrip(" |").rsplit("|", 1)[1])
    assert runs and all(any(key.endswith(f" {run}") for key in recorded) for run in runs), runs


@pytest.mark.parametrize(
    "scene",
    [
        ["env=sprites", "env.kwargs.task=none"],
        ["env=dmc_walker_walk"],
        ["env=dmc_cheetah_run"],
        [
            "env=highway",
            "++env.kwargs.view=top_down",
            "++env.kwargs.top_down_follow=road",
            "++env.kwargs.top_down_scaling=2.5",
        ],
    ],
)
@pytest.mark.parametrize("algo", ["isodream_v2", "dreamerv2"])
def test_the_decomposition_recipe_is_the_same_on_every_scene(scene, algo):
    cfg = composed("exp=decomposition", *scene, f"algo={algo}")
    validate_config(cfg)
    cfg = resolved(cfg)
    assert cfg.algo.name == algo and cfg.run_dir == f"runs/decomposition-{cfg.env.name}-{algo}"
    assert (cfg.algo.free_branch_loss, cfg.algo.reward_uses_free, cfg.algo.lambda_reward) == (
        "kl",
        False,
        1.0,
    )
    assert (cfg.train.batch_size, cfg.train.sequence_length, cfg.train.world_model_lr) == (8, 16, 1e-3)
    assert (cfg.model.size, cfg.world_model.max_minutes, cfg.world_model.probe_episodes) == ("small", 30.0, 0)
    wm = cfg.world_model
    assert (wm.episodes, wm.episode_length, wm.held_out_episodes, wm.action_hold) == (60, 96, 4, 8)
    if cfg.env.name == "sprites":  # three discs, a new background per episode
        assert "num_backgrounds" not in cfg.env.kwargs and "num_distractors" not in cfg.env.kwargs
    if cfg.env.name.startswith("dmc_"):
        assert cfg.env.kwargs["background"] == "video_easy"
    if cfg.env.name == "highway":  # the road's view: the ego moves across the frame
        assert (cfg.env.kwargs["top_down_follow"], cfg.env.kwargs["top_down_scaling"]) == ("road", 2.5)


def test_domain_presets_follow_the_paper():
    dmc = composed("env=dmc_walker_walk")
    assert (dmc.env.domain, dmc.algo.policy_input, dmc.algo.reward_uses_free) == (
        "dmc",
        "controllable",
        False,
    )
    highway = composed("env=highway")
    assert (highway.env.domain, highway.algo.policy_input, highway.algo.reward_uses_free) == (
        "carla",
        "attention",
        True,
    )
    # the DreamerV2-style learner's own per-domain values come from its table, by env.domain
    dmc_v2, highway_v2 = (
        resolved(composed(f"env={env}", "algo=isodream_v2")) for env in ("dmc_walker_walk", "highway")
    )
    assert (dmc_v2.algo.free_branch_loss, highway_v2.algo.free_branch_loss) == ("recon_only", "kl")
    assert (dmc_v2.algo.lambda_reward, highway_v2.algo.lambda_reward) == (2.0, 2.0)
    assert (
        dmc.algo.free_branch_loss is None and resolved(dmc).algo.free_branch_loss is None
    )  # the default's: none
    assert highway.algo.attention_window == 5 and highway.env.action_repeat == 4
    paper = composed("size=paper")
    assert (paper.train.batch_size, paper.train.sequence_length, paper.train.prefill_steps) == (50, 50, 2500)
    assert paper.train.train_every == 5


def test_sprites_trains_with_the_library_defaults_and_the_paper_preset_with_the_papers_settings():
    """The DreamerV2-style learner: ``algo=isodream_v2`` at the library's settings, ``isodream_paper`` at the
    paper's."""
    from isodream_rl.modules.isodream_v2 import IsoDreamV2Config
    from isodream_rl.modules.isodream_v2.config import PAPER_EXACT
    from isodream_rl.objectives.isodream_v2.world_model import PAPER_WEIGHTS
    from isodream_rl.trainers.isodream_v2 import make_world_model_loss

    defaults = make_world_model_loss(composed("env=sprites", "size=tiny", "algo=isodream_v2"), action_dim=2)
    library = IsoDreamV2Config(action_dim=2)
    for name in PAPER_EXACT:
        assert getattr(defaults.world_model.config, name) == getattr(library, name)
    assert defaults.inverse_loss.lambda_inverse == 30.0
    paper = make_world_model_loss(composed("env=sprites", "size=tiny", "algo=isodream_paper"), action_dim=2)
    for name, value in PAPER_EXACT.items():
        assert getattr(paper.world_model.config, name) == value
    assert paper.inverse_loss.lambda_inverse == PAPER_WEIGHTS["lambda_inverse"]


def test_dreamerv2_preset_is_the_libraries_baseline():
    from isodream_rl.modules.isodream_v2 import IsoDreamV2Config
    from isodream_rl.trainers.isodream_v2 import make_world_model_config

    trained = make_world_model_config(composed("algo=dreamerv2", "size=tiny"), action_dim=2)
    baseline = IsoDreamV2Config.dreamerv2("tiny", action_dim=2)
    assert trained.to_dict() == {**baseline.to_dict(), "channels_last": trained.channels_last}


def test_wrong_type_fails_naming_the_key():
    with pytest.raises(Exception, match="train.total_steps"):
        composed("train.total_steps=many")


def test_impossible_combination_says_what_to_change():
    cfg = composed("algo=dreamerv2", "algo.policy_input=attention")
    with pytest.raises(ConfigError, match="set algo.policy_input=controllable or algo.free_branch=true"):
        validate_config(cfg)


def test_lr_warmup_sets_dreamer_v3s_optimisers_and_is_refused_elsewhere():
    from isodream_rl.trainers.registry import make_components

    for algo in ("isodream", "torchrl_dreamer_v3"):
        cfg = composed(f"algo={algo}", "size=tiny", "train.lr_warmup=7")
        validate_config(cfg)
        with tempfile.TemporaryDirectory() as scratch:
            components = make_components(cfg, action_dim=2, scratch_dir=Path(scratch))
        optimizers = components.stepper.optimizers.values()
        assert {group["warmup_steps"] for opt in optimizers for group in opt.param_groups} == {7}, algo
    with pytest.raises(
        ConfigError, match=r"train.lr_warmup=7 is not read by algo=isodream_v2 .*TorchRL's DreamerV3"
    ):
        validate_config(composed("algo=isodream_v2", "train.lr_warmup=7"))
    with pytest.raises(ConfigError, match=r"train.lr_warmup=-1 must be >= 0"):
        validate_config(composed("train.lr_warmup=-1"))


def test_the_former_name_of_the_default_is_refused_naming_the_new_one():
    from isodream_rl.cli_overrides import check_overrides

    message = r"algo=isodream_v3 is now algo=isodream \(.*the DreamerV2-style learner is algo=isodream_v2\)"
    with pytest.raises(ConfigError, match=message):
        check_overrides(["algo=isodream_v3", "size=tiny"])
    cfg = composed("algo.name=isodream_v3")  # the field itself: validate_config refuses it
    with pytest.raises(ConfigError, match=message):
        validate_config(cfg)


def test_a_config_saved_before_the_default_became_dreamer_v3s_learner_reads_back_under_todays_names():
    import dataclasses

    from isodream_rl.trainers.config import config_from_dict

    saved = dataclasses.asdict(composed("algo=isodream"))
    saved["algo"]["name"] = "isodream_v3"  # Iso-Dream on DreamerV3's learner, as it was named
    assert config_from_dict(saved).algo.name == "isodream"
    # mode=world_model trained the DreamerV2-style model under that name; it now trains the default's too, so the
    # configuration reads as saved and the weights tell (tests/test_world_model_mode.py reads such a run back)
    from isodream_rl.trainers.saved_models import saved_run_config

    world_model = dataclasses.asdict(composed("exp=world_model"))
    world_model["algo"]["name"] = "isodream"
    assert config_from_dict(world_model).algo.name == "isodream"
    for prefix, learner in (("control_rssm.", "isodream_v2"), ("control_prior.", "isodream")):
        state = {"config": world_model, "models": {"world_model": {f"{prefix}weight": None}}}
        assert saved_run_config(state).algo.name == learner
    assert (
        config_from_dict(dataclasses.asdict(composed("exp=world_model_dreamerv2"))).algo.name == "dreamerv2"
    )
    assert config_from_dict(dataclasses.asdict(composed())).algo.name == "isodream"  # mode=rl: as saved


def test_unknown_group_option_fails_listing_the_valid_options():
    with pytest.raises(Exception, match="Could not find 'env/carla'") as err:
        composed("env=carla")
    assert "sprites" in str(err.value) and "highway" in str(err.value)


def test_impossible_combination_fails_in_the_cli_before_training(tmp_path):
    out = run_cli(["algo=dreamerv2", "algo.policy_input=attention", *TINY], tmp_path)
    assert out.returncode == 2
    assert "set algo.policy_input=controllable or algo.free_branch=true" in out.stderr
    assert not list(tmp_path.glob("runs/*/checkpoints"))


@pytest.mark.parametrize(
    "flag, hint",
    [(["--steps", "300"], "train.total_steps=...?"), (["--steps=300"], "train.total_steps=300?")],
)
def test_an_unknown_flag_is_one_line_naming_it_not_hydras_usage(flag, hint, tmp_path):
    out = run_cli([*flag, *TINY], tmp_path, timeout=120)
    assert out.returncode == 2, out.stderr[-2000:]
    assert out.stderr.strip().splitlines() == [out.stderr.strip()], out.stderr  # one line
    assert out.stderr.startswith(f"isodream-train: unknown flag {flag[0]} (did you mean {hint})")
    assert "key=value" in out.stderr and "usage:" not in out.stderr


def test_every_algo_trains_on_sprites_and_evaluates(tmp_path, capsys):
    sweep = ",".join(ALGOS)
    args = ["-m", f"algo={sweep}", *TINY, "train.total_steps=40", "train.prefill_steps=20"]
    args += ["train.frames_per_batch=20", "logging.eval_every=30", "logging.log_every=10"]
    args += ["env.kwargs.max_steps=30", "logging.final_eval_episodes=2"]
    out = run_cli(args, tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count("run finished: 40 env steps, 8 updates") == len(ALGOS)
    for algo in ALGOS:
        run = tmp_path / "runs" / f"sprites-{algo}-tiny"
        assert list((run / "checkpoints").glob("step_00000008")), algo
        if algo not in TORCHRL_BASELINES:  # TorchRL's world models have no branches to picture
            assert list((run / "pictures").glob("openloop_*.gif")), algo
        assert list((run / "logs").rglob("*.csv")), algo
        summary = json.loads((run / "summary.json").read_text())
        assert summary["eval_episodes"] == 2 and summary["env_steps"] == 40 and summary["wall_s"] > 0
        refs = summary["references"]
        assert summary["scripted_return"] == refs["scripted"]["return"] > summary["constant_return"]
        expected = (summary["eval_return"] - summary["constant_return"]) / (
            summary["scripted_return"] - summary["constant_return"]
        )
        assert summary["normalised_score"] == pytest.approx(expected)
        assert summary["eval_reaches"] >= 0 and refs["scripted"]["reaches"] > refs["random"]["reaches"]

    # isodream-eval's entry point, in this process (its start-up would double the test's time).
    video = tmp_path / "eval.gif"
    isodream_rl.cli.evaluate(
        [str(tmp_path / "runs" / "sprites-isodream-tiny"), "--episodes", "2", "--video", str(video)]
    )
    assert re.search(r"return over 2 episodes: -?[0-9.]+ \+- [0-9.]+", capsys.readouterr().out)
    assert video.stat().st_size > 0


@pytest.mark.parametrize("env", ["highway", "dmc_walker_walk"])
def test_every_algo_trains_on_the_simulated_envs(env, tmp_path):
    sweep = ",".join(ALGOS)
    args = ["-m", f"env={env}", f"algo={sweep}", *TINY, "train.total_steps=10", "train.prefill_steps=10"]
    args += ["train.frames_per_batch=10", "logging.final_eval_episodes=0"]
    out = run_cli(args, tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count("run finished: 10 env steps, 2 updates") == len(ALGOS)


def test_quickstart_preset_is_the_readme_main_job():
    readme = (Path(isodream_rl.cli.__file__).parents[1] / "README.md").read_text()
    assert "isodream-train size=quickstart" in readme
    cfg = composed("size=quickstart")
    validate_config(cfg)
    assert (cfg.env.name, cfg.algo.name, cfg.train.total_steps, cfg.train.threads) == (
        "sprites",
        "isodream",
        25000,
        1,
    )
    # the plain reach task (env=sprites_reach) unless an env is named; a named env keeps its own settings
    assert dict(cfg.env.kwargs) == {
        "task": "reach",
        "max_steps": 200,
        "num_distractors": 0,
        "sprite_size": 0.15,
        "num_backgrounds": 1,
    }
    for named in (["env=sprites", "size=quickstart"], ["size=quickstart", "env=sprites"]):
        assert dict(composed(*named).env.kwargs) == {"task": "reach", "max_steps": 200}
    assert composed("size=quickstart", "env=highway").env.name == "highway"
    assert cfg.run_dir == "runs/sprites-isodream-quickstart"
    assert 0 < cfg.logging.eval_every < cfg.train.total_steps  # pictures during the run, not only at the end


def test_readme_main_job_shows_a_progress_bar_and_says_where_its_outputs_went(tmp_path):
    # `isodream-train size=quickstart` with its length cut to a few batches.
    args = ["size=quickstart", "train.total_steps=40", "train.prefill_steps=20", "train.frames_per_batch=20"]
    args += [
        "train.sequence_length=8",
        "train.batch_size=2",
        "logging.video_length=8",
        "logging.eval_every=20",
    ]
    args += ["logging.log_every=10", "env.kwargs.max_steps=30"]
    out = run_cli(args, tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert re.search(r"updates_per_s: [0-9.]+.*\| *40/40", out.stderr), "no tqdm bar with updates/s"
    run = Path("runs/sprites-isodream-quickstart")
    assert "run finished: 40 env steps, 8 updates" in out.stdout
    for line in (f"logs:        {run / 'logs'}", f"checkpoint:  {run / 'checkpoints' / 'step_00000008'}"):
        assert line in out.stdout
    gif = re.search(r"newest open-loop prediction: (\S+)", out.stdout).group(1)
    assert (tmp_path / gif).stat().st_size > 0
    assert list((tmp_path / run / "logs").rglob("loss_model_reco.csv"))


def test_a_config_saved_before_the_loc_penalty_reads_back_with_the_loss_it_trained_with():
    import dataclasses

    from isodream_rl.trainers.config import config_from_dict
    from isodream_rl.trainers.run_dir import differing_settings

    today = RunConfig(algo=AlgoConfig(name="isodream_v2"))
    saved = dataclasses.asdict(resolved(today))
    assert saved["algo"]["actor_loc_penalty"] == 0.1  # the DreamerV2-style learner's today
    del saved["algo"]["actor_loc_penalty"]  # as run_config.json and checkpoints had it before
    assert config_from_dict(saved).algo.actor_loc_penalty == 0.0
    # so resuming such a run with today's defaults is refused, naming the setting, instead of changing its loss
    assert differing_settings(saved, today) == {"algo.actor_loc_penalty": (0.0, 0.1)}
    saved["algo"]["actor_loc_penalty"] = 0.1
    assert config_from_dict(saved).algo.actor_loc_penalty == 0.1


def test_a_config_saved_with_model_overrides_reads_back_into_the_typed_model_fields():
    import dataclasses

    from isodream_rl.trainers.config import config_from_dict
    from isodream_rl.trainers.run_dir import differing_settings

    now = composed("algo=isodream_v2", "size=bench", "model.precision=bf16")
    saved = dataclasses.asdict(now)
    # as size=bench wrote it before: the small preset, its widths and the precision in model.overrides
    model = {"depth": 8, "belief_dim": 64, "hidden_dim": 64, "precision": "bf16"}
    saved["model"] = {
        **{k: v for k, v in saved["model"].items() if v is not None},
        "size": "small",
        "overrides": model,
    }
    assert config_from_dict(saved).model.world_model_fields() == model
    assert differing_settings(saved, now) == {}  # the same run: a resume goes on
    deeper = composed("algo=isodream_v2", "size=bench", "model.precision=bf16", "model.depth=16")
    assert differing_settings(saved, deeper) == {"model.depth": (8, 16)}


@pytest.mark.parametrize("env", ["sprites", "dmc_walker_walk"])
def test_a_run_saved_by_an_algo_that_changed_learner_resumes_as_isodream_v2(env):
    import dataclasses

    from isodream_rl.trainers.learners import ISODREAM_ALGOS
    from isodream_rl.trainers.renames import FORMER_DREAMER_V2_ALGOS
    from isodream_rl.trainers.run_dir import differing_settings

    assert set(FORMER_DREAMER_V2_ALGOS) == set(ISODREAM_ALGOS)
    for name, settings in FORMER_DREAMER_V2_ALGOS.items():
        # saved by algo=<name> (its algo fields are the same before and after it changed learner), continued by
        # algo=isodream_v2 with the settings that build the same variant; the weights tell which it was
        saved = dataclasses.asdict(composed(f"env={env}", f"algo={name}"))
        assert differing_settings(saved, composed(f"env={env}", "algo=isodream_v2", *settings)) == {}, name
    # not the other way round: a run saved as algo=isodream_v2 is the DreamerV2-style learner's
    saved = dataclasses.asdict(composed(f"env={env}", "algo=isodream_v2"))
    assert differing_settings(saved, composed(f"env={env}"))["algo.name"] == ("isodream_v2", "isodream")


def test_the_model_section_holds_every_world_model_field_but_the_envs():
    from isodream_rl.modules.isodream_v2.config import IsoDreamV2Config
    from isodream_rl.trainers.config import ModelConfig

    names = [f.name for f in dataclasses_fields(ModelConfig)]
    # the preset, the behavior widths and the default learner's action-free width, then the world model's fields
    assert names[:5] == ["size", "actor_units", "value_units", "attention_dim", "free_hidden_fraction"]
    assert names[5:] == [f.name for f in dataclasses_fields(IsoDreamV2Config) if f.name != "action_dim"]
    assert all(getattr(ModelConfig(), name) is None for name in names[4:])  # None: the preset's value
    assert composed("model.depth=8", "model.precision=bf16").model.world_model_fields() == {
        "depth": 8,
        "precision": "bf16",
    }


def test_the_loss_weights_have_one_table_per_learner_and_the_paper_preset_names_its_alpha_once():
    from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS
    from isodream_rl.objectives.isodream_v2.world_model import LOSS_WEIGHTS, PAPER_WEIGHTS
    from isodream_rl.trainers.isodream_v2 import make_world_model_loss

    loss = make_world_model_loss(
        composed("size=tiny", "env=dmc_walker_walk", "algo=isodream_v2"), action_dim=2
    )
    for name, weight in LOSS_WEIGHTS.items():
        if name != "lambda_reward":  # the DMC env group's 2 (the authors' reward_scale)
            assert getattr(loss.inverse_loss if name == "lambda_inverse" else loss, name) == weight
    assert resolved(composed("algo=isodream_paper")).algo.lambda_inverse == PAPER_WEIGHTS["lambda_inverse"]
    assert resolved(composed("algo=isodream_paper", "algo.lambda_inverse=5")).algo.lambda_inverse == 5.0
    assert resolved(composed("algo=isodream_v2")).algo.lambda_inverse == LOSS_WEIGHTS["lambda_inverse"]
    # the default's is its own table's, whatever the DreamerV2-style learner's
    assert resolved(composed()).algo.lambda_inverse == ISODREAM_SETTINGS.lambda_inverse
    assert composed().algo.lambda_inverse is None is RunConfig().algo.lambda_inverse  # None: the learner's


@pytest.mark.parametrize("algo", ALGOS)
def test_the_branch_switches_of_every_algo_come_from_one_table(algo):
    import yaml

    from isodream_rl.trainers.config import ALGO_BRANCHES

    written = yaml.safe_load((CONFIGS / "algo" / f"{algo}.yaml").read_text())["algo"]
    assert not set(written) & set(ALGO_BRANCHES[algo])  # the YAML files do not repeat them
    cfg = composed(f"algo={algo}", "size=tiny")
    assert {name: getattr(cfg.algo, name) for name in ALGO_BRANCHES[algo]} == ALGO_BRANCHES[algo]
    given = composed(f"algo={algo}", "algo.static_branch=false")
    assert given.algo.static_branch is False  # a value given wins


@pytest.mark.parametrize("env", ENVS)
def test_env_groups_set_env_fields_only_and_pick_a_domain(env):
    import yaml

    written = yaml.safe_load((CONFIGS / "env" / f"{env}.yaml").read_text())
    assert set(written) == {"defaults", "env"}  # the algorithm's per-domain choices live in configs/domain/
    picks = [entry for entry in written["defaults"] if isinstance(entry, dict)]
    while not any("/domain" in entry for entry in picks):
        # builds on another env group (env=sprites_reach on env=sprites), which picks the domain; the group may
        # pick its own over the base's ("override /domain")
        (base,) = [entry for entry in written["defaults"] if isinstance(entry, str) and entry != "_self_"]
        written = yaml.safe_load((CONFIGS / "env" / f"{base}.yaml").read_text())
        assert set(written) == {"defaults", "env"}
        picks += [entry for entry in written["defaults"] if isinstance(entry, dict)]
    for entry in picks:
        (domain,) = entry.values()
        assert (CONFIGS / "domain" / f"{domain}.yaml").exists()
    stored = composed("env=dmc_cartpole_swingup")  # a DMC task without a YAML file picks domain=dmc too
    assert (stored.env.domain, stored.algo.policy_input, stored.algo.reward_uses_free) == (
        "dmc",
        "controllable",
        False,
    )


def test_an_env_argument_the_env_group_does_not_write_is_accepted_without_a_plus():
    """``env.kwargs.contact_penalty=0.0`` is an argument of the sprites env: isodream-train gives it to Hydra as
    ``++env.kwargs...`` (Hydra alone refuses a key its group did not write, "not in struct")."""
    from isodream_rl.cli_overrides import check_overrides, free_form_overrides

    line = free_form_overrides(["env=sprites_reach", "env.kwargs.contact_penalty=0.0", "+env.kwargs.seed=1"])
    assert line == ["env=sprites_reach", "++env.kwargs.contact_penalty=0.0", "+env.kwargs.seed=1"]
    check_overrides(line)
    assert composed(*line).env.kwargs["contact_penalty"] == 0.0
    assert free_form_overrides(["train.slurm_kwargs.timeout_min=5"]) == ["++train.slurm_kwargs.timeout_min=5"]


def test_the_highway_top_down_options_reach_the_env_from_the_command_line():
    from isodream_rl.cli_overrides import free_form_overrides
    from isodream_rl.envs import make_gym_env
    from isodream_rl.trainers.builders import env_factory

    options = [
        "++env.kwargs.view=top_down",
        "++env.kwargs.top_down_follow=road",
        "++env.kwargs.top_down_scaling=2.5",
    ]
    plain = [option.removeprefix("++") for option in options]  # isodream-train adds the ++ itself
    assert free_form_overrides(["env=highway", *plain]) == ["env=highway", *options]
    cfg = composed("env=highway", *options)
    validate_config(cfg)
    factory = env_factory(cfg)
    assert factory.args == ("highway",)
    assert {k: factory.keywords[k] for k in ("top_down_follow", "top_down_scaling")} == {
        "top_down_follow": "road",
        "top_down_scaling": 2.5,
    }
    env = make_gym_env(cfg.env.name, **factory.keywords)
    assert (env.view, env.top_down_follow, env.top_down_scaling) == ("top_down", "road", 2.5)
    env.close()


@pytest.mark.parametrize(
    ("line", "refused", "readers"),
    [
        (["algo.gamma=0.9"], "algo.gamma=0.9 is not read by algo=isodream", "the DreamerV2-style learner"),
        (
            ["algo.exploration_noise=0.3"],
            "algo.exploration_noise=0.3 is not read by algo=isodream",
            "isodream_v2",
        ),
        (["model.depth=8"], "model.depth=8 is not read by algo=isodream", "TorchRL's Dreamer"),
        (
            ["algo=torchrl_dreamer_v3", "train.grad_clip=10"],
            "train.grad_clip=10.0 is not read",
            "torchrl_dreamer",
        ),
        (
            ["algo=isodream_v2", "train.lr_warmup=7"],
            "train.lr_warmup=7 is not read",
            "Iso-Dream on DreamerV3's",
        ),
    ],
)
def test_a_setting_the_learner_does_not_read_is_refused_naming_the_learners_that_do(line, refused, readers):
    with pytest.raises(ConfigError, match=rf"{re.escape(refused)} .*{re.escape(readers)}"):
        validate_config(composed(*line, "size=tiny"))


def test_each_learner_reads_its_own_table_and_the_default_leaves_the_others_unset():
    from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS
    from isodream_rl.trainers.learners import ISODREAM_V2_SETTINGS, learner_of

    default = resolved(composed("env=sprites"))
    assert default.algo.lambda_inverse == ISODREAM_SETTINGS.lambda_inverse
    assert default.train.lr_warmup == ISODREAM_SETTINGS.lr_warmup
    reads = learner_of("isodream").values
    unread = [key for key in ISODREAM_V2_SETTINGS if key not in reads and not key.startswith("model.")]
    assert "algo.gamma" in unread and "train.grad_clip" in unread
    assert all(getattr(getattr(default, k.split(".")[0]), k.split(".")[1]) is None for k in unread)
    v2 = resolved(composed("env=sprites", "algo=isodream_v2"))
    assert (v2.algo.gamma, v2.algo.lambda_reward, v2.train.grad_clip, v2.train.lr_warmup) == (
        0.9,
        2.0,
        100.0,
        None,
    )


def test_a_config_saved_before_the_settings_tables_reads_back_without_what_its_learner_never_read():
    """Before each learner had its own table, every configuration held the DreamerV2-style learner's values; the
    default's run folders made then resume as they are (those values dropped), and so do the DreamerV2-style ones."""
    import dataclasses

    from isodream_rl.trainers.config import config_from_dict
    from isodream_rl.trainers.run_dir import differing_settings

    saved = dataclasses.asdict(composed("size=quickstart"))
    saved["algo"].update(gamma=0.9, lambda_reward=2.0, exploration_noise=0.3, free_branch_loss="kl")
    saved["train"].update(grad_clip=100.0, adam_eps=1e-5)
    cfg = config_from_dict(saved)
    assert (cfg.algo.gamma, cfg.algo.exploration_noise, cfg.train.grad_clip) == (None, None, None)
    validate_config(cfg)
    assert differing_settings(saved, composed("size=quickstart")) == {}
    old_v2 = dataclasses.asdict(resolved(composed("algo=isodream_v2")))
    assert differing_settings(old_v2, composed("algo=isodream_v2")) == {}
