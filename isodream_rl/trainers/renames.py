"""The renames' bookkeeping, in one place: what a name, configuration, run folder or checkpoint saved before a
rename means today.

Two renames changed what an ``algo`` name builds:

- ``algo=isodream_v3`` (Iso-Dream on DreamerV3's learner) became ``algo=isodream``, the default
  (:data:`RENAMED_ALGOS`): ``algo=isodream_v3`` is refused in one line naming ``algo=isodream``
  (:func:`renamed_algo_error`), and a configuration saved under it is read as ``algo=isodream``
  (:func:`saved_algo_name`);
- ``algo=isodream`` and its ablations were the DreamerV2-style learner until then, now ``algo=isodream_v2``
  (:data:`FORMER_DREAMER_V2_ALGOS`). A saved configuration does not tell such a run from a later one, in either
  mode (``mode=world_model`` trained the DreamerV2-style world model under those names too, until it trained the
  default's); its weights do (:func:`saved_learner`): what only reads a checkpoint builds the learner its weights
  are of (:func:`name_of_saved_learner`), a resume that does not fit says in one line which settings continue it
  (:func:`former_learner_error`), and ``algo=isodream_v2`` with those settings may resume it
  (:func:`resumes_former_run`).

Since each learner has its own settings table (:mod:`isodream_rl.trainers.learners`), a configuration saved before
holds values for the settings its learner does not read; they are dropped when it is read back
(:func:`drop_unread_settings`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from isodream_rl.trainers.learners import LEARNER_SETTINGS, learner_of

#: ``old name -> (new name, why)`` of the ``algo`` presets that were renamed.
RENAMED_ALGOS: dict[str, tuple[str, str]] = {
    "isodream_v3": (
        "isodream",
        "Iso-Dream on DreamerV3's learner became the default; the DreamerV2-style learner is algo=isodream_v2",
    ),
}
#: ``name -> settings``: the ``algo`` names that were Iso-Dream on the DreamerV2-style learner until they became
#: Iso-Dream on DreamerV3's learner, with the settings beside ``algo=isodream_v2`` that build the variant each was then
#: (its branch switch or policy input; the ``algo`` fields of a configuration saved then hold the same values).
FORMER_DREAMER_V2_ALGOS: dict[str, tuple[str, ...]] = {
    "isodream": (),
    "isodream_no_inverse": ("algo.inverse_dynamics=false",),
    "isodream_no_attention": ("algo.policy_input=controllable",),
    "isodream_no_static": ("algo.static_branch=false",),
}
#: ``learner -> (model names, world-model key prefix)``: what the weights of a ``mode=rl`` checkpoint of Iso-Dream's
#: two learners hold, and the other's do not. The names of the models (``state["models"]``): the DreamerV2-style
#: learner's (:meth:`~isodream_rl.trainers.isodream_v2.IsoDreamV2Components.modules`) has ``actor_loss``,
#: DreamerV3's (:func:`~isodream_rl.trainers.dreamer_v3.dreamer_v3_checkpoint_modules`) ``actor`` and
#: ``return_norm``; the world model's controllable branch: ``IsoDreamV2WorldModel``'s RSSM ``control_rssm``,
#: ``IsoDreamWorldModel``'s prior ``control_prior`` (neither is in the other, nor in a TorchRL baseline's world
#: model). A ``mode=world_model`` checkpoint holds the world model alone (:data:`WORLD_MODEL_ONLY`), told by the
#: same prefix.
LEARNER_SIGNATURES: dict[str, tuple[frozenset[str], str]] = {
    "isodream_v2": (frozenset({"world_model", "actor_loss", "value_loss"}), "control_rssm."),
    "isodream": (frozenset({"world_model", "actor", "value_loss", "return_norm"}), "control_prior."),
}
#: The models of a ``mode=world_model`` checkpoint, of either learner.
WORLD_MODEL_ONLY = frozenset({"world_model"})


def renamed_algo_error(name: str) -> str | None:
    """Why ``algo=name`` is refused when ``name`` is a former preset name (:data:`RENAMED_ALGOS`), with the name to
    give instead; ``None`` for any other name."""
    if name not in RENAMED_ALGOS:
        return None
    new_name, why = RENAMED_ALGOS[name]
    return f"algo={name} is now algo={new_name} ({why})"


def saved_algo_name(name: str) -> str:
    """The name today of the ``algo.name`` of a saved configuration: a renamed preset's new name, any other name as
    it is. A name of :data:`FORMER_DREAMER_V2_ALGOS` stays as it is, in either mode: its configuration does not tell
    which learner it was saved by, its weights do (:func:`name_of_saved_learner`)."""
    return RENAMED_ALGOS.get(name, (name,))[0]


def drop_unread_settings(saved: Mapping[str, Any]) -> dict[str, Any]:
    """A saved configuration (``dataclasses.asdict`` of a run configuration, its ``algo.name`` today's) without the
    values of the settings its learner does not read (:data:`~isodream_rl.trainers.learners.LEARNER_SETTINGS`):
    written before each learner had its own table, they were the schema's defaults, never read."""
    reads = learner_of(saved.get("algo", {}).get("name", "isodream")).values
    out = {section: dict(value) if isinstance(value, Mapping) else value for section, value in saved.items()}
    for key in LEARNER_SETTINGS:
        section, _, name = key.partition(".")
        if key not in reads and isinstance(out.get(section), dict) and name in out[section]:
            out[section][name] = None
    return out


def saved_learner(models: Mapping[str, Mapping]) -> str | None:
    """The Iso-Dream learner whose weights ``models`` (a checkpoint's ``state["models"]``, of either mode) are, by
    :data:`LEARNER_SIGNATURES` (a ``mode=world_model`` checkpoint, :data:`WORLD_MODEL_ONLY`, by its world model's
    prefix alone): ``"isodream_v2"`` (the DreamerV2-style learner), ``"isodream"`` (DreamerV3's), or ``None``
    (another algorithm's)."""
    for learner, (names, prefix) in LEARNER_SIGNATURES.items():
        if set(models) in (names, WORLD_MODEL_ONLY) and any(
            str(key).startswith(prefix) for key in models["world_model"]
        ):
            return learner
    return None


def name_of_saved_learner(algo: str, models: Mapping[str, Mapping]) -> str:
    """The ``algo.name`` that builds the models of a checkpoint saved as ``algo=<algo>`` (today's name) with the
    weights ``models``: ``isodream_v2`` for a name of :data:`FORMER_DREAMER_V2_ALGOS` whose weights are the
    DreamerV2-style learner's (saved before that name became Iso-Dream on DreamerV3's learner), ``algo`` otherwise.
    The ``algo`` fields saved with it (branch switches, policy input) set the variant."""
    return (
        "isodream_v2" if algo in FORMER_DREAMER_V2_ALGOS and saved_learner(models) == "isodream_v2" else algo
    )


def former_learner_error(
    models: Mapping[str, Mapping], *, saved_algo: str | None, algo: str, checkpoint: str
) -> str | None:
    """The one-line message of a checkpoint whose weights ``models`` are the other Iso-Dream learner's than
    ``algo=<algo>``'s, where a name that changed learner explains it, with the settings that resume it; ``None``
    otherwise. ``saved_algo``: the ``algo.name`` saved with it (today's name), ``None`` without one."""
    learner = saved_learner(models)
    if algo in FORMER_DREAMER_V2_ALGOS and learner == "isodream_v2":
        settings = " ".join(("algo=isodream_v2", *FORMER_DREAMER_V2_ALGOS[algo]))
        return (
            f"{checkpoint} was saved by algo={algo} before it became Iso-Dream on DreamerV3's learner: its weights "
            f"are the DreamerV2-style learner's, now algo=isodream_v2; resume it with {settings}"
        )
    if algo == "isodream_v2" and learner == "isodream" and saved_algo in FORMER_DREAMER_V2_ALGOS:
        return (
            f"{checkpoint} holds the weights of Iso-Dream on DreamerV3's learner (algo={saved_algo}), not the "
            f"DreamerV2-style learner's of algo=isodream_v2: resume it with algo={saved_algo}"
        )
    return None


def resumes_former_run(saved_algo: str, algo: str) -> bool:
    """Whether ``algo=<algo>`` may resume a run (of either mode) saved as ``algo=<saved_algo>`` (today's name) though
    the names differ: ``algo=isodream_v2`` continues a run saved under a name of :data:`FORMER_DREAMER_V2_ALGOS`,
    which may be one of the DreamerV2-style learner trained before that name became Iso-Dream on DreamerV3's
    learner; only its weights tell, and they are checked when they load (:func:`former_learner_error`)."""
    return saved_algo in FORMER_DREAMER_V2_ALGOS and algo == "isodream_v2"
