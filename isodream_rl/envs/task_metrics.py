"""The success counts of each task, beside its return: reaches and contacts on sprites, metres driven and
collisions on the highway.

``make_env`` exports the info entries these counts read (:func:`task_info_keys`) as float scalars, so evaluation
episodes run through TorchRL are scored the same way as the reference policies of
:mod:`isodream_rl.envs.reference`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


def _count(value):
    return value * 1.0


def _positive(value):
    return (value > 0) * 1.0


#: The task's success counts, per env name: ``metric -> (info key, per-step value)``; a metric is the sum of
#: the per-step values over an episode. ``make_env`` exports these info keys as float scalars, so evaluation
#: episodes run through TorchRL are scored the same way as the reference policies.
TASK_METRICS: dict[str, dict[str, tuple[str, Callable]]] = {
    "sprites": {"reaches": ("reached", _count), "contacts": ("touching", _count)},
    "highway": {"distance": ("distance", _count), "collisions": ("collision_impulse", _positive)},
}


def task_info_keys(name: str) -> tuple[str, ...]:
    """The info keys :data:`TASK_METRICS` reads for env ``name`` (empty for DMC)."""
    return tuple(key for key, _ in TASK_METRICS.get(name, {}).values())


def episode_metrics(name: str, steps: Sequence[dict[str, Any]]) -> dict[str, float]:
    """The task's success counts over one episode of env ``name``, from the per-step ``info`` dicts (or
    tensordicts holding the same keys).

    - sprites: ``reaches`` (targets reached), ``contacts`` (steps touching a distractor);
    - highway: ``distance`` (metres driven along the lane), ``collisions`` (crashes; a crash ends the episode);
    - other envs: ``{}``.
    """
    return {
        metric: float(sum(transform(step[key]) for step in steps))
        for metric, (key, transform) in TASK_METRICS.get(name, {}).items()
    }


__all__ = ["TASK_METRICS", "episode_metrics", "task_info_keys"]
