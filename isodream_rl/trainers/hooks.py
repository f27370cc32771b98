"""TorchRL ``Trainer`` hooks of an Iso-Dream run: replay preparation, returns, throughput, signals, checkpoints."""

from __future__ import annotations

import logging
import signal
import time

import torch
from tensordict import TensorDictBase
from torchrl.trainers import TrainerHookBase

from isodream_rl.envs.finite import raise_marked_fault
from isodream_rl.run_utils.signals import StopOnSignal
from isodream_rl.trainers.builders import REPLAY_KEYS, STREAM_KEY

logger = logging.getLogger(__name__)


class ReplayPreparation(TrainerHookBase):
    """``batch_process`` hook run before ``ReplayBufferTrainer.extend``: keep the replay keys, one row per env,
    and write the stream id that ``SliceSampler`` cuts windows by.

    Windows may span episode boundaries, as in Dreamer: the stored ``is_init`` marks where an episode starts
    and the world model resets its state there, so short episodes (a random driver leaving the road after a
    few steps) still give full windows. What a window must not span is the buffer's write cursor, where the
    newest steps sit next to the oldest. The stream id ``lap * num_envs + env`` changes exactly there
    (``lap``: how many times this env's slice of the storage has been filled), and between envs.

    A batch in which an env of a collector worker marked a NaN/inf frame or reward
    (:class:`~isodream_rl.envs.finite.FiniteEnvData` with ``on_fault="mark"``) is refused here, before the replay
    stores it: :class:`~isodream_rl.envs.finite.NonFiniteEnvDataError` names the env, the entry and its env step.

    Args:
        num_envs: envs of the collector; batches are reshaped to ``[num_envs, T]`` when ``num_envs > 1``.
        capacity_per_env: steps of storage per env (``buffer_size // num_envs``).
        envs: how each env is named in that error, one per env. Defaults to ``"collector env i of n"``.
    """

    def __init__(self, *, num_envs: int, capacity_per_env: int, envs: tuple[str, ...] | None = None) -> None:
        self.num_envs = num_envs
        self.capacity_per_env = capacity_per_env
        self.envs = envs or tuple(f"collector env {i + 1} of {num_envs}" for i in range(num_envs))
        if len(self.envs) != num_envs:
            raise ValueError(f"envs names {len(self.envs)} envs, num_envs={num_envs}")
        self.written = 0

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        raise_marked_fault(batch, self.envs)
        batch = batch.select(*REPLAY_KEYS, strict=False)
        if self.num_envs > 1 and batch.ndim == 1:
            batch = batch.reshape(self.num_envs, -1)
        elif self.num_envs == 1 and batch.ndim == 2:
            batch = batch.reshape(-1)
        time = batch.shape[-1]
        lap = (self.written + torch.arange(time)) // self.capacity_per_env
        stream = lap * self.num_envs
        if batch.ndim == 2:
            stream = stream[None, :] + torch.arange(self.num_envs)[:, None]
        batch.set(STREAM_KEY, stream)
        self.written += time
        return batch

    def state_dict(self) -> dict:
        return {"written": self.written}

    def load_state_dict(self, state_dict: dict) -> None:
        self.written = state_dict["written"]

    def register(self, trainer, name: str = "replay_preparation") -> None:
        trainer.register_op("batch_process", self)
        trainer.register_module(name, self)


class EpisodeReturns(TrainerHookBase):
    """``pre_steps_log`` hook: returns and lengths of the episodes that ended in the batch.

    Keeps a running sum per env across collector batches, so episodes longer than a batch are counted whole.
    Logs ``episode_return`` (mean over the episodes that ended) and ``episodes`` (total count).
    """

    def __init__(self) -> None:
        self.running: torch.Tensor | None = None
        self.episodes = 0
        self.last_returns: list[float] = []

    def __call__(self, batch: TensorDictBase | None) -> dict | None:
        if batch is None:
            return None
        rows = batch if batch.ndim == 2 else batch.unsqueeze(0)
        reward = rows.get(("next", "reward")).squeeze(-1)
        done = rows.get(("next", "done")).squeeze(-1)
        if self.running is None or self.running.shape[0] != rows.shape[0]:
            self.running = torch.zeros(rows.shape[0])
        ended = []
        for t in range(rows.shape[1]):
            self.running += reward[:, t].float()
            for env in done[:, t].nonzero().flatten().tolist():
                ended.append(float(self.running[env]))
                self.running[env] = 0.0
        if not ended:
            return None
        self.episodes += len(ended)
        self.last_returns = ended
        return {"episode_return": sum(ended) / len(ended), "episodes": self.episodes, "log_pbar": True}

    def state_dict(self) -> dict:
        return {"episodes": self.episodes}

    def load_state_dict(self, state_dict: dict) -> None:
        self.episodes = state_dict["episodes"]

    def register(self, trainer, name: str = "episode_returns") -> None:
        trainer.register_op("pre_steps_log", self)
        trainer.register_module(name, self)


class Throughput(TrainerHookBase):
    """``post_steps_log`` hook: env steps/s and updates/s since the previous batch, shown on the progress bar.

    Args:
        stepper: the optimisation stepper (its ``updates`` counter).
    """

    def __init__(self, stepper) -> None:
        self.stepper = stepper
        self._trainer = None
        self._last: tuple[float, int, int] | None = None

    def __call__(self, batch: TensorDictBase | None) -> dict | None:
        now = time.perf_counter()
        frames, updates = self._trainer.collected_frames, self.stepper.updates
        last, self._last = self._last, (now, frames, updates)
        if last is None or now <= last[0]:
            return None
        elapsed = now - last[0]
        return {
            "env_steps_per_s": (frames - last[1]) / elapsed,
            "updates_per_s": (updates - last[2]) / elapsed,
            "updates": updates,
            "log_pbar": True,
        }

    def register(self, trainer, name: str = "throughput") -> None:
        self._trainer = trainer
        trainer.register_op("post_steps_log", self)


class PeriodicCheckpoint(TrainerHookBase):
    """``post_steps`` hook: a checkpoint every ``every_updates`` updates and when a stop signal arrived.

    Args:
        save: ``() -> Path``, writes one checkpoint.
        stepper: the optimisation stepper (its ``updates`` counter).
        every_updates: updates between checkpoints.
        signals: a :class:`StopOnSignal`; when it received a signal, the hook saves and asks the trainer to stop.
    """

    def __init__(self, *, save, stepper, every_updates: int, signals: StopOnSignal | None = None) -> None:
        self.save = save
        self.stepper = stepper
        self.every_updates = every_updates
        self.signals = signals
        self.last_saved = stepper.updates
        self._trainer = None

    def __call__(self) -> None:
        updates = self.stepper.updates
        if self.signals is not None and self.signals.received is not None:
            self.save()
            self.last_saved = updates
            self._trainer.request_stop(f"signal {signal.Signals(self.signals.received).name}")
            return
        if updates // self.every_updates > self.last_saved // self.every_updates:
            self.save()
            self.last_saved = updates

    def register(self, trainer, name: str = "checkpoint") -> None:
        self._trainer = trainer
        trainer.register_op("post_steps", self)
