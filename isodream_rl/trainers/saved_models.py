"""A checkpoint's weights read into the models built from a run's configuration, with one line when they do not fit.

The models of a run are built from its configuration (``algo``, ``model``), and a checkpoint's ``state["models"]``
(:func:`~isodream_rl.trainers.run_lifecycle.run_state`) holds the weights of each, by name. When the names, keys or
shapes differ, :func:`check_saved_models` raises :class:`CheckpointMismatchError`, which ``isodream-train`` and
``isodream-eval`` say in one line naming the checkpoint, the models that do not fit and what to change, where
``torch.nn.Module.load_state_dict`` would print its missing and unexpected keys in a traceback.

The saved configuration does not tell every learner apart: until ``algo=isodream`` became Iso-Dream on DreamerV3's
learner, it and its ablations (:data:`~isodream_rl.trainers.config.FORMER_DREAMER_V2_ALGOS`) were the
DreamerV2-style learner, now ``algo=isodream_v2``. Their weights tell them apart (:func:`saved_learner`): a resumed
run is refused naming the settings that continue it, and what only reads a checkpoint (``isodream-eval``, the latent
probe's :func:`~isodream_rl.trainers.world_model_run.load_world_model`) builds the learner the weights are of (:func:`saved_run_config`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from torch import nn

from isodream_rl.run_utils.checkpoint import CheckpointError
from isodream_rl.trainers.config import FORMER_DREAMER_V2_ALGOS, RunConfig, config_from_dict

#: ``learner -> (model names, world-model key prefix)``: what the weights of a checkpoint of Iso-Dream's two learners
#: hold, and the other's do not. The names of the models (``state["models"]``): the DreamerV2-style learner's
#: (:meth:`~isodream_rl.trainers.components.RunComponents.modules`) has ``actor_loss``, DreamerV3's
#: (:func:`~isodream_rl.trainers.dreamer_v3.dreamer_v3_checkpoint_modules`) ``actor`` and ``return_norm``; the
#: world model's controllable branch: ``IsoDreamV2WorldModel``'s RSSM ``control_rssm``, ``IsoDreamWorldModel``'s
#: prior ``control_prior`` (neither is in the other, nor in a TorchRL baseline's world model).
LEARNER_SIGNATURES: dict[str, tuple[frozenset[str], str]] = {
    "isodream_v2": (frozenset({"world_model", "actor_loss", "value_loss"}), "control_rssm."),
    "isodream": (frozenset({"world_model", "actor", "value_loss", "return_norm"}), "control_prior."),
}
#: how many keys of each kind a mismatch names
_NAMED_KEYS = 3


class CheckpointMismatchError(CheckpointError):
    """A checkpoint whose weights do not fit the models built from the run's configuration; the message names the
    checkpoint, the models and what to change."""


def saved_learner(models: Mapping[str, Mapping]) -> str | None:
    """The Iso-Dream learner whose weights ``models`` (a checkpoint's ``state["models"]``) are, by
    :data:`LEARNER_SIGNATURES`: ``"isodream_v2"`` (the DreamerV2-style learner), ``"isodream"`` (DreamerV3's), or
    ``None`` (another algorithm's, or a ``mode=world_model`` checkpoint)."""
    for learner, (names, prefix) in LEARNER_SIGNATURES.items():
        if set(models) == names and any(str(key).startswith(prefix) for key in models["world_model"]):
            return learner
    return None


def saved_run_config(state: Mapping) -> RunConfig:
    """The configuration that builds the models of a checkpoint's ``state``, to read its weights:
    :func:`~isodream_rl.trainers.config.config_from_dict` of ``state["config"]``, where a name of
    :data:`~isodream_rl.trainers.config.FORMER_DREAMER_V2_ALGOS` whose weights are the DreamerV2-style learner's
    (:func:`saved_learner`; a run saved before that name became Iso-Dream on DreamerV3's learner) is read as
    ``isodream_v2``. The ``algo`` fields saved with it (branch switches, policy input) set the variant, so the
    models built are the ones it trained; nothing else changes."""
    cfg = config_from_dict(state["config"])
    if cfg.algo.name in FORMER_DREAMER_V2_ALGOS and saved_learner(state["models"]) == "isodream_v2":
        cfg.algo.name = "isodream_v2"
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


def _learner_error(state: Mapping, *, algo: str, checkpoint: str) -> str | None:
    """The message of a checkpoint whose weights are the other Iso-Dream learner's than ``algo``'s, where a name
    that changed learner explains it, with the settings that resume it; ``None`` otherwise."""
    learner = saved_learner(state["models"])
    if algo in FORMER_DREAMER_V2_ALGOS and learner == "isodream_v2":
        settings = " ".join(("algo=isodream_v2", *FORMER_DREAMER_V2_ALGOS[algo]))
        return (
            f"{checkpoint} was saved by algo={algo} before it became Iso-Dream on DreamerV3's learner: its weights "
            f"are the DreamerV2-style learner's, now algo=isodream_v2; resume it with {settings}"
        )
    saved_algo = config_from_dict(state["config"]).algo.name if "config" in state else None
    if algo == "isodream_v2" and learner == "isodream" and saved_algo in FORMER_DREAMER_V2_ALGOS:
        return (
            f"{checkpoint} holds the weights of Iso-Dream on DreamerV3's learner (algo={saved_algo}), not the "
            f"DreamerV2-style learner's of algo=isodream_v2: resume it with algo={saved_algo}"
        )
    return None


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
            explains it (:data:`~isodream_rl.trainers.config.FORMER_DREAMER_V2_ALGOS`), the message says so and
            names the settings that resume it; otherwise it names the models and a few keys, and says that the
            run's settings must be the ones it was saved with.
    """
    problems = weight_problems(modules, state["models"])
    if not problems:
        return
    message = _learner_error(state, algo=algo, checkpoint=str(checkpoint))
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
