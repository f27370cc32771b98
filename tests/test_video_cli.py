"""``isodream-video train|eval`` end to end on tiny BAIR-format files."""

import json

import pytest
import torch

from isodream_rl.data import write_tiny_bair
from isodream_rl.video_prediction.cli import main
from isodream_rl.video_prediction.trainer import VideoTrainConfig, load_checkpoint


@pytest.fixture(autouse=True)
def _one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def bair_root(tmp_path):
    return write_tiny_bair(tmp_path)


TINY = ["--hidden-channels", "4", "--encoder-channels", "4", "4", "--kernel-size", "3", "--num-layers", "1",
        "--action-embedding", "4", "--batch-size", "2", "--threads", "1"]  # fmt: skip


def test_train_then_eval_writes_checkpoint_logs_metrics_and_figures(bair_root, tmp_path):
    out = tmp_path / "run"
    args = ["train", "--dataset", "bair", "--data-path", str(bair_root), "--sequence-length", "5",
            "--train-frames", "4", "--test-frames", "5", "--horizons", "2", "3", "--iterations", "2",
            "--out-dir", str(out), "--result-json", str(out / "result.json"), "--no-progress",
            "--precision", "bf16", *TINY]  # fmt: skip
    assert main(args) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["iterations"] == 2 and set(result["metrics"]) >= {"psnr_2", "ssim_3", "psnr_uint8_3"}
    assert len(result["curves"]["psnr"]) == 3
    assert (out / "checkpoints" / "step_00000002").is_dir() and not list(out.rglob("*.tmp"))
    assert list((out / "logs").rglob("loss_image.csv"))

    model, config, state = load_checkpoint(out)
    assert config.variant == "isodream" and state["iteration"] == 2
    assert model.config.precision == "bf16" and model.config.channels_last
    eval_args = ["eval", "--checkpoint", str(out), "--horizons", "3", "--no-balls",
                 "--json", str(tmp_path / "e.json"), "--showcase", str(tmp_path / "s.png"),
                 "--curves", str(tmp_path / "c.png")]  # fmt: skip
    assert main(eval_args) == 0
    assert set(json.loads((tmp_path / "e.json").read_text())["metrics"]) >= {"psnr_3", "ssim_uint8_3"}
    assert (tmp_path / "s.png").stat().st_size > 0 and (tmp_path / "c.png").stat().st_size > 0


def test_config_rejects_inconsistent_protocol():
    with pytest.raises(ValueError, match="train_frames"):
        VideoTrainConfig(train_frames=40)
    with pytest.raises(ValueError, match="data_path"):
        VideoTrainConfig(dataset="bair")
    with pytest.raises(ValueError, match="precision"):
        VideoTrainConfig(precision="fp16")
    with pytest.raises(KeyError, match="unknown"):
        VideoTrainConfig.from_dict({"colour": 1})


def test_resumed_training_equals_uninterrupted_and_keeps_the_validation_curve(bair_root, tmp_path):
    common = ["train", "--dataset", "bair", "--data-path", str(bair_root), "--sequence-length", "5",
              "--train-frames", "4", "--test-frames", "5", "--horizons", "2", "3", "--no-progress",
              "--val-every", "2", "--val-batches", "1", "--checkpoint-every", "2", "--logger", "", *TINY]  # fmt: skip
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert main([*common, "--iterations", "4", "--out-dir", str(straight)]) == 0
    assert (
        main(
            [*common, "--iterations", "2", "--out-dir", str(split), "--result-json", str(tmp_path / "a.json")]
        )
        == 0
    )
    assert main([*common, "--iterations", "4", "--out-dir", str(split), "--resume",
                 "--result-json", str(tmp_path / "b.json")]) == 0  # fmt: skip
    a, _, state_a = load_checkpoint(straight)
    b, _, state_b = load_checkpoint(split)
    assert state_a["iteration"] == state_b["iteration"] == 4
    for (name, p), q in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(p, q, rtol=0, atol=0, msg=name)
    history = json.loads((tmp_path / "b.json").read_text())["history"]
    assert [h["iteration"] for h in history] == [0, 2, 4] == [h["iteration"] for h in state_a["history"]]
    assert all(set(h) >= {"mse_3", "psnr_3", "ssim_3"} for h in history)
    assert history == state_a["history"]


def test_resume_refuses_other_model_settings(bair_root, tmp_path, capsys):
    common = ["train", "--dataset", "bair", "--data-path", str(bair_root), "--sequence-length", "5",
              "--train-frames", "4", "--test-frames", "5", "--horizons", "2", "3", "--no-progress",
              "--iterations", "1", "--out-dir", str(tmp_path / "run"), "--logger", "", *TINY]  # fmt: skip
    assert main(common) == 0
    with pytest.raises(SystemExit) as exit_info:
        main([*common, "--resume", "--lr", "0.5"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "cannot resume" in err and "lr: 0.0001 -> 0.5" in err
