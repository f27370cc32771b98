"""The Speed table of docs/architecture.md is bench/speed_table.py's output over the committed bench JSONs."""

from pathlib import Path

from tests.conftest import load_bench

ROOT = Path(__file__).resolve().parents[1]


def _speed_table():
    return load_bench("speed_table")


def test_architecture_doc_holds_the_table_of_the_committed_jsons():
    module = _speed_table()
    text = module.table(sorted((ROOT / "docs" / "results").glob("world_model_speed*.json")))
    assert text in (ROOT / "docs" / "architecture.md").read_text()


def test_bf16_ratio_range_counts_native_runs_only(tmp_path):
    import json

    module = _speed_table()
    variants = {"ours_fp32_cl": {"ms": 2000.0}, "torchrl_fp32_cl": {"ms": 1000.0}}
    for name, native, ratio_bf16 in (("a", True, 1.3), ("b", False, 1.7)):
        run = {
            "ratio": 2.0,
            "ratio_bf16": ratio_bf16,
            "variants": variants,
            "config": {"cpu_capability": "AVX512", "cpu_avx512_bf16": native, "steps": 4},
        }
        (tmp_path / f"{name}.json").write_text(json.dumps(run))
    text = module.table(sorted(tmp_path.glob("*.json")))
    assert "- `ratio_bf16`: 1.30 across 1 committed run(s) (native bf16 only)" in text
    assert "1.70 (emulated bf16)" in text
    assert "- `ratio`: 2.00 across 2 committed run(s)" in text
