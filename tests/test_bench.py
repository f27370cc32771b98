"""``bench/world_model_speed.py`` at a tiny size: it runs both sides and writes the JSON the issue names."""

import json

import pytest

from tests.conftest import load_bench


@pytest.fixture(scope="module")
def bench():
    return load_bench("world_model_speed")


def test_world_model_speed_writes_both_times_their_ratio_and_the_flops(bench, tmp_path):
    path = tmp_path / "speed.json"
    variants = "ours_fp32_cl,ours_bf16_cl,torchrl_fp32_nchw,torchrl_fp32_cl,torchrl_bf16_cl"
    args = ["--size", "tiny", "--batch-size", "2", "--time", "4", "--steps", "2", "--warmup", "1"]
    out = bench.main([*args, "--variants", variants, "--profile", "--json", str(path)])
    assert json.loads(path.read_text()) == out
    ms = {name: v["ms"] for name, v in out["variants"].items()}
    assert set(ms) == set(variants.split(","))
    assert out["ours_ms"] == ms["ours_fp32_cl"] and out["torchrl_ms"] == ms["torchrl_fp32_cl"]
    assert out["ratio"] == round(ms["ours_fp32_cl"] / ms["torchrl_fp32_cl"], 3)
    assert out["ratio_bf16"] == round(ms["ours_bf16_cl"] / ms["torchrl_bf16_cl"], 3)
    assert out["fastest_ours"] == min(("ours_fp32_cl", "ours_bf16_cl"), key=ms.get)
    assert out["ratio_fast_vs_default"] == round(ms[out["fastest_ours"]] / ms["torchrl_fp32_nchw"], 3)
    # two full-width dynamic decoders, encoder heads and the static branch: more FLOPs than one Dreamer
    assert out["flops_ratio"] > 1.2
    assert set(out["profile_ms"]) == {n for n in ms if n.endswith("_cl")}
    assert out["config"]["batch_size"] == 2 and out["config"]["time"] == 4
    assert {"cpu_avx512_bf16", "cpu_amx"} <= set(out["config"])


def test_video_prediction_bench_trains_equal_budgets_resumes_and_checks_the_aims(tmp_path, monkeypatch):
    """Tiny runs through the whole bench: seeds, the single-seed variants, JSON shape, pictures, and a second
    call with more iterations that resumes every run instead of starting over."""
    import json
    import sys

    bench = load_bench("video_prediction")
    monkeypatch.setenv("ISODREAM_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("MUJOCO_GL", "egl")
    out = tmp_path / "video.json"

    def run(iterations: int) -> dict:
        argv = ["video_prediction.py", "--json", str(out), "--out-dir", str(tmp_path / "runs"),
                "--variants", "isodream", "predrnn", "--seeds", "0", "1", "--iterations", str(iterations),
                "--val-every", "1", "--val-batches", "1", "--checkpoint-every", "1", "--train-sequences", "2",
                "--test-sequences", "2", "--batch-size", "2", "--hidden-channels", "4", "--encoder-channels", "4",
                "4", "--action-embedding", "4", "--precision", "fp32"]  # fmt: skip
        monkeypatch.setattr(sys, "argv", argv)
        assert bench.main() == 0
        return json.loads(out.read_text())

    first = run(1)
    assert [r["seed"] for r in first["variants"]["isodream"]["seeds"]] == [0, 1]
    assert [r["seed"] for r in first["variants"]["predrnn"]["seeds"]] == [0]  # a single-seed variant
    assert set(first["aims"]["above_copy_last_frame"]) == {"isodream", "predrnn"}
    assert (
        set(first["copy_last_frame"]) >= {"psnr_28", "ssim_28"}
        and len(first["curves"]["copy_last_frame"]["psnr"]) == 28
    )
    for name in ("_curves.png", "_validation.png", "_showcase.png"):
        assert out.with_name(out.stem + name).stat().st_size > 0
    assert "copy_last_frame" in out.with_suffix(".md").read_text()

    second = run(2)  # every run continues from its checkpoint: validation points 0, 1, then 2
    for variant in ("isodream", "predrnn"):
        assert all(r["iterations"] == 2 for r in second["variants"][variant]["seeds"])
        assert [p["iteration"] for p in second["history"][variant]["seed_0"]] == [0, 1, 2]
    assert second["history"]["isodream"]["seed_0"][:2] == first["history"]["isodream"]["seed_0"]


def test_update_rate_reads_the_runs_own_rate_and_plans_10k_updates(tmp_path):
    module = load_bench("update_rate")
    path = tmp_path / "rate.json"
    result = module.main(
        [
            "--algos",
            "dreamerv2",
            "--sizes",
            "tiny",
            "--updates",
            "60",
            "--log-every",
            "50",
            "--json",
            str(path),
        ]
    )
    entry = result["rates"]["dreamerv2"]["tiny"]
    assert entry["updates_per_s"] > 0 and len(entry["updates_per_s_rows"]) >= 1
    assert entry["hours_per_10k_updates"] == pytest.approx(10_000 / entry["updates_per_s"] / 3600)
    assert entry["env_steps"] == 50 + 5 * 60
    saved = json.loads(path.read_text())
    assert saved["rates"] == result["rates"] and saved["cpu"] and saved["overrides"] == module.RUNG1


def test_update_speed_builds_each_learner_with_fast_paths_once_per_value_asked():
    """``--fast-paths``: the learners that read ``model.fast_paths`` under their name when on and as
    ``<algo>[fast_paths=false]`` when off; TorchRL's DreamerV3, which has none, once as it is."""
    variants = load_bench("update_speed").variants
    algos = ["isodream", "torchrl_dreamer_v3", "isodream_v2"]
    assert variants(algos, "on") == [
        ("isodream", "isodream", True),
        ("torchrl_dreamer_v3", "torchrl_dreamer_v3", None),
        ("isodream_v2", "isodream_v2", True),
    ]
    assert variants(algos[:2], "off") == [
        ("isodream[fast_paths=false]", "isodream", False),
        ("torchrl_dreamer_v3", "torchrl_dreamer_v3", None),
    ]
    assert [label for label, _, _ in variants(algos[:2], "both")] == [
        "isodream",
        "isodream[fast_paths=false]",
        "torchrl_dreamer_v3",
    ]
    with pytest.raises(ValueError, match="fast_paths must be one of"):
        variants(algos, "true")
    with pytest.raises(ValueError, match=r"listed more than once: \['isodream'\]"):
        variants(["isodream", "isodream"], "on")


def test_update_speed_times_the_default_with_and_without_its_fast_paths(tmp_path):
    path = tmp_path / "speed.json"
    args = ["--size", "tiny", "--algos", "isodream,torchrl_dreamer_v3", "--fast-paths", "both"]
    out = load_bench("update_speed").main([*args, "--rounds", "1", "--warmup", "0", "--json", str(path)])
    assert json.loads(path.read_text()) == out and out["fast_paths"] == "both"
    entries = out["algos"]
    assert list(entries) == ["isodream", "isodream[fast_paths=false]", "torchrl_dreamer_v3"]
    assert [(e["algo"], e["fast_paths"]) for e in entries.values()] == [
        ("isodream", True),
        ("isodream", False),
        ("torchrl_dreamer_v3", None),
    ]
    reference = entries["isodream[fast_paths=false]"]
    assert reference["parameters"] == entries["isodream"]["parameters"]  # the same learner
    assert reference["parameters"]["world_model"] > 0 and out["cpu"]
    expected = reference["median_wall_s"] / entries["isodream"]["median_wall_s"]
    assert reference["ratio_to_isodream"] == pytest.approx(expected)


def test_update_speed_env_builds_the_quickstart_learner_as_it_trains(tmp_path):
    """``--env sprites_reach``: the learner the quickstart trains (its env group, hence no static branch: fewer
    world-model parameters than ``env=sprites``'s), recorded as the JSON's ``env``; ``sprites`` is the default."""
    module = load_bench("update_speed")
    assert module.run_config("isodream", "tiny").algo.static_branch
    assert not module.run_config("isodream", "tiny", env="sprites_reach").algo.static_branch
    path = tmp_path / "speed.json"
    args = ["--size", "tiny", "--algos", "isodream", "--rounds", "1", "--warmup", "0", "--json", str(path)]
    reach = module.main([*args, "--env", "sprites_reach"])
    assert json.loads(path.read_text()) == reach and reach["env"] == "sprites_reach"
    assert reach["thp_mem_alloc"] is None  # torch came first: the process keeps its own setting
    sprites = module.main(args)
    assert sprites["env"] == "sprites"
    parameters = [out["algos"]["isodream"]["parameters"]["world_model"] for out in (reach, sprites)]
    assert 0 < parameters[0] < parameters[1]


def test_update_speed_times_updates_after_the_world_model_warm_up():
    """The quickstart's first 500 updates train the world model alone: the bench times the other kind (world model
    and behaviour), which are 4400 of its 4900."""
    module = load_bench("update_speed")
    for algo in ("isodream", "torchrl_dreamer_v3"):
        assert module.run_config(algo, "quickstart", env="sprites_reach").train.world_model_warmup == 0


def test_update_speed_times_one_full_update_of_each_algorithm_on_one_sample(tmp_path):
    module = load_bench("update_speed")
    path = tmp_path / "speed.json"
    args = ["--size", "tiny", "--rounds", "2", "--warmup", "1", "--json", str(path)]
    out = module.main(args)
    assert json.loads(path.read_text()) == out
    assert set(out["algos"]) == {"isodream", "isodream_v2", "dreamerv2", "torchrl_dreamer_v3"}
    assert out["cpu"] and out["torch_threads"] == 1 and out["size"] == "tiny" and out["fast_paths"] == "on"
    for algo, entry in out["algos"].items():
        assert len(entry["wall_s"]) == len(entry["cpu_s"]) == 2, algo
        assert entry["updates_per_s"] == pytest.approx(1 / entry["median_wall_s"])
        for reference in ("isodream", "dreamerv2"):
            expected = entry["median_wall_s"] / out["algos"][reference]["median_wall_s"]
            assert entry[f"ratio_to_{reference}"] == pytest.approx(expected)
        assert set(entry["parameters"]) == {"world_model", "actor", "value"}
        assert entry["algo"] == algo  # fast paths on where the learner has them (the default)
        assert entry["fast_paths"] is (None if algo == "torchrl_dreamer_v3" else True), algo
    assert out["algos"]["isodream"]["ratio_to_isodream"] == 1.0


def test_openloop_png_stacks_the_chosen_frames_of_a_gif_downwards(tmp_path):
    from PIL import Image

    openloop_png = load_bench("openloop_png")

    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255)]
    frames = [Image.new("RGB", (6, 4), c) for c in colours]
    frames[0].save(tmp_path / "a.gif", save_all=True, append_images=frames[1:], duration=100)
    png = openloop_png.main([str(tmp_path / "a.gif"), str(tmp_path / "a.png"), "--steps", "0,-1"])
    picture = Image.open(png).convert("RGB")
    assert picture.size == (6, 8)
    assert picture.getpixel((0, 0)) == colours[0] and picture.getpixel((0, 7)) == colours[2]
    with pytest.raises(ValueError, match="outside the GIF's 3 frames"):
        openloop_png.stack_frames(openloop_png.gif_frames(tmp_path / "a.gif"), [3])


def test_run_summary_wraps_a_finished_runs_summary_with_its_training_command(tmp_path):
    bench = load_bench("run_summary")
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(
        "- size=quickstart\n- train.threads=1\n- run_dir=/somewhere\n"
    )
    with pytest.raises(SystemExit, match="has not finished"):
        bench.run_summary(run, train_commit="abc1234")
    summary = {"eval_return": 153.3, "normalised_score": 0.56, "isolation": {"agent_branch": "control"}}
    (run / "summary.json").write_text(json.dumps(summary))
    out_json = tmp_path / "out.json"
    bench.main([str(run), "--train-commit", "abc1234", "--note", "one run per core", "--json", str(out_json)])
    out = json.loads(out_json.read_text())
    assert out["command"] == "isodream-train size=quickstart train.threads=1"
    assert out["train_commit"] == "abc1234" and out["note"] == "one run per core"
    assert out["summary"] == summary
    assert out["collected_by"]["command"].startswith("python bench/run_summary.py ")
    (run / ".hydra" / "overrides.yaml").unlink()
    with pytest.raises(SystemExit, match="not an isodream-train run folder"):
        bench.run_summary(run, train_commit="abc1234")


def test_world_model_flops_counts_each_learners_update_by_module(tmp_path):
    """``bench/world_model_flops.py`` at the tiny size: both learners' updates, the forward split by the world
    model's modules (each dynamic branch's decoder among them), the JSON as returned."""
    flops = load_bench("world_model_flops")
    path = tmp_path / "flops.json"
    out = flops.main(["--sizes", "tiny", "--override", "train.batch_size=2", "--json", str(path)])
    assert json.loads(path.read_text()) == out
    runs = {run["algo"]: run for run in out["runs"]}
    assert set(runs) == {"isodream", "isodream_v2"}
    for run in runs.values():
        assert run["batch_size"] == 2 and run["sequence_length"] == 16
        # backward costs more than the forward alone; each module's share is part of the forward
        assert run["gflop_update"] > 2 * run["gflop_forward"] > 0
        assert {"control_decoder", "free_decoder", "static_decoder"} <= set(run["forward_by_module"])
        assert 0 < max(run["forward_by_module"].values()) <= run["gflop_forward"]
        assert run["parameters"] > 0
    # the two dynamic decoders are alike in each learner
    default = runs["isodream"]["forward_by_module"]
    assert default["control_decoder"] == pytest.approx(default["free_decoder"], rel=0.05)


def test_run_curves_reads_what_an_unfinished_run_has_logged(tmp_path):
    """``bench/run_curves.py``: a run folder without ``summary.json`` gives its evaluation curves so far, its update
    rate and its training command (``run_dir=`` left out); a score it never logged is an empty curve."""
    curves = load_bench("run_curves")
    run = tmp_path / "walker-isodream_v2-s0"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(
        "- exp=decomposition\n- env=dmc_walker_walk\n- run_dir=/somewhere\n"
    )
    scalars = run / "logs" / "train" / "scalars"
    (scalars / "eval" / "decomposition").mkdir(parents=True)
    (scalars / "eval" / "decomposition" / "iou_control_vs_agent.csv").write_text("500,0.05\n1000,0.123456\n")
    (scalars / "updates_per_s.csv").write_text("0,1.5\n20,1.98765\n")
    out = curves.main([str(run), "--json", str(tmp_path / "curves.json")])
    assert json.loads((tmp_path / "curves.json").read_text()) == out
    entry = out["runs"]["walker-isodream_v2-s0"]
    assert entry["command"] == "isodream-train exp=decomposition env=dmc_walker_walk"
    assert entry["finished"] is False
    assert entry["curves"]["iou_control_vs_agent"] == [[500, 0.05], [1000, 0.1235]]
    assert entry["curves"]["iou_free_vs_distractors"] == []
    assert entry["updates_per_s"] == [[0, 1.5], [20, 1.988]]
