"""TensorBoard and W&B (offline) logging of a tiny sprites run: the scalars the recipe promises reach the files."""

import pytest

from isodream_rl.trainers import RunConfig, train

#: Losses, both KLs, mask means and throughput (docs/recipes/index.md, "Outputs").
PROMISED = (
    "loss_model_reco",
    "loss_actor",
    "loss_value",
    "kl_control",
    "kl_free",
    "mask_control",
    "mask_free",
    "mask_static",
    "env_steps_per_s",
    "updates_per_s",
)


def tiny_run(tmp_path, backend: str) -> RunConfig:
    cfg = RunConfig(run_dir=str(tmp_path), size_name="tiny")
    cfg.model.size, cfg.model.actor_units, cfg.model.value_units, cfg.model.attention_dim = "tiny", 16, 16, 8
    cfg.train.batch_size, cfg.train.sequence_length, cfg.train.buffer_size = 2, 6, 200
    cfg.train.prefill_steps, cfg.train.frames_per_batch, cfg.train.total_steps = 10, 10, 30
    cfg.train.threads = 1
    cfg.algo.horizon, cfg.algo.attention_window = 3, 2
    cfg.logging.backend, cfg.logging.progress_bar = backend, False
    cfg.logging.log_every, cfg.logging.eval_every = 10, 20
    cfg.logging.video_length, cfg.logging.video_context = 6, 3
    cfg.env.kwargs = {"max_steps": 20}
    return cfg


def test_tensorboard_event_file_holds_the_scalars_and_the_prediction(tmp_path):
    pytest.importorskip("tensorboard", reason="tensorboard is not installed: pip install tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    result = train(tiny_run(tmp_path, "tensorboard"))
    events = list((tmp_path / "logs").rglob("events.out.tfevents.*"))
    assert len(events) == 1
    accumulator = EventAccumulator(str(events[0].parent), size_guidance={"images": 0})
    accumulator.Reload()
    scalars = set(accumulator.Tags()["scalars"])
    assert set(PROMISED) <= scalars, set(PROMISED) - scalars
    assert "openloop_prediction" in accumulator.Tags()["images"] + accumulator.Tags()["tensors"]
    assert 0 < accumulator.Scalars("updates")[-1].value <= result.updates


def test_wandb_offline_run_holds_the_scalars(tmp_path, monkeypatch):
    wandb = pytest.importorskip("wandb", reason="wandb is not installed: pip install wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = tiny_run(tmp_path, "wandb")
    cfg.logging.offline = True
    train(cfg)
    wandb.teardown()  # stops W&B's writer process, so the run file is complete
    runs = list((tmp_path / "logs" / "wandb").glob("offline-run-*"))
    assert len(runs) == 1
    # The run file is a log of protobuf records; metric names are stored as plain UTF-8 in the history rows.
    records = next(runs[0].glob("run-*.wandb")).read_bytes()
    missing = [key for key in PROMISED if key.encode() not in records]
    assert not missing
    assert list(runs[0].rglob("openloop_prediction*"))
