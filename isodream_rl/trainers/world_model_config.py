"""Settings of ``mode=world_model`` (the world model alone, on random-action episodes) and their checks.

The rest of such a run is configured by the sections every run shares: ``train`` (batch ``B x T``, learning
rate, seed, device), ``model`` and ``algo`` (the world model and its loss), ``env`` (the scene),
``logging`` (cadence in updates) and ``checkpoint``. ``configs/exp/world_model*.yaml`` are the recorded
recipes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from isodream_rl.modules.sizes import SIZE_PRESETS
from isodream_rl.trainers.learners import world_model_mode_error

#: What ``isodream-train`` trains: Algorithm 1 (world model, actor and value), or the world model alone.
MODES = ("rl", "world_model")


@dataclass
class WorldModelModeConfig:
    """The data and length of a ``mode=world_model`` run."""

    updates: int = 3000
    """World-model updates to run (``train.batch_size`` windows of ``train.sequence_length`` steps each)."""
    max_minutes: float = 0.0
    """Wall-clock budget of the run in minutes, data collection included and summed over resumes: training
    stops after the first update past it (scored, checkpointed and summarised as at ``updates``); 0: none."""
    episodes: int = 60
    """Random-action training episodes, collected once before the first update."""
    episode_length: int = 96
    """Steps per episode; a multiple of ``train.sequence_length`` (held-out episodes are cut into windows)."""
    held_out_episodes: int = 4
    """Episodes of other seeds, scored at every evaluation (as many training episodes are scored beside them,
    so a gap between the two is memorisation)."""
    action_hold: int = 8
    """Steps each random action is kept (1: a new one every step, and the sprites agent then jitters in place
    and the background branch absorbs it)."""
    probe_episodes: int = 32
    """Fresh episodes of the final latent probe on sprites (half fit, half score; 0: no probe)."""


def world_model_mode_errors(cfg: Any) -> list[str]:
    """The problems of a ``mode=world_model`` :class:`~isodream_rl.trainers.config.RunConfig`, one line each
    with its fix (the checks of Algorithm 1's collection and replay do not apply to it)."""
    errors: list[str] = []
    wm, train, algo = cfg.world_model, cfg.train, cfg.algo
    overrides = cfg.model.world_model_fields()
    if cfg.model.size not in SIZE_PRESETS:
        errors.append(f"model.size={cfg.model.size!r} is not one of {list(SIZE_PRESETS)}")
    refused = world_model_mode_error(algo.name)
    if refused:
        errors.append(refused)
    for name, value, minimum in (
        ("world_model.updates", wm.updates, 1),
        ("world_model.episodes", wm.episodes, 1),
        ("world_model.held_out_episodes", wm.held_out_episodes, 1),
        ("world_model.action_hold", wm.action_hold, 1),
        ("world_model.probe_episodes", wm.probe_episodes, 0),
        ("train.batch_size", train.batch_size, 1),
        ("train.sequence_length", train.sequence_length, 1),
        ("train.threads", train.threads, 1),
        ("train.max_nonfinite_updates", train.max_nonfinite_updates, 1),
        ("logging.log_every", cfg.logging.log_every, 1),
        ("logging.eval_every", cfg.logging.eval_every, 0),
        ("checkpoint.every_updates", cfg.checkpoint.every_updates, 1),
        ("checkpoint.keep", cfg.checkpoint.keep, 2),
    ):
        if value < minimum:
            errors.append(f"{name}={value} must be >= {minimum}")
    if train.sequence_length >= 1 and wm.episode_length % train.sequence_length:
        errors.append(
            f"world_model.episode_length={wm.episode_length} must be a multiple of train.sequence_length="
            f"{train.sequence_length} (exp=world_model, the recorded recipe, has 96-step episodes and 8 x 16 "
            "windows)"
        )
    softmax_static = algo.static_branch and overrides.get("mask_mode", "softmax") == "softmax"
    if overrides.get("static_mask_bias") and not softmax_static:
        errors.append(
            "model.static_mask_bias needs the static branch's mask logit (softmax masks, "
            "algo.static_branch=true); in sigmoid mode the background has no logit: drop it"
        )
    if not wm.max_minutes >= 0:
        errors.append(f"world_model.max_minutes={wm.max_minutes} must be >= 0 (0: no time limit)")
    if wm.probe_episodes == 1:
        errors.append(
            "world_model.probe_episodes=1: the probe fits on half the episodes and scores the rest: 0 or >= 2"
        )
    return errors
