"""bench/decomposition.py at a tiny size: runs one scene with both default algorithms (the default's world model,
``isodream``, and the DreamerV2-style learner's, ``isodream_v2``), reads finished runs back instead of training them
again, reads the folders made when the DreamerV2-style learner was ``isodream`` as its runs, resumes interrupted
ones, and writes the JSON, the picture and the table."""

import argparse
import json

import pytest

from tests.conftest import load_bench


def test_decomposition_bench_writes_the_schema(tmp_path):
    bench = load_bench("decomposition")
    out = tmp_path / "results" / "decomposition.json"
    args = ["--scenes", "sprites", "--seeds", "0", "--minutes", "5", "--runs", str(tmp_path / "runs")]
    args += ["--json", str(out), *(f"--override={o}" for o in bench.TINY)]
    results = bench.main(args)
    saved = json.loads(out.read_text())
    assert saved == json.loads(json.dumps(results))
    assert {"scenes", "commit", "cpu", "command", "minutes"} <= set(saved)
    assert set(saved["scenes"]) == {"sprites"} and set(saved["scenes"]["sprites"]) == {
        "isodream",
        "isodream_v2",
    }
    for algo, runs in saved["scenes"]["sprites"].items():
        (run,) = runs
        assert run["seed"] == 0 and run["updates"] == 2 and run["stopped_by"] == "updates"
        assert 0.0 <= run["iou_control_vs_agent"] <= 1.0 and 0.0 <= run["iou_free_vs_distractors"] <= 1.0
        assert run["wall_minutes"] >= 0 and "train_iou_control_vs_agent" in run, algo
        learner = json.loads((tmp_path / "runs" / f"sprites-{algo}-s0" / "summary.json").read_text())[
            "learner"
        ]
        assert learner == algo  # each algo's own world model
    # the picture is the default's
    assert saved["pictures"]["sprites"] == "decomposition_sprites.png"
    assert saved["scenes"]["sprites"]["isodream"][0]["picture"].startswith(
        str(tmp_path / "runs" / "sprites-isodream-s0")
    )
    assert (out.parent / "decomposition_sprites.png").stat().st_size > 0
    # and the other learner's beside it
    assert saved["pictures_by_algo"]["sprites"] == {
        "isodream": "decomposition_sprites.png",
        "isodream_v2": "decomposition_sprites_isodream_v2.png",
    }
    assert (out.parent / "decomposition_sprites_isodream_v2.png").stat().st_size > 0
    table = out.with_suffix(".md").read_text()
    assert "| sprites | isodream | 1 |" in table and "| sprites | isodream_v2 | 1 |" in table

    # a second call finds the finished runs and only collects them
    summary = tmp_path / "runs" / "sprites-isodream_v2-s0" / "summary.json"
    stamp = summary.stat().st_mtime
    assert bench.main([*args, "--collect-only"])["scenes"] == results["scenes"]
    bench.main(args)
    assert summary.stat().st_mtime == stamp


def test_an_interrupted_run_resumes_and_a_fresh_one_starts_over(tmp_path):
    bench = load_bench("decomposition")
    args = argparse.Namespace(runs=tmp_path, minutes=7.0, size="", override=["world_model.updates=3"])
    command = bench.run_command(args, "highway", "dreamerv2", 1)
    assert command[command.index("exp=decomposition") + 1 : command.index("algo=dreamerv2")] == [
        "env=highway",
        "++env.kwargs.view=top_down",
        "++env.kwargs.top_down_follow=road",
        "++env.kwargs.top_down_scaling=2.5",
    ]
    assert "world_model.max_minutes=7.0" in command and command[-1] == "overwrite=true"
    (tmp_path / "highway-dreamerv2-s1" / "checkpoints" / "step_00000002").mkdir(parents=True)
    assert bench.run_command(args, "highway", "dreamerv2", 1)[-1] == "resume=true"
    assert list(bench.SCENES) == ["sprites", "dmc_walker_walk", "dmc_cheetah_run", "highway"]


def _former_run(folder, *, iou):
    """A finished run folder as ``mode=world_model`` left it before it trained the default's world model: a
    ``summary.json`` without ``learner``, of the DreamerV2-style learner saved as ``algo=isodream``."""
    folder.mkdir(parents=True)
    summary = {
        "mode": "world_model",
        "algo": "isodream",
        "env": "sprites",
        "updates": 7,
        "stopped_by": "updates",
    }
    summary.update(
        seconds=60.0, precision="fp32", size="tiny", seed=0, iou_control_vs_agent=iou, png="none.png"
    )
    (folder / "summary.json").write_text(json.dumps(summary))


def test_a_former_isodream_folder_is_read_as_isodream_v2s_and_never_trained_over(tmp_path, capsys):
    bench = load_bench("decomposition")
    runs = tmp_path / "runs"
    _former_run(runs / "sprites-isodream-s0", iou=0.7)
    args = ["--scenes", "sprites", "--seeds", "0", "--runs", str(runs), "--json", str(tmp_path / "d.json")]
    # the default algos: the former folder is isodream_v2's run, and not the default's (which is not trained into it)
    results = bench.main([*args, "--collect-only"])
    assert results["scenes"]["sprites"]["isodream"] == []
    (run,) = results["scenes"]["sprites"]["isodream_v2"]
    assert (run["iou_control_vs_agent"], run["updates"]) == (0.7, 7)
    # asked to train the default there, the bench leaves the folder as it is, says why, and starts nothing
    results = bench.main([*args, "--algos", "isodream"])
    assert (
        results["scenes"]["sprites"]["isodream"] == [] and "isodream_v2" not in results["scenes"]["sprites"]
    )
    said = capsys.readouterr().out
    assert "sprites-isodream-s0 holds a finished run of the DreamerV2-style learner" in said
    assert not (runs / "sprites-isodream-s0" / "bench.log").exists()
    # a run of isodream_v2's own folder is read before the former one
    _former_run(runs / "sprites-isodream_v2-s0", iou=0.2)
    (run,) = bench.main([*args, "--algos", "isodream_v2", "--collect-only"])["scenes"]["sprites"][
        "isodream_v2"
    ]
    assert run["iou_control_vs_agent"] == 0.2


def test_takes_the_three_algorithms_and_names_them_for_another(tmp_path, capsys):
    bench = load_bench("decomposition")
    assert bench.ALGOS == ("isodream", "isodream_v2", "dreamerv2")
    assert bench.DEFAULT_ALGOS == ("isodream", "isodream_v2")
    args = [
        "--scenes",
        "sprites",
        "--seeds",
        "0",
        "--runs",
        str(tmp_path),
        "--json",
        str(tmp_path / "d.json"),
    ]
    results = bench.main([*args, "--algos", "isodream,isodream_v2,dreamerv2", "--collect-only"])
    assert list(results["scenes"]["sprites"]) == ["isodream", "isodream_v2", "dreamerv2"]
    with pytest.raises(SystemExit):
        bench.main([*args, "--algos", "isodream_v3"])
    assert (
        "unknown algos ['isodream_v3']; valid: ['isodream', 'isodream_v2', 'dreamerv2']"
        in capsys.readouterr().err
    )
