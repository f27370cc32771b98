"""Print the Speed table of docs/architecture.md from the committed world-model bench JSONs.

One row per ``docs/results/world_model_speed*.json`` written by ``bench/world_model_speed.py --json``, then
the range of each ratio across the runs that measured it (bf16 ratios only where the CPU computes bf16
natively: elsewhere autocast emulates it and both sides run ~10x slower than fp32).

    python bench/speed_table.py > table.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
#: ``(column, variant)``: seconds per update of each variant
TIMES = (
    ("ours fp32", "ours_fp32_cl"),
    ("TorchRL fp32", "torchrl_fp32_cl"),
    ("TorchRL fp32 NCHW", "torchrl_fp32_nchw"),
    ("ours bf16", "ours_bf16_cl"),
    ("TorchRL bf16", "torchrl_bf16_cl"),
)
#: the ratios ours / TorchRL the bench writes (see bench/world_model_speed.py)
RATIOS = ("ratio", "ratio_vs_torchrl_default", "ratio_bf16", "ratio_fast_vs_default")


def native_bf16(config: dict) -> bool:
    return bool(config.get("cpu_avx512_bf16") or config.get("cpu_amx"))


def cpu_name(config: dict) -> str:
    extras = [
        name for name, key in (("AVX512-BF16", "cpu_avx512_bf16"), ("AMX", "cpu_amx")) if config.get(key)
    ]
    return " + ".join([config.get("cpu_capability", "?"), *extras])


def table(paths: list[Path]) -> str:
    """The markdown table of ``paths`` and the ranges of the ratios across them."""
    runs = [(path, json.loads(path.read_text())) for path in paths]
    header = ["JSON", "CPU", "rounds", *(f"{name} (s)" for name, _ in TIMES), *RATIOS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for path, run in runs:
        config, variants = run["config"], run["variants"]
        times = [f"{variants[v]['ms'] / 1000:.2f}" if v in variants else "-" for _, v in TIMES]
        ratios = ["-" if run.get(key) is None else f"{run[key]:.2f}" for key in RATIOS]
        if ratios[2] != "-" and not native_bf16(config):
            ratios[2] += " (emulated bf16)"
        row = [f"`{path.name}`", cpu_name(config), str(config.get("steps", "?")), *times, *ratios]
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    for key in RATIOS:
        # bf16 is compared only where the CPU computes it: emulated, both sides run ~10x slower than fp32
        native_only = key == "ratio_bf16"
        values = [
            run[key]
            for _, run in runs
            if run.get(key) is not None and (not native_only or native_bf16(run["config"]))
        ]
        if values:
            low, high = f"{min(values):.2f}", f"{max(values):.2f}"
            span = low if low == high else f"{low}-{high}"
            where = " (native bf16 only)" if native_only else ""
            lines.append(f"- `{key}`: {span} across {len(values)} committed run(s){where}")
    return "\n".join(lines)


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "paths", nargs="*", type=Path, help="bench JSONs (default: docs/results/world_model_speed*.json)"
    )
    args = p.parse_args(argv)
    text = table(args.paths or sorted(RESULTS.glob("world_model_speed*.json")))
    print(text)
    return text


if __name__ == "__main__":
    main()
