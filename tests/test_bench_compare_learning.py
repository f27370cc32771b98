"""bench/compare_learning.py: runs of several learning-bench JSONs side by side, refusing entries of another env."""

import json

import pytest

from tests.conftest import load_bench


def bench_json(path, *, algo="isodream", returns=(1.0, 5.0, 9.0), scripted=100.0, env="sprites_reach"):
    """A learning-bench JSON (bench/learning.py's schema) holding one finished seed of ``algo``."""
    steps = [2500 * (i + 1) for i in range(len(returns))]
    entry = {
        "final_per_seed": [returns[-1]],
        "final_successes_per_seed": [3.0],
        "normalised_per_seed": [returns[-1] / scripted],
        "wall_s_per_seed": [60.0],
        "updates_per_seed": [480.0],
        "seeds": [0],
        "curves": {
            "0": {
                "env_steps": steps,
                "eval_return": list(returns),
                "wall_s": [10.0] * len(steps),
                "updates": [100.0] * len(steps),
                "finished": True,
            }
        },
    }
    refs = {"random": {"return": 0.0}, "constant": {"return": 0.0}, "scripted": {"return": scripted}}
    path.write_text(
        json.dumps(
            {
                "env": env,
                "env_steps": steps[-1],
                "algos": {algo: entry},
                "random_return": 0.0,
                "constant_return": 0.0,
                "scripted_return": scripted,
                "references": refs,
                "env_kwargs": {"task": "reach"},
                "size": "quickstart",
                "overrides": [],
                "commit": "abc",
                "cpu": "cpu",
                "command": f"python bench/learning.py --algos {algo}",
            }
        )
    )
    return path


def test_entries_are_labelled_side_by_side_with_their_sources(tmp_path):
    bench = load_bench("compare_learning")
    a = bench_json(tmp_path / "a.json", returns=(1.0, 5.0, 9.0))
    b = bench_json(tmp_path / "b.json", algo="torchrl_dreamer_v3", returns=(2.0, 4.0))
    out = tmp_path / "side.json"
    results = bench.main(
        ["--entry", f"default={a}", "--entry", f"baseline={b}:torchrl_dreamer_v3", "--json", str(out)]
    )
    written = json.loads(out.read_text())
    assert list(written["algos"]) == ["default", "baseline"] == list(results["algos"])
    assert written["algos"]["default"]["mean_eval_per_seed"] == [5.0]
    assert written["algos"]["baseline"]["eval_at"] == {"2500": {"0": 2.0}, "5000": {"0": 4.0}}
    assert written["sources"]["baseline"]["command"] == "python bench/learning.py --algos torchrl_dreamer_v3"
    assert written["command"].startswith("python bench/compare_learning.py --entry default=")
    assert out.with_suffix(".png").stat().st_size > 0
    table = out.with_suffix(".md").read_text()
    assert "| default | 480 | 9.0 | 5.0 | 1.0 | 5.0 | 9.0 |" in table
    assert "| baseline | 480 | 4.0 | 3.0 | 2.0 | 4.0 | - |" in table


def test_entries_of_another_env_or_reference_set_are_refused(tmp_path, capsys):
    bench = load_bench("compare_learning")
    a = bench_json(tmp_path / "a.json")
    other = bench_json(tmp_path / "b.json", env="sprites")
    rescored = bench_json(tmp_path / "c.json", scripted=50.0)
    for bad in (other, rescored):
        with pytest.raises(SystemExit):
            bench.main(["--entry", f"a={a}", "--entry", f"b={bad}", "--json", str(tmp_path / "x.json")])
    assert "compare runs of one env and one reference set only" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench.main(["--entry", f"a={a}:dreamerv2", "--json", str(tmp_path / "x.json")])
    assert "holds no algo 'dreamerv2'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench.main(["--entry", "no-path", "--json", str(tmp_path / "x.json")])
    assert not (tmp_path / "x.json").exists()
