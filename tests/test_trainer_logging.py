"""TensorBoard and W&B (offline) logging of a tiny sprites run: the scalars the recipe promises reach the files."""

import pytest

from isodream_rl.trainers import RunConfig, train
from tests.conftest import tiny_run_config

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
    return tiny_run_config(
        tmp_path,
        train__buffer_size=200,
        train__total_steps=30,
        logging__backend=backend,
        logging__progress_bar=False,
        logging__log_every=10,
        logging__eval_every=20,
        env__kwargs={"max_steps": 20},
    )


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
