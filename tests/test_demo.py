"""The world-model recipe (``isodream-demo``), at a tiny size: it trains, scores the masks and writes its outputs."""

import json

from isodream_rl.recipes.world_model_demo import main


def test_demo_writes_picture_scores_checkpoint_and_csv(tmp_path):
    summary = main(
        [
            "--steps",
            "3",
            "--episodes",
            "2",
            "--episode-length",
            "16",
            "--window",
            "8",
            "--batch-size",
            "2",
            "--size",
            "tiny",
            "--eval-every",
            "2",
            "--precision",
            "fp32",
            "--out",
            str(tmp_path),
        ]
    )
    assert (tmp_path / "branches.png").stat().st_size > 0
    assert (tmp_path / "world_model.pt").exists()
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["updates"] == 3 and 0.0 <= saved["iou_control_vs_agent"] <= 1.0
    assert summary["png"] == str(tmp_path / "branches.png")
    assert list(tmp_path.rglob("*.csv")), "the CSV logger wrote nothing"
