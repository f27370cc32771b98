"""bench/learning.py at a tiny size: runs, resumes nothing twice, and writes the JSON, the picture and the table."""

import json

from tests.conftest import load_bench


def test_learning_bench_writes_the_schema(tmp_path):
    bench = load_bench("learning")
    out = tmp_path / "learning.json"
    tiny = [
        "train.prefill_steps=20",
        "train.frames_per_batch=10",
        "train.batch_size=2",
        "train.sequence_length=8",
        "logging.video_length=8",
        "logging.log_every=10",
        "env.kwargs.max_steps=20",
        "++env.kwargs.num_distractors=1",
    ]
    args = ["--algos", "dreamerv2,torchrl_dreamer", "--seeds", "0", "--size", "tiny", "--env-steps", "40"]
    args += [
        "--eval-every",
        "20",
        "--eval-episodes",
        "2",
        "--runs",
        str(tmp_path / "runs"),
        "--json",
        str(out),
    ]
    args += [f"--override={o}" for o in tiny]
    results = bench.main(args)
    saved = json.loads(out.read_text())
    assert saved == json.loads(json.dumps(results))
    for key in (
        "env",
        "env_steps",
        "random_return",
        "constant_return",
        "scripted_return",
        "commit",
        "cpu",
        "command",
    ):
        assert key in saved, key
    assert saved["scripted_return"] > saved["constant_return"]
    for algo in ("dreamerv2", "torchrl_dreamer"):
        entry = saved["algos"][algo]
        assert len(entry["final_per_seed"]) == 1 and len(entry["final_successes_per_seed"]) == 1
        curve = entry["curves"]["0"]
        assert curve["env_steps"][-1] == 40 and len(curve["eval_return"]) == len(curve["wall_s"]) >= 2
        assert curve["eval_return"][-1] == entry["final_per_seed"][0]
    assert out.with_suffix(".png").stat().st_size > 0
    assert "| dreamerv2 | 1 |" in out.with_suffix(".md").read_text()

    # A second call finds the finished runs and only collects them.
    summary = tmp_path / "runs" / "dreamerv2_s0" / "summary.json"
    stamp = summary.stat().st_mtime
    bench.main(args)
    assert summary.stat().st_mtime == stamp
