"""A checkpoint's weights read into the models built from a run's configuration, with one line when they do not fit.

The models of a run are built from its configuration (``algo``, ``model``), and a checkpoint's ``state["models"]``
(:func:`~isodream_rl.trainers.run_lifecycle.run_state`) holds the weights of each, by name. When the names, keys or
shapes differ, :func:`check_saved_models` raises :class:`CheckpointMismatchError`, which ``isodream-train`` and
``isodream-eval`` say in one line naming the checkpoint, the models that do not fit and what to change, where
``torch.nn.Module.load_state_dict`` would print its missing and unexpected keys in a traceback.

The saved configuration does not tell every learner apart: until ``algo=isodream`` became Iso-Dream on DreamerV3's
learner, it and its ablations were the DreamerV2-style learner, now ``algo=isodream_v2``. Their weights tell them
apart (:mod:`isodream_rl.trainers.renames`): a resumed run is refused naming the settings that continue it, and what
only reads a checkpoint (``isodream-eval``, the latent probe's
:func:`~isodream_rl.trainers.world_model_run.load_world_model`) builds the learner the weights are of
(:func:`saved_run_config`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from torch import nn

from isodream_rl.run_utils.checkpoint import CheckpointError
from isodream_rl.trainers.config import RunConfig, config_from_dict
from isodream_rl.trainers.renames import former_learner_error, name_of_saved_learner

#: how many keys of each kind a mismatch names
_NAMED_KEYS = 3


class CheckpointMismatchError(CheckpointError):
    """A checkpoint whose weights do not fit the models built from the run's configuration; the message names the
    checkpoint, the models and what to change."""


def saved_run_config(state: Mapping) -> RunConfig:
    """The configuration that builds the models of a checkpoint's ``state``, to read its weights:
    :func:`~isodream_rl.trainers.config.config_from_dict` of ``state["config"]`` under the name of the learner its
    weights are of (:func:`~isodream_rl.trainers.renames.name_of_saved_learner`)."""
    cfg = config_from_dict(state["config"])
    name = name_of_saved_learner(cfg.algo.name, state["models"])
    if name != cfg.algo.name:
        cfg = config_from_dict({**state["config"], "algo": {**state["config"]["algo"], "name": name}})
    return cfg


def _shape(value) -> str:
    """``16x24``: a tensor's shape (``scalar`` for none); the type's name for a value without one."""
    shape = getattr(value, "shape", None)
    if shape is None:
        return type(value).__name__
    return "x".join(map(str, shape)) or "scalar"


def _few(keys: list[str]) -> str:
    named = ", ".join(keys[:_NAMED_KEYS])
    return named + (", ..." if len(keys) > _NAMED_KEYS else "")


def weight_problems(modules: Mapping[str, nn.Module], saved: Mapping[str, Mapping]) -> list[str]:
    """What of ``saved`` (``{name: state_dict}``) does not fit ``modules``, one entry per model that does not:
    ``"<name>: not in the checkpoint"``, or its missing and unexpected keys and those of another shape (a few of
    each named); ``[]`` when every module can load its weights. Saved models that no module reads are not a
    problem."""
    problems = []
    for name, module in modules.items():
        if name not in saved:
            problems.append(f"{name}: not in the checkpoint")
            continue
        expected, given = module.state_dict(), saved[name]
        missing = [key for key in expected if key not in given]
        unexpected = [key for key in given if key not in expected]
        reshaped = [
            f"{key} {_shape(given[key])} -> {_shape(value)}"
            for key, value in expected.items()
            if key in given and hasattr(value, "shape") and getattr(given[key], "shape", None) != value.shape
        ]
        found = [f"{len(missing)} missing keys ({_few(missing)})"] if missing else []
        if unexpected:
            found.append(f"{len(unexpected)} unexpected keys ({_few(unexpected)})")
        if reshaped:
            found.append(f"{len(reshaped)} keys of another shape (saved -> here: {_few(reshaped)})")
        if found:
            problems.append(f"{name}: {', '.join(found)}")
    return problems


def check_saved_models(
    modules: Mapping[str, nn.Module], state: Mapping, *, algo: str, checkpoint: str | Path
) -> None:
    """Refuse a checkpoint whose weights (``state["models"]``) do not fit ``modules``, those of an ``algo=<algo>``
    run, in one line.

    Args:
        modules: the run's models, by checkpoint name.
        state: the checkpoint's state (``"models"``; ``"config"`` where it has one).
        algo: the run's ``algo.name``.
        checkpoint: the checkpoint's folder, or words naming it, for the message.

    Raises:
        CheckpointMismatchError: some model is not in the checkpoint, or some of its keys are missing, unexpected or
            of another shape. Where the weights are the other Iso-Dream learner's and the name of the run's algo
            explains it (:data:`~isodream_rl.trainers.renames.FORMER_DREAMER_V2_ALGOS`), the message says so and
            names the settings that resume it; otherwise it names the models and a few keys, and says that the
            run's settings must be the ones it was saved with.
    """
    problems = weight_problems(modules, state["models"])
    if not problems:
        return
    saved_algo = config_from_dict(state["config"]).algo.name if "config" in state else None
    message = former_learner_error(
        state["models"], saved_algo=saved_algo, algo=algo, checkpoint=str(checkpoint)
    )
    raise CheckpointMismatchError(
        message
        or (
            f"{checkpoint} does not fit the models of algo={algo} ({'; '.join(problems)}): the run's algo and model "
            "settings (size, widths, branches) must be the ones it was saved with, on a version of isodream_rl "
            "whose models have these weights"
        )
    )


def load_saved_models(
    modules: Mapping[str, nn.Module], state: Mapping, *, algo: str, checkpoint: str | Path
) -> None:
    """Load a checkpoint's weights (``state["models"]``) into ``modules`` once :func:`check_saved_models` finds
    that they fit (same arguments).

    Raises:
        CheckpointMismatchError: as :func:`check_saved_models`.
    """
    check_saved_models(modules, state, algo=algo, checkpoint=checkpoint)
    for name, module in modules.items():
        module.load_state_dict(state["models"][name])
