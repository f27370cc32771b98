"""The adapter over TorchRL ``Trainer``'s private state (isodream_rl/trainers/trainer_state.py), on a real Trainer:
these fail when a TorchRL release renames or drops what it reads."""

import torch
from tensordict import TensorDict
from torchrl.trainers import Trainer

from isodream_rl.trainers import trainer_state


class _OneBatch:
    """A stand-in collector: one batch of 4 frames, then done."""

    init_random_frames = 0

    def __iter__(self):
        yield TensorDict({"x": torch.zeros(4, 1)}, [4])

    def shutdown(self):
        pass


def _trainer(**kwargs) -> Trainer:
    loss = torch.nn.Linear(1, 1)
    return Trainer(
        collector=_OneBatch(),
        total_frames=4,
        frame_skip=1,
        optim_steps_per_batch=1,
        loss_module=lambda td: TensorDict({"loss": loss(td["x"]).sum()}, []),
        optimizer=torch.optim.SGD(loss.parameters(), lr=0.0),
        log_interval=1,
        save_trainer_file=None,
        **kwargs,
    )


def test_counters_round_trip_through_a_new_trainer():
    trainer = _trainer(progress_bar=False)
    assert trainer_state.optim_count(trainer) == 0 and trainer_state.log_marks(trainer) == {}
    trainer.train()
    assert trainer_state.optim_count(trainer) == 1
    resumed = _trainer(progress_bar=False)
    trainer_state.restore(resumed, optim_count=7, log_marks={"loss": 4})
    assert trainer_state.optim_count(resumed) == 7 and trainer_state.log_marks(resumed) == {"loss": 4}
    resumed.train()
    assert trainer_state.optim_count(resumed) == 8  # the trainer counts on from the restored value


def test_logged_values_hold_what_the_hooks_logged():
    trainer = _trainer(progress_bar=False)
    trainer.register_op("post_steps_log", lambda batch: {"frames_seen": float(batch.numel())})
    trainer.train()
    assert trainer_state.logged_values(trainer)["frames_seen"] == [4.0]


def test_progress_bar_can_be_advanced_from_the_setup_stage():
    trainer = _trainer(progress_bar=True)
    seen = []

    def advance():
        trainer_state.advance_progress_bar(trainer, 3)
        seen.append(trainer._pbar.n)

    trainer.register_op("setup", advance)
    trainer.train()
    assert seen == [3]
