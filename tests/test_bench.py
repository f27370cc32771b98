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
