"""What both TorchRL baselines (:mod:`~isodream_rl.baselines.torchrl_dreamer`,
:mod:`~isodream_rl.baselines.torchrl_dreamer_v3`) share around TorchRL's pieces.

- :func:`preset_widths`: the widths a baseline reads from the run's size preset, the ``model.<field>`` settings applied.
- :class:`BaselineComponents`: the run parts' interface with the run's replay side and a checkpoint check.

The other shared pieces live in the lower layers, where Iso-Dream's learners use them too:
:func:`~isodream_rl.objectives.imagination_env.latent_dreamer_env` (a ``DreamerEnv`` over ``state``/``belief``
with its specs set by hand), :class:`~isodream_rl.modules.isodream_v2.policy.CarriedStatePolicy` (an acting policy that carries
its recurrent state under TorchRL's ``("next", ...)`` convention) and
:class:`~isodream_rl.trainers.stepper.ZeroStateStepper` (a stepper that turns a flat replay sample into the loss's
input, zero root ``state``/``belief`` added).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

from isodream_rl.modules.sizes import SIZE_PRESETS
from isodream_rl.trainers.components import RunComponents, make_replay_parts
from isodream_rl.trainers.config import RunConfig


def preset_widths(cfg: RunConfig, keys: Sequence[str]) -> dict[str, int]:
    """The size-preset fields ``keys`` of ``cfg`` (``SIZE_PRESETS[model.size]``, the ``model.<field>`` it sets applied;
    the others are refused by :func:`~isodream_rl.trainers.config.validate_config`).

    Raises:
        ValueError: an unknown size preset.
    """
    if cfg.model.size not in SIZE_PRESETS:
        raise ValueError(f"unknown size preset {cfg.model.size!r}; valid: {sorted(SIZE_PRESETS)}")
    overrides = cfg.model.world_model_fields()
    return {key: int(overrides.get(key, SIZE_PRESETS[cfg.model.size][key])) for key in keys}


class BaselineComponents(RunComponents):
    """The interface of :class:`~isodream_rl.trainers.components.RunComponents` for a baseline whose
    ``__init__`` builds its own models, losses and stepper: :meth:`set_replay_parts` gives it the run's replay
    buffer, preparation and episode-return hooks."""

    #: the ``algo.name`` the subclass is registered under (named by :meth:`load_models`)
    algo: ClassVar[str]

    def set_replay_parts(self, cfg: RunConfig, *, scratch_dir: Path) -> None:
        """``replay_buffer``, ``preparation``, ``returns``: the Iso-Dream run's
        (:func:`~isodream_rl.trainers.components.make_replay_parts`)."""
        self.replay_buffer, self.preparation, self.returns = make_replay_parts(cfg, scratch_dir=scratch_dir)
