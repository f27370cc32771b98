"""bench/decomposition.py at a tiny size: runs one scene with both algorithms, reads finished runs back
instead of training them again, resumes interrupted ones, and writes the JSON, the picture and the table."""

import argparse
import json

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
        "isodream_v2",
        "dreamerv2",
    }
    for algo, runs in saved["scenes"]["sprites"].items():
        (run,) = runs
        assert run["seed"] == 0 and run["updates"] == 2 and run["stopped_by"] == "updates"
        assert 0.0 <= run["iou_control_vs_agent"] <= 1.0 and 0.0 <= run["iou_free_vs_distractors"] <= 1.0
        assert run["wall_minutes"] >= 0 and "train_iou_control_vs_agent" in run, algo
    assert saved["scenes"]["sprites"]["dreamerv2"][0]["background_share_control"] == 1.0
    assert (out.parent / "decomposition_sprites.png").stat().st_size > 0
    assert "| sprites | isodream_v2 | 1 |" in out.with_suffix(".md").read_text()

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
    ]
    assert "world_model.max_minutes=7.0" in command and command[-1] == "overwrite=true"
    (tmp_path / "highway-dreamerv2-s1" / "checkpoints" / "step_00000002").mkdir(parents=True)
    assert bench.run_command(args, "highway", "dreamerv2", 1)[-1] == "resume=true"
    assert list(bench.SCENES) == ["sprites", "dmc_walker_walk", "dmc_cheetah_run", "highway"]
