"""The parts of an ``algo=isodream`` run (the default, and its ablations ``isodream_no_inverse``,
``isodream_no_attention``, ``isodream_no_static``): Iso-Dream's decomposition on DreamerV3's learner.

The world model, actor and critic of :func:`~isodream_rl.objectives.isodream.make_isodream`, one
``DreamerV3Optimizer`` per parameter group (:func:`~isodream_rl.trainers.dreamer_v3.make_dreamer_v3_optimizers`)
and the DreamerV3 update (:class:`~isodream_rl.trainers.dreamer_v3.DreamerV3OptimizationStepper`), both shared with
``algo=torchrl_dreamer_v3``; the replay side is every run's. Its settings are one table,
:data:`~isodream_rl.modules.isodream.settings.ISODREAM_SETTINGS`.

Widths. DreamerV3's size rule per branch (``hidden``; ``deter = 8 hidden``; categoricals of ``hidden / 16``
classes): the controllable branch at ``hidden = hidden_per_hidden_dim x`` the size preset's ``hidden_dim`` (a
multiple of 8) with 32 categoricals, the action-free branch at ``free_hidden_fraction`` of that
(``model.free_hidden_fraction``, the settings table's 0.5 unless set; a multiple of 8) with as many fewer
categoricals (the same classes, so that both branches' logits stack for the KL terms); an image depth of
``hidden_dim / 8`` for the encoder and each of the three decoders. At ``size=bench``: ``hidden`` 80 and 40, image
depth 8, a 1.58 M-parameter world model, where ``algo=torchrl_dreamer_v3`` has one branch of ``hidden`` 120, image
depth 8 and 1.84 M (``bench/update_speed.py`` writes both counts).

``mode=world_model`` trains the world model alone (:func:`make_world_model_alone`): its loss,
:class:`~isodream_rl.objectives.isodream.IsoDreamModelLoss`, and the world model's ``DreamerV3Optimizer`` of a run
(:func:`~isodream_rl.trainers.dreamer_v3.make_dreamer_v3_world_model_stepper`), no actor, no critic;
:func:`make_world_model` builds it to read a checkpoint.

What it reads of the run configuration: ``model.size`` (``hidden_dim``), ``model.actor_units`` /
``value_units`` / ``attention_dim``, ``model.fast_paths`` (``IsoDreamConfig.fast_paths``; ``None``: on),
``model.free_hidden_fraction``, ``model.static_mask_bias`` (``IsoDreamConfig.static_mask_bias``; ``None``: 3);
``algo.free_branch`` / ``static_branch`` / ``inverse_dynamics`` (the branch switches), ``algo.reward_uses_free``,
``algo.policy_input``, ``algo.attention_window`` (tau), ``algo.horizon`` (L), ``algo.lambda_inverse``;
``train.world_model_lr`` / ``actor_lr`` / ``value_lr``, ``world_model_warmup``, ``lr_warmup``,
``max_nonfinite_updates``, ``sequence_length``, ``device``. The DreamerV2-style learner's settings
(``algo.gamma``: the continuation head's ``1 - 1/333`` discounts here; ``algo.lmbda``, ``actor_entropy``,
``free_nats``, ``kl_balance``, ``slow_target_every``, ``lambda_reward``, ``train.grad_clip``, ``adam_eps``...) are
refused (:func:`~isodream_rl.trainers.learners.unread_setting_errors`).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS, IsoDreamSettings
from isodream_rl.modules.isodream.world_model import IsoDreamConfig, IsoDreamWorldModel
from isodream_rl.modules.sizes import SIZE_PRESETS
from isodream_rl.objectives.isodream import IsoDreamLearner, IsoDreamModelLoss, make_isodream
from isodream_rl.trainers.components import RunComponents, WorldModelAlone, make_replay_parts
from isodream_rl.trainers.config import ConfigError, RunConfig
from isodream_rl.trainers.dreamer_v3 import (
    dreamer_v3_checkpoint_modules,
    make_dreamer_v3_stepper,
    make_dreamer_v3_world_model_stepper,
)


def isodream_config(
    cfg: RunConfig, *, action_dim: int, settings: IsoDreamSettings = ISODREAM_SETTINGS
) -> IsoDreamConfig:
    """The world model's :class:`~isodream_rl.modules.isodream.world_model.IsoDreamConfig` for ``cfg``.

    Raises:
        ConfigError: an unknown size preset or a precision other than fp32.
    """
    if cfg.model.size not in SIZE_PRESETS:
        raise ConfigError(f"invalid training configuration: unknown model.size={cfg.model.size!r}")
    precision = cfg.model.precision or "fp32"
    if precision != "fp32":
        raise ConfigError(
            f"invalid training configuration: algo={cfg.algo.name} trains in fp32 only (TorchRL's DreamerV3 "
            f"pieces autocast on CUDA only), got model.precision={precision!r}: drop the override"
        )
    hidden_dim = cfg.model.hidden_dim or SIZE_PRESETS[cfg.model.size]["hidden_dim"]
    hidden = 8 * max(1, round(settings.hidden_per_hidden_dim * hidden_dim / 8))
    fraction = (
        settings.free_hidden_fraction
        if cfg.model.free_hidden_fraction is None
        else cfg.model.free_hidden_fraction
    )
    if not 0 < fraction <= 2:
        raise ConfigError(
            f"invalid training configuration: model.free_hidden_fraction={fraction!r} must be in (0, 2] (the "
            "action-free branch's width per unit of the controllable branch's)"
        )
    free_hidden = 8 * max(1, round(fraction * hidden / 8))
    algo = cfg.algo
    fast_paths = True if cfg.model.fast_paths is None else cfg.model.fast_paths
    return IsoDreamConfig(
        action_dim=action_dim,
        hidden=hidden,
        free_hidden=free_hidden,
        image_depth=max(2, hidden_dim // 8),
        units=hidden,
        attention_window=algo.attention_window,
        free_branch=bool(algo.free_branch),
        static_branch=bool(algo.static_branch),
        inverse_dynamics=bool(algo.inverse_dynamics),
        reward_uses_free=bool(algo.reward_uses_free and algo.free_branch),
        settings=settings,
        fast_paths=fast_paths,
        **({} if cfg.model.static_mask_bias is None else {"static_mask_bias": cfg.model.static_mask_bias}),
    )


def lambda_inverse_of(cfg: RunConfig, settings: IsoDreamSettings = ISODREAM_SETTINGS) -> float:
    """The inverse-dynamics term's weight: ``algo.lambda_inverse``, or the learner's where it is ``None``."""
    return settings.lambda_inverse if cfg.algo.lambda_inverse is None else cfg.algo.lambda_inverse


def make_world_model(
    cfg: RunConfig,
    *,
    action_dim: int,
    device: torch.device | str,
    settings: IsoDreamSettings = ISODREAM_SETTINGS,
) -> IsoDreamWorldModel:
    """The world model of ``cfg`` (:func:`isodream_config`) on ``device``, as a run builds it (to read a checkpoint's
    weights into).

    Raises:
        ConfigError: as :func:`isodream_config`.
    """
    return IsoDreamWorldModel(isodream_config(cfg, action_dim=action_dim, settings=settings), device=device)


def make_world_model_alone(
    cfg: RunConfig, *, action_dim: int, settings: IsoDreamSettings = ISODREAM_SETTINGS
) -> WorldModelAlone:
    """The world model of ``cfg`` trained alone (``mode=world_model``): the world model a run of ``cfg`` builds, its
    loss (:class:`~isodream_rl.objectives.isodream.IsoDreamModelLoss`: DreamerV3's world-model terms and the
    inverse-dynamics term) and the world model's update of a run
    (:func:`~isodream_rl.trainers.dreamer_v3.make_dreamer_v3_world_model_stepper`: its ``DreamerV3Optimizer`` at
    ``train.world_model_lr``, ``lr_warmup``), no actor, no critic.

    Raises:
        ConfigError: as :func:`isodream_config`.
    """
    config = isodream_config(cfg, action_dim=action_dim, settings=settings)
    world_model = IsoDreamWorldModel(config, device=cfg.train.device)
    model_loss = IsoDreamModelLoss(
        world_model, lambda_inverse=lambda_inverse_of(cfg, settings), settings=settings
    )
    stepper = make_dreamer_v3_world_model_stepper(
        cfg,
        model_loss,
        world_model,
        state_dim=config.packed_state_dim,
        belief_dim=config.packed_belief_dim,
        settings=settings,
    )
    return WorldModelAlone(world_model=world_model, model_loss=model_loss, stepper=stepper, precision="fp32")


class IsoDreamComponents(RunComponents):
    """Models, losses, optimisers, stepper and replay buffer of an ``algo=isodream`` run or one of its ablations
    (module docstring).

    The interface of :class:`~isodream_rl.trainers.components.RunComponents`.

    Args:
        cfg: the run configuration.
        action_dim: width of the env's action.
        scratch_dir: folder of the replay buffer's memmap files.
        settings: the learner's settings. Defaults to its table,
            :data:`~isodream_rl.modules.isodream.settings.ISODREAM_SETTINGS`.

    Attributes:
        learner (:class:`~isodream_rl.objectives.isodream.IsoDreamLearner`), model_loss, world_model,
        behavior (``policy``, ``actor_loss``, ``value_loss``), stepper, replay_buffer, preparation, returns.
    """

    def __init__(
        self,
        cfg: RunConfig,
        *,
        action_dim: int,
        scratch_dir: Path,
        settings: IsoDreamSettings = ISODREAM_SETTINGS,
    ) -> None:
        train, model = cfg.train, cfg.model
        self.algo = cfg.algo.name
        config = isodream_config(cfg, action_dim=action_dim, settings=settings)
        self.learner: IsoDreamLearner = make_isodream(
            config,
            policy_input=cfg.algo.policy_input,
            attention_dim=model.attention_dim,
            actor_units=model.actor_units,
            value_units=model.value_units,
            horizon=cfg.algo.horizon,
            lambda_inverse=lambda_inverse_of(cfg, settings),
            device=train.device,
        )
        self.model_loss = self.learner.model_loss
        self.world_model = self.learner.world_model
        self.behavior = self.learner
        self.stepper = make_dreamer_v3_stepper(
            cfg,
            self.learner,
            state_dim=config.packed_state_dim,
            belief_dim=config.packed_belief_dim,
            settings=settings,
        )
        self.replay_buffer, self.preparation, self.returns = make_replay_parts(cfg, scratch_dir=scratch_dir)

    def modules(self) -> dict[str, nn.Module]:
        """The trained modules and the return normalisation's statistics, by checkpoint name
        (:func:`~isodream_rl.trainers.dreamer_v3.dreamer_v3_checkpoint_modules`)."""
        return dreamer_v3_checkpoint_modules(self.learner)
