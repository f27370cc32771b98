"""bench/learning.py at a tiny size: runs, resumes nothing twice, writes the JSON while the runs train (unfinished
runs as curves), and writes the JSON, the picture and the table at the end."""

import json
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import load_bench

TOP_KEYS = (
    "env",
    "env_kwargs",
    "env_steps",
    "random_return",
    "constant_return",
    "scripted_return",
    "references",
    "commit",
    "cpu",
    "command",
    "overrides",
)


def fake_logs(run_dir: Path, **scalars: list[tuple[int, float]]) -> None:
    """CSV scalar logs as ``isodream-train`` writes them (``<run_dir>/logs/train/scalars/<name>.csv``)."""
    folder = run_dir / "logs" / "train" / "scalars"
    folder.mkdir(parents=True, exist_ok=True)
    for name, rows in scalars.items():
        (folder / f"{name}.csv").write_text("".join(f"{step},{value}\n" for step, value in rows))


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
    for key in TOP_KEYS:
        assert key in saved, key
    assert saved["env_kwargs"]["max_steps"] == 20 and saved["env_kwargs"]["num_distractors"] == 1
    assert saved["scripted_return"] > saved["constant_return"]
    for algo in ("dreamerv2", "torchrl_dreamer"):
        entry = saved["algos"][algo]
        assert len(entry["final_per_seed"]) == 1 and len(entry["final_successes_per_seed"]) == 1
        curve = entry["curves"]["0"]
        assert curve["finished"] is True
        assert curve["env_steps"][-1] == 40 and len(curve["eval_return"]) == len(curve["wall_s"]) >= 2
        assert len(curve["updates"]) == len(curve["env_steps"])
        # logged every 10 steps (log_every=10 is "more than 10 since the last"): at each evaluation's step
        assert (
            all(u is not None for u in curve["updates"])
            and curve["updates"][-1] == entry["updates_per_seed"][0]
        )
        assert curve["eval_return"][-1] == entry["final_per_seed"][0]
    assert out.with_suffix(".png").stat().st_size > 0
    assert "| dreamerv2 | 1 | 0 |" in out.with_suffix(".md").read_text()

    # A second call finds the finished runs and only collects them.
    summary = tmp_path / "runs" / "dreamerv2_s0" / "summary.json"
    stamp = summary.stat().st_mtime
    bench.main(args)
    assert summary.stat().st_mtime == stamp

    # A run with CSV logs but no summary.json (still training, or its machine lost) is a curve, not a final
    # score; a run without logs (torchrl_dreamer seed 1) is left out.
    fake_logs(
        tmp_path / "runs" / "dreamerv2_s1",
        eval_return=[(20, 1.5), (40, 2.5)],
        eval_wall_s=[(20, 3.0), (40, 6.0)],
        updates=[(30, 4.0), (10, 1.0)],
    )
    seeds = args.index("--seeds") + 1
    both = [*args[:seeds], "0,1", *args[seeds + 1 :], "--collect-only"]
    saved = bench.main(both)
    assert set(saved) >= set(TOP_KEYS)
    entry = saved["algos"]["dreamerv2"]
    assert entry["seeds"] == [0] and len(entry["final_per_seed"]) == len(entry["normalised_per_seed"]) == 1
    assert entry["curves"]["1"] == {
        "env_steps": [20, 40],
        "eval_return": [1.5, 2.5],
        "wall_s": [3.0, 6.0],
        "updates": [1.0, 4.0],  # the newest count logged at or before each evaluation
        "finished": False,
    }
    assert set(saved["algos"]["torchrl_dreamer"]["curves"]) == {"0"}
    md = out.with_suffix(".md").read_text()
    assert "| dreamerv2 | 1 | 1 |" in md and "| torchrl_dreamer | 1 | 0 |" in md
    assert out.with_suffix(".png").stat().st_size > 0


FAKE_RUN = """
import json, pathlib, sys, time
run_dir, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
scalars = run_dir / "logs" / "train" / "scalars"
scalars.mkdir(parents=True, exist_ok=True)
# whole files, the updates first: the bench may read the logs at any moment, and a curve starts with its returns
for name, text in (("updates.csv", "100,10.0\\n200,30.0\\n"), ("eval_return.csv", "100,1.0\\n200,2.0\\n")):
    (scalars / (name + ".tmp")).write_text(text)
    (scalars / (name + ".tmp")).replace(scalars / name)
deadline = time.monotonic() + 60
while time.monotonic() < deadline:  # until the bench has written this curve into its JSON
    try:
        saved = json.loads(out.read_text())
    except (OSError, ValueError):
        saved = {}
    if "0" in saved.get("algos", {}).get("dreamerv2", {}).get("curves", {}):
        (run_dir / "seen.json").write_text(json.dumps(saved))
        break
    time.sleep(0.05)
"""


def test_learning_bench_writes_the_json_while_runs_train(tmp_path, monkeypatch):
    bench = load_bench("learning")
    out = tmp_path / "learning.json"
    monkeypatch.setattr(bench, "POLL_S", 0.05)
    monkeypatch.setattr(
        bench,
        "run_command",
        lambda algo, seed, run_dir, args: [sys.executable, "-c", FAKE_RUN, str(run_dir), str(out)],
    )
    args = ["--algos", "dreamerv2", "--seeds", "0", "--env-steps", "200", "--write-every", "0"]
    results = bench.main([*args, "--runs", str(tmp_path / "runs"), "--json", str(out)])
    # The fake run saw the JSON written while it ran, with its curve so far.
    seen = json.loads((tmp_path / "runs" / "dreamerv2_s0" / "seen.json").read_text())
    assert set(seen) >= set(TOP_KEYS) and seen["env_kwargs"] is None and seen["references"] is None
    curve = {"env_steps": [100, 200], "eval_return": [1.0, 2.0], "wall_s": [None, None]}
    curve.update(updates=[10.0, 30.0], finished=False)
    assert seen["algos"]["dreamerv2"]["curves"]["0"] == curve
    # It ended without a summary.json: the final write keeps it as an unfinished curve, and the table says so.
    assert (
        results["algos"]["dreamerv2"]["curves"]["0"] == curve and results["algos"]["dreamerv2"]["seeds"] == []
    )
    assert "| dreamerv2 | 0 | 1 |" in out.with_suffix(".md").read_text()
    assert out.with_suffix(".png").stat().st_size > 0 and not out.with_name(out.name + ".tmp").exists()


def test_learning_bench_defaults_give_every_run_10k_updates():
    bench = load_bench("learning")
    args = bench.build_parser().parse_args([])
    assert args.seeds == [0, 1] and args.size == "bench" and args.write_every == 120
    assert args.runs == Path.home() / "isodream-runs" / "bench_learning"
    from isodream_rl.trainers import RunConfig

    size = yaml.safe_load((bench.ROOT / "isodream_rl" / "configs" / "size" / "bench.yaml").read_text())
    train_every = size["train"].get("train_every", RunConfig().train.train_every)
    assert (size["train"]["prefill_steps"], train_every) == (1000, 5)
    assert (args.env_steps - size["train"]["prefill_steps"]) / train_every == 10_000


def test_learning_bench_runs_torchrl_dreamer_v3_by_default_and_accepts_the_older_dreamer(tmp_path, capsys):
    bench = load_bench("learning")
    assert bench.build_parser().parse_args([]).algos == ["isodream", "dreamerv2", "torchrl_dreamer_v3"]
    runs, out = tmp_path / "runs", tmp_path / "learning.json"
    args = [
        "--algos",
        "isodream,torchrl_dreamer",
        "--runs",
        str(runs),
        "--json",
        str(out),
        "--collect-only",
    ]
    bench.main(args)  # nothing to collect yet, and no "unknown algos"
    saved = json.loads(out.read_text())["algos"]
    assert set(saved) == {"isodream", "torchrl_dreamer"} and saved["torchrl_dreamer"]["seeds"] == []
    with pytest.raises(SystemExit):
        bench.main(["--algos", "torchrl_dreamer_v4", "--collect-only", "--json", str(out)])
    assert "unknown algos ['torchrl_dreamer_v4']" in capsys.readouterr().err


def test_the_default_table_never_overwrites_the_status_page(tmp_path):
    learning = load_bench("learning")
    results = learning.ROOT / "docs" / "results"
    assert learning.table_path(results / "learning.json") == results / "learning_table.md"
    assert (
        learning.table_path(results / "learning_rung1_isodream.json")
        == results / "learning_rung1_isodream.md"
    )
    assert learning.table_path(tmp_path / "learning.json") == tmp_path / "learning.md"


def test_an_algo_override_reaches_that_algorithms_runs_only(tmp_path):
    """``--algo-override isodream:KEY=VALUE``: in the default's command, not DreamerV3's (whose learner refuses a
    setting it does not read), and in the JSON; a malformed entry or an algorithm not benched is refused."""
    bench = load_bench("learning")
    parser = bench.build_parser()
    args = parser.parse_args(
        [
            "--algos",
            "isodream,torchrl_dreamer_v3",
            "--override",
            "model.hidden_dim=32",
            "--algo-override",
            "isodream:model.free_hidden_fraction=0.6",
            "--runs",
            str(tmp_path / "runs"),
            "--json",
            str(tmp_path / "out.json"),
        ]
    )
    default = bench.run_command("isodream", 0, tmp_path / "a", args)
    baseline = bench.run_command("torchrl_dreamer_v3", 0, tmp_path / "b", args)
    assert "model.free_hidden_fraction=0.6" in default and "model.hidden_dim=32" in default
    assert "model.free_hidden_fraction=0.6" not in baseline and "model.hidden_dim=32" in baseline
    args.collect_only = True
    saved = bench.write_results(args, None, final=False)
    assert saved["algo_overrides"] == {"isodream": ["model.free_hidden_fraction=0.6"]}
    for bad in ("model.free_hidden_fraction=0.6", "dreamerv2:model.depth=8", "isodream:depth"):
        args.algo_override = [bad]
        with pytest.raises(SystemExit, match="--algo-override"):
            bench.algo_overrides(args)
