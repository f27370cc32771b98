"""The learners ``isodream-train`` builds, the ``algo`` names that build each, and each learner's settings table.

=========================================  =========================================  ===============================
learner                                    ``algo`` names                             its run parts
=========================================  =========================================  ===============================
Iso-Dream on DreamerV3's learner, the      ``isodream``, ``isodream_no_inverse``,     :mod:`isodream_rl.trainers.isodream`
default                                    ``isodream_no_attention``,
                                           ``isodream_no_static``
Iso-Dream on the DreamerV2-style learner   ``isodream_v2``, ``isodream_paper``,       :mod:`isodream_rl.trainers.isodream_v2`
                                           ``dreamerv2``, a name of your own
TorchRL's Dreamer                          ``torchrl_dreamer``                        :mod:`isodream_rl.baselines`
TorchRL's DreamerV3                        ``torchrl_dreamer_v3``                     :mod:`isodream_rl.baselines`
=========================================  =========================================  ===============================

Every learner reads the settings of a run's scale and shape (env, size preset, schedule, learning rates, branch
switches, policy input, horizon). The settings in the tables below are each read by some learners only: the run
configuration leaves them ``None``, which means "the learner's value", each learner's table
(:attr:`Learner.values`, with :attr:`Learner.per_domain` over it for the env's domain) gives that value
(:func:`resolved`), and a value given for a learner that does not read it is refused in one line naming the learners
that do (:func:`unread_setting_errors`), never checked and ignored. ``model.<field>`` settings are ``None`` in every
table: the size preset's width.

The default's table holds the values of its one settings table,
:data:`~isodream_rl.modules.isodream.settings.ISODREAM_SETTINGS`; TorchRL's DreamerV3's those of
:data:`~isodream_rl.modules.dreamer_v3.TORCHRL_DREAMER_V3_SETTINGS`; the DreamerV2-style learner's are
:data:`ISODREAM_V2_SETTINGS` (its loss weights from :data:`~isodream_rl.objectives.isodream_v2.LOSS_WEIGHTS`), of
which TorchRL's Dreamer reads :data:`SHARED_WITH_TORCHRL_DREAMER`, by design (the two DreamerV2-era learners
compared at the same discount, reward weight, free nats and optimiser).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from isodream_rl.modules.dreamer_v3 import TORCHRL_DREAMER_V3_SETTINGS
from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS
from isodream_rl.modules.isodream_v2.config import IsoDreamV2Config
from isodream_rl.objectives.isodream_v2.world_model import LOSS_WEIGHTS, PAPER_WEIGHTS

#: Iso-Dream on DreamerV3's learner: the default and its ablations.
ISODREAM_ALGOS = ("isodream", "isodream_no_inverse", "isodream_no_attention", "isodream_no_static")
#: The presets of the DreamerV2-style learner (a name of your own builds it too); the ``exp`` recipes of
#: ``mode=world_model`` pick it.
ISODREAM_V2_ALGOS = ("isodream_v2", "isodream_paper", "dreamerv2")
#: The algorithms built from TorchRL's own Dreamer pieces (``isodream_rl.baselines``): no Iso-Dream world model.
TORCHRL_BASELINES = ("torchrl_dreamer", "torchrl_dreamer_v3")
#: The algorithms trained by DreamerV3's update (:class:`~isodream_rl.trainers.dreamer_v3.DreamerV3OptimizationStepper`).
DREAMER_V3_LEARNERS = (*ISODREAM_ALGOS, "torchrl_dreamer_v3")
#: The learners (keys of :data:`LEARNERS`) whose world model ``mode=world_model`` trains alone and the latent probe
#: reads: Iso-Dream's two, whose world models have the branches the mode scores
#: (:mod:`isodream_rl.trainers.world_model_run`); TorchRL's baselines have none.
WORLD_MODEL_LEARNERS = ("isodream", "isodream_v2")

#: The ``model.<field>`` settings of the DreamerV2-style world model: every field of its configuration but the
#: env's ``action_dim``.
WORLD_MODEL_FIELDS = tuple(f.name for f in fields(IsoDreamV2Config) if f.name != "action_dim")

#: The settings TorchRL's Dreamer shares with the DreamerV2-style learner, with their values.
SHARED_WITH_TORCHRL_DREAMER: dict[str, Any] = {
    "algo.gamma": 0.99,
    "algo.lmbda": 0.95,
    "algo.lambda_reward": LOSS_WEIGHTS["lambda_reward"],
    "algo.free_nats": 1.0,
    "train.grad_clip": 100.0,
    "train.adam_eps": 1e-5,
}
#: ``env.domain -> values`` of :data:`SHARED_WITH_TORCHRL_DREAMER` on each domain (the paper's per-domain choices):
#: the authors' reward scale 2; on sprites a discount of 0.9, because the reach task's progress reward is
#: potential-based: with gamma near 1 and a critic that has learnt the progress still to come, it cancels out of the
#: actor's lambda-return except for a (1 - gamma) factor, and the actor stalls (docs/results/learning.md, "Why the
#: pixel runs stalled").
SHARED_WITH_TORCHRL_DREAMER_PER_DOMAIN: dict[str, dict[str, Any]] = {
    "carla": {"algo.lambda_reward": 2.0},
    "dmc": {"algo.lambda_reward": 2.0},
    "sprites": {"algo.lambda_reward": 2.0, "algo.gamma": 0.9},
}
#: The DreamerV2-style learner's settings table.
ISODREAM_V2_SETTINGS: dict[str, Any] = {
    **SHARED_WITH_TORCHRL_DREAMER,
    "algo.paper_exact": False,
    "algo.free_branch_loss": "kl",
    "algo.attention_through_actor": False,
    "algo.actor_entropy": 1e-4,
    "algo.actor_loc_penalty": 0.1,
    "algo.exploration_noise": 0.0,
    "algo.lambda_inverse": LOSS_WEIGHTS["lambda_inverse"],
    "algo.kl_balance": 0.8,
    "algo.slow_target_every": 100,
    **{f"model.{name}": None for name in WORLD_MODEL_FIELDS},
}


@dataclass(frozen=True)
class Learner:
    """One learner: what messages call it, the ``algo`` names that build it, and its settings table."""

    title: str
    """How a message names it."""
    algos: tuple[str, ...]
    """The ``algo`` presets that build it."""
    values: Mapping[str, Any]
    """``"section.field" -> value``: the settings it reads that not every learner reads, with its value of each
    (``None`` for a ``model.<field>``: the size preset's)."""
    per_domain: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """``env.domain -> values`` over :attr:`values` on that domain."""
    paper_exact: Mapping[str, Any] = field(default_factory=dict)
    """Values over the others where ``algo.paper_exact`` is true (eq. 5's weights)."""

    def named(self) -> str:
        """``"the DreamerV2-style learner (algo=isodream_v2, isodream_paper, dreamerv2)"``."""
        return f"{self.title} (algo={', '.join(self.algos)})"


#: The learners by the name of their first preset.
LEARNERS: dict[str, Learner] = {
    "isodream": Learner(
        title="Iso-Dream on DreamerV3's learner",
        algos=ISODREAM_ALGOS,
        values={
            "algo.lambda_inverse": ISODREAM_SETTINGS.lambda_inverse,
            "train.lr_warmup": ISODREAM_SETTINGS.lr_warmup,
            "model.hidden_dim": None,
            "model.precision": None,
            "model.fast_paths": None,  # IsoDreamConfig.fast_paths: None is on
            "model.free_hidden_fraction": None,  # None: ISODREAM_SETTINGS.free_hidden_fraction
            "model.static_mask_bias": None,  # None: IsoDreamConfig.static_mask_bias
        },
    ),
    "isodream_v2": Learner(
        title="the DreamerV2-style learner",
        algos=ISODREAM_V2_ALGOS,
        values=ISODREAM_V2_SETTINGS,
        per_domain={
            **SHARED_WITH_TORCHRL_DREAMER_PER_DOMAIN,
            "dmc": {**SHARED_WITH_TORCHRL_DREAMER_PER_DOMAIN["dmc"], "algo.free_branch_loss": "recon_only"},
        },
        paper_exact={"algo.lambda_inverse": PAPER_WEIGHTS["lambda_inverse"]},
    ),
    "torchrl_dreamer": Learner(
        title="TorchRL's Dreamer",
        algos=("torchrl_dreamer",),
        values={
            **SHARED_WITH_TORCHRL_DREAMER,
            **{f"model.{name}": None for name in ("depth", "state_dim", "belief_dim", "hidden_dim", "units")},
            "model.precision": None,
        },
        per_domain=SHARED_WITH_TORCHRL_DREAMER_PER_DOMAIN,
    ),
    "torchrl_dreamer_v3": Learner(
        title="TorchRL's DreamerV3",
        algos=("torchrl_dreamer_v3",),
        values={
            "train.lr_warmup": TORCHRL_DREAMER_V3_SETTINGS.lr_warmup,
            "model.hidden_dim": None,
            "model.precision": None,
        },
    ),
}
#: Every setting some learner reads and another does not.
LEARNER_SETTINGS = tuple(dict.fromkeys(key for learner in LEARNERS.values() for key in learner.values))


def learner_name(algo: str) -> str:
    """The key in :data:`LEARNERS` of the learner ``algo=<algo>`` builds: ``"isodream_v2"`` (the DreamerV2-style
    learner) for a name no learner lists."""
    return next((name for name, learner in LEARNERS.items() if algo in learner.algos), "isodream_v2")


def learner_of(algo: str) -> Learner:
    """The learner ``algo=<algo>`` builds: the DreamerV2-style one for a name no learner lists."""
    return LEARNERS[learner_name(algo)]


def world_model_algos() -> tuple[str, ...]:
    """The ``algo`` presets whose world model ``mode=world_model`` trains (those of :data:`WORLD_MODEL_LEARNERS`,
    the default's first; a name of your own builds the DreamerV2-style learner and is trained too)."""
    return tuple(name for learner in WORLD_MODEL_LEARNERS for name in LEARNERS[learner].algos)


def world_model_mode_error(algo: str) -> str | None:
    """Why ``mode=world_model`` refuses ``algo=<algo>``, in one line naming the algorithms it trains (those of
    :data:`WORLD_MODEL_LEARNERS`); ``None`` for one it trains."""
    if learner_name(algo) in WORLD_MODEL_LEARNERS:
        return None
    return (
        f"mode=world_model trains the world model of Iso-Dream's learners, whose branches it scores, not "
        f"algo={algo}'s ({learner_of(algo).title}: no branches): pick one of "
        f"{', '.join(f'algo={name}' for name in world_model_algos())}"
    )


def model_fields_read(algo: str) -> tuple[str, ...]:
    """The ``model.<field>`` settings (field names) the learner of ``algo`` reads besides the size preset."""
    return tuple(key.partition(".")[2] for key in learner_of(algo).values if key.startswith("model."))


def _get(cfg: Any, key: str) -> Any:
    section, _, name = key.partition(".")
    return getattr(getattr(cfg, section), name)


def unread_setting_errors(cfg: Any) -> list[str]:
    """One line per setting of :data:`LEARNER_SETTINGS` given a value (not ``None``) that the learner of
    ``cfg.algo.name`` does not read, naming the learners that read it."""
    learner = learner_of(cfg.algo.name)
    errors = []
    for key in LEARNER_SETTINGS:
        value = _get(cfg, key)
        if value is None or key in learner.values:
            continue
        readers = " and ".join(other.named() for other in LEARNERS.values() if key in other.values)
        errors.append(
            f"{key}={value!r} is not read by algo={cfg.algo.name} ({learner.title}): it is read by {readers}; "
            "drop it, or pick one of them"
        )
    return errors


def resolved(cfg: Any) -> Any:
    """A copy of the run configuration ``cfg`` with each setting its learner reads and ``cfg`` leaves ``None`` set to
    the learner's value: its table's, its ``env.domain`` row's over that, and its ``paper_exact`` values over those
    where ``algo.paper_exact`` is true. The settings the learner does not read stay as they are (``None``, unless
    given: :func:`unread_setting_errors` refuses those)."""
    learner = learner_of(cfg.algo.name)
    out = copy.deepcopy(cfg)
    values = {**learner.values, **learner.per_domain.get(cfg.env.domain, {})}
    for key, value in values.items():
        if _get(out, key) is None:
            section, _, name = key.partition(".")
            setattr(getattr(out, section), name, value)
    if learner.paper_exact and out.algo.paper_exact:
        for key, value in learner.paper_exact.items():
            if _get(cfg, key) is None:
                section, _, name = key.partition(".")
                setattr(getattr(out, section), name, value)
    return out
