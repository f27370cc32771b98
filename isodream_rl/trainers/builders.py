"""Builders of the TorchRL pieces of a run: env, collector, replay buffer, world model and loss, optimisers, logger."""

from __future__ import annotations

import functools
import importlib
from pathlib import Path

import torch
from torch import nn
from torchrl.data import LazyMemmapStorage, SliceSampler, TensorDictReplayBuffer
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger, get_logger

from isodream_rl.envs import make_env
from isodream_rl.envs.finite import FiniteEnvData
from isodream_rl.trainers.config import RunConfig

#: What the replay buffer stores per step. The root ``"pixels"`` is left out: it is the previous step's
#: ``("next", "pixels")``, and the world model filters ``o_{t+1}`` only, so storing it would double the bytes.
REPLAY_KEYS = (
    "action",
    "is_init",
    ("next", "pixels"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)
#: Written by ``ReplayPreparation``: windows never cross a change of this id (env, or buffer write cursor).
STREAM_KEY = ("collector", "stream")


def env_factory(cfg: RunConfig, *, eval_mode: bool = False) -> functools.partial:
    """A picklable ``() -> EnvBase`` for ``cfg.env``: ``env.factory`` if given, else ``make_env(env.name)``
    (evaluation envs use the held-out "eval" video split on DMC)."""
    kwargs = dict(cfg.env.kwargs)
    if cfg.env.factory:
        module, _, attribute = cfg.env.factory.partition(":")
        return functools.partial(getattr(importlib.import_module(module), attribute), **kwargs)
    if eval_mode and cfg.env.name.startswith("dmc_"):
        kwargs.setdefault("video_split", "eval")
    return functools.partial(make_env, cfg.env.name, **kwargs)


def env_label(cfg: RunConfig) -> str:
    """How the settings name the env of ``cfg``: ``env.factory=...`` when given, else ``env.name=...``."""
    return f"env.factory={cfg.env.factory}" if cfg.env.factory else f"env.name={cfg.env.name}"


def collector_env_suffix(index: int, num_envs: int) -> str:
    """How an env of the collector is told apart in messages: ``" (collector env 1 of 2)"``, ``""`` for one."""
    return f" (collector env {index + 1} of {num_envs})" if num_envs > 1 else ""


def checked_env_factory(
    cfg: RunConfig, *, eval_mode: bool = False, which: str = "", first_step: int = 0, on_fault: str = "raise"
) -> functools.partial:
    """:func:`env_factory` whose envs refuse NaN/inf frames and rewards where they enter the run
    (:class:`~isodream_rl.envs.finite.FiniteEnvData`, appended last: it checks what the policy and the replay
    get); keyword arguments of the call go to the env's factory.

    Args:
        cfg: the run's configuration.
        eval_mode: as :func:`env_factory`.
        which: added to the env's name in the error (``" (collector env 1 of 2)"``).
        first_step: the env steps this env took in the run before it was made (a resumed run's).
        on_fault: ``"raise"``, or ``"mark"`` for an env in a collector worker process: the finding travels in the
            batch to the run's process (:func:`~isodream_rl.envs.finite.raise_marked_fault`).
    """
    return functools.partial(
        _finite_env,
        env_factory(cfg, eval_mode=eval_mode),
        env=env_label(cfg) + which,
        first_step=first_step,
        on_fault=on_fault,
    )


def _finite_env(make, *, env: str, first_step: int, on_fault: str = "raise", **kwargs) -> EnvBase:
    return make(**kwargs).append_transform(FiniteEnvData(env=env, first_step=first_step, on_fault=on_fault))


def action_dim_of(env: EnvBase) -> int:
    """Width of the env's action vector."""
    return int(env.action_spec.shape[-1])


def make_replay_buffer(cfg: RunConfig, *, scratch_dir: str | Path) -> TensorDictReplayBuffer:
    """``TensorDictReplayBuffer(LazyMemmapStorage, SliceSampler)`` over episodes, windows of ``T`` steps.

    With several envs the storage is ``[capacity / num_envs, num_envs]`` (``ndim=2``), so each env's steps
    stay contiguous. Windows follow ``STREAM_KEY`` (see ``ReplayPreparation``): they may cross episode
    boundaries, marked by ``is_init``, but never envs or the write cursor. ``sample()`` returns ``[B * T]``
    steps, ``B`` windows one after the other. ``SliceSampler`` ORs ``is_init`` with a mark at each window
    start, which the world model treats as a fresh start, the same as its zero initial state.
    """
    train = cfg.train
    storage = LazyMemmapStorage(
        train.buffer_size, scratch_dir=str(scratch_dir), ndim=2 if cfg.env.num_envs > 1 else 1
    )
    sampler = SliceSampler(slice_len=train.sequence_length, traj_key=STREAM_KEY, strict_length=True)
    return TensorDictReplayBuffer(
        storage=storage, sampler=sampler, batch_size=train.batch_size * train.sequence_length
    )


def make_adam(params, *, lr: float, eps: float) -> torch.optim.Adam:
    """Adam over ``params`` (the paper's optimiser for all three parameter groups)."""
    params = list(params)
    if not params:
        raise ValueError("an optimiser needs at least one parameter")
    return torch.optim.Adam(params, lr=lr, eps=eps)


def make_logger(cfg: RunConfig, *, run_dir: str | Path) -> Logger:
    """TorchRL logger (``get_logger``) writing under ``<run_dir>/logs``: CSV, TensorBoard or W&B."""
    kwargs = {}
    if cfg.logging.backend == "wandb":
        kwargs["wandb_kwargs"] = {"project": cfg.logging.project, "offline": cfg.logging.offline}
    return get_logger(
        cfg.logging.backend, logger_name=str(Path(run_dir) / "logs"), experiment_name="train", **kwargs
    )


def close_logger(logger: Logger) -> None:
    """Flush and close the logger's writer (TensorBoard's event file, W&B's run); CSV writes as it goes."""
    experiment = getattr(logger, "experiment", None)
    for method in ("finish", "close"):  # W&B run, TensorBoard SummaryWriter
        if callable(getattr(experiment, method, None)):
            getattr(experiment, method)()
            return


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
