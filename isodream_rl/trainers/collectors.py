"""The TorchRL collector of a run, on one machine or several (``train.collector_backend``).

``sync``/``multiprocess`` collect in this process or in local worker processes; ``ray`` hands the workers to a
Ray cluster (``torchrl.collectors.distributed.RayCollector``); ``distributed`` starts them with
``torch.distributed`` (``torchrl.collectors.distributed.DistributedCollector``, gloo by default), launched as
local processes (``launcher=mp``) or as SLURM jobs through submitit. Both remote backends send the policy
weights to their workers with ``torch.distributed``, which takes dense tensors only: ``world_model_overrides``
turns the world model's ``channels_last`` off for them.
"""

from __future__ import annotations

import datetime
import functools
from typing import Any

from torchrl.collectors import BaseCollector, Collector

from isodream_rl.trainers.builders import checked_env_factory, collector_env_suffix
from isodream_rl.trainers.config import RunConfig


def _with_transform(make, transform_factory):
    env = make()
    env.append_transform(transform_factory())
    return env


def _seeded(make, seed: int):
    env = make()
    env.set_seed(seed)
    return env


#: How long the driver waits for Ray workers to join the weight-sync process group.
RAY_WEIGHT_SYNC_TIMEOUT = datetime.timedelta(minutes=5)

#: Ray's ``worker_niceness`` for the local Ray instance a run starts (Ray's default is 15).
RAY_WORKER_NICENESS = 0


def _lengthen_ray_weight_sync_timeout() -> None:
    """TorchRL 0.14.1 hard-codes 60 s for Ray workers to join the weight-sync group (``_DIST_TIMEOUT``).

    A worker that starts slowly (a cold cluster node, or a busy node of a cluster whose Ray workers keep Ray's
    niceness 15) then fails the run with ``DistStoreError: wait timeout after 60000ms``. The driver-side constant
    is read when the collector connects, so raising it here, before the collector exists, is enough. On the local
    Ray instance a run starts, the workers run at the learner's priority (:data:`RAY_WORKER_NICENESS`) and join
    in seconds; the longer wait only matters on a cluster (``train.ray_address``).
    """
    from torchrl.weight_update import _ray

    if getattr(_ray, "_DIST_TIMEOUT", None) is not None and _ray._DIST_TIMEOUT < RAY_WEIGHT_SYNC_TIMEOUT:
        _ray._DIST_TIMEOUT = RAY_WEIGHT_SYNC_TIMEOUT


def _backend_options(cfg: RunConfig) -> dict[str, Any]:
    train = cfg.train
    options: dict[str, Any] = {}
    if train.collector_backend == "ray":
        if train.ray_address:
            options["ray_init_config"] = {"address": train.ray_address}
        else:
            options["ray_init_config"] = {
                "num_cpus": train.collector_cpus,
                "include_dashboard": False,
                # The workers print their collector at start-up; keep the console to the progress bar.
                "log_to_driver": False,
                # Ray starts every worker process at niceness 15, so the collection workers (and the weight-sync
                # ConnectionInfo actor, which imports torchrl in a fresh worker) get ~3% of a core next to any
                # other busy process: on a 2-core machine shared with another run, starting the workers took
                # minutes instead of seconds. They are the run's own work (the learner waits for their
                # batches): give them the learner's priority.
                "_system_config": {"worker_niceness": RAY_WORKER_NICENESS},
            }
        _lengthen_ray_weight_sync_timeout()
        # One CPU per worker and no memory reservation (TorchRL's default reserves 2 GB per worker).
        gpus = 0.2 if train.device.startswith("cuda") else 0
        options["remote_configs"] = {"num_cpus": 1, "num_gpus": gpus, "memory": None}
    elif train.collector_backend == "distributed":
        options.update(
            launcher=train.distributed_launcher,
            tcp_port=train.distributed_port,
            backend=train.distributed_backend,
        )
        if train.slurm_kwargs:
            options["slurm_kwargs"] = dict(train.slurm_kwargs)
    return options


def make_collector(
    cfg: RunConfig,
    policy,
    *,
    total_frames: int,
    init_random_frames: int,
    env_transform=None,
    first_step: int = 0,
) -> BaseCollector:
    """TorchRL ``Collector``: one env in this process, ``num_envs`` local worker processes, or remote workers.

    Args:
        cfg: the run configuration (``env``, ``train.frames_per_batch``, ``train.collector_backend`` and the
            ``train`` fields of the chosen backend).
        policy: the acting policy (:class:`~isodream_rl.modules.isodream_v2.IsoDreamV2Policy`).
        total_frames: agent steps still to collect (the whole run minus what a resumed run already has).
        init_random_frames: random-policy steps still to collect (the prefill).
        env_transform: ``() -> Transform`` appended to each env (the policy's recurrent-state primer).
        first_step: the env steps the run took before (a resumed run's). An env that returns a NaN/inf frame or
            reward stops the run naming the env step (:func:`~isodream_rl.trainers.builders.checked_env_factory`):
            the run's with one env, with several the env's own (its share of ``first_step`` plus its steps since).

    Returns:
        The collector; with ``ray``/``distributed`` each of the ``env.num_envs`` workers collects
        ``frames_per_batch / num_envs`` steps per batch (``sync=True``: one batch stacks them all).
    """
    train, num_envs = cfg.train, cfg.env.num_envs
    backend = train.collector_backend
    if backend == "sync":
        backend = "direct" if num_envs == 1 else "process"
    elif backend == "multiprocess":
        backend = "process"
    kwargs: dict[str, Any] = {}
    if backend != "direct":
        kwargs.update(num_collectors=num_envs, sync=True)
    options = _backend_options(cfg)
    if options:
        kwargs["backend_options"] = options
    # Every env is seeded in its factory, before the collector's first reset: ``collector.set_seed`` after
    # construction reseeds an env whose first observation the collector already holds (drawn unseeded), so the
    # first episode of a run would differ between runs of one seed and start from a frame of another episode.
    # (torchrl 0.14's DistributedCollector.set_seed also fails on its workers: it parses the seed as a list.)
    # An env in a worker process marks a NaN/inf in the batch instead of raising there (FiniteEnvData's
    # on_fault="mark"): the run's process refuses the batch in one line (ReplayPreparation).
    on_fault = "raise" if backend == "direct" else "mark"
    makes = []
    for i in range(num_envs):
        make = checked_env_factory(
            cfg, which=collector_env_suffix(i, num_envs), first_step=first_step // num_envs, on_fault=on_fault
        )
        if env_transform is not None:
            make = functools.partial(_with_transform, make, env_transform)
        makes.append(functools.partial(_seeded, make, train.seed + i))
    if backend == "direct":
        makes = makes[0]
    collector = Collector(
        makes,
        policy,
        backend=backend,
        frames_per_batch=train.frames_per_batch,
        total_frames=total_frames,
        init_random_frames=init_random_frames,
        # the policy acts on train.device (the env's outputs are cast there, its actions back); batches are stored
        # on the CPU, where the replay stays: the stepper moves each update's sample to the model's device
        device=train.device,
        storing_device="cpu",
        **kwargs,
    )
    if backend in ("ray", "distributed"):
        # The workers start from the pickled policy; this sets up the weight transfer the Trainer's
        # UpdateWeights hook uses after every batch.
        collector.update_policy_weights_()
    # TorchRL's Trainer starts optimising once ``collected_frames >= collector.init_random_frames``; the remote
    # collectors pass the prefill to their workers without keeping it themselves.
    if not hasattr(collector, "init_random_frames"):
        collector.init_random_frames = init_random_frames
    return collector
