"""The algorithms ``isodream-train`` can build, by ``algo.name``: a registry ``name -> components builder``.

Iso-Dream (the default) and its ablations are Iso-Dream on DreamerV3's learner,
:class:`~isodream_rl.trainers.isodream.IsoDreamComponents`
(:data:`~isodream_rl.trainers.learners.ISODREAM_ALGOS`); the DreamerV2-style learner (``isodream_v2``,
``isodream_paper``) and the DreamerV2 baseline are :class:`~isodream_rl.trainers.isodream_v2.IsoDreamV2Components`,
registered here; so is any other name (``algo.name`` is informational for it: the ``algo`` fields set the variant).
An algorithm defined elsewhere registers its builder where it is defined, with
:func:`register_algorithm` (in the spirit of SheepRL's ``@register_algorithm``); the TorchRL baselines of
:mod:`isodream_rl.baselines` do so when they are imported, which ``isodream-train`` does::

    @register_algorithm("my_dreamer")
    class MyDreamerComponents(RunComponents): ...

The trainers build a run's parts through :func:`make_components` and never import the algorithms above them.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Protocol, TypeVar

from isodream_rl.trainers.components import RunComponents
from isodream_rl.trainers.config import ALGO_NAMES, ConfigError, RunConfig
from isodream_rl.trainers.isodream import IsoDreamComponents
from isodream_rl.trainers.isodream_v2 import IsoDreamV2Components
from isodream_rl.trainers.learners import ISODREAM_ALGOS, TORCHRL_BASELINES
from isodream_rl.trainers.renames import renamed_algo_error


class ComponentsBuilder(Protocol):
    """Builds a run's parts: a :class:`~isodream_rl.trainers.components.RunComponents` (or one with its
    interface) for ``cfg``."""

    def __call__(self, cfg: RunConfig, *, action_dim: int, scratch_dir: Path) -> RunComponents: ...


Builder = TypeVar("Builder", bound=ComponentsBuilder)

#: ``algo.name -> builder`` of every algorithm registered so far
ALGORITHMS: dict[str, ComponentsBuilder] = {
    **dict.fromkeys((name for name in ALGO_NAMES if name not in TORCHRL_BASELINES), IsoDreamV2Components),
    **dict.fromkeys(ISODREAM_ALGOS, IsoDreamComponents),
}

#: the module that registers each algorithm defined outside the trainers, named when it is not registered yet
DEFINED_IN = dict.fromkeys(TORCHRL_BASELINES, "isodream_rl.baselines")


def register_algorithm(*names: str) -> Callable[[Builder], Builder]:
    """A decorator that registers the builder it decorates under each of ``names`` (``algo.name`` values).

    Raises:
        ValueError: a name is registered to another builder already.
    """

    def register(builder: Builder) -> Builder:
        for name in names:
            if ALGORITHMS.get(name, builder) is not builder:
                raise ValueError(f"algo={name} is registered already, to {ALGORITHMS[name]!r}")
            ALGORITHMS[name] = builder
        return builder

    return register


def components_builder(name: str) -> ComponentsBuilder:
    """The builder registered for ``algo.name`` ``name``; :class:`~isodream_rl.trainers.isodream_v2.IsoDreamV2Components`
    for a name nobody registered (an Iso-Dream variant named by its user).

    Raises:
        ConfigError: ``name`` is an algorithm defined outside the trainers (:data:`DEFINED_IN`) whose module has
            not been imported yet (the message names it), or a former name
            (:data:`~isodream_rl.trainers.renames.RENAMED_ALGOS`; the message names the new one).
    """
    if name in ALGORITHMS:
        return ALGORITHMS[name]
    renamed = renamed_algo_error(name)
    if renamed:
        raise ConfigError(f"invalid training configuration: {renamed}")
    if name in DEFINED_IN:
        raise ConfigError(
            f"invalid training configuration: algo.name={name!r} is not registered yet: it is registered when "
            f"{DEFINED_IN[name]} is imported (isodream-train imports it)"
        )
    return IsoDreamV2Components


def make_components(cfg: RunConfig, *, action_dim: int, scratch_dir: Path) -> RunComponents:
    """The run's parts for ``cfg.algo.name``, from its registered builder.

    Raises:
        ConfigError: ``cfg.algo.name`` is not registered (see :func:`components_builder`).
    """
    return components_builder(cfg.algo.name)(cfg, action_dim=action_dim, scratch_dir=scratch_dir)
