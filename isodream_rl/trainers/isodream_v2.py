"""The parts of a run of the DreamerV2-style learner (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2`` and a
name of your own): the world model and its loss (eq. 5), the behavior (future-state attention, actor, value, their
losses and the acting policy), Adam per parameter group and :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`.

Its settings are the values :func:`~isodream_rl.trainers.learners.resolved` gives (its table,
:data:`~isodream_rl.trainers.learners.ISODREAM_V2_SETTINGS`, where the configuration leaves them ``None``);
``mode=world_model`` trains the world model of :func:`make_world_model_loss` alone
(:func:`make_world_model_alone`), and :func:`make_world_model` builds it to read a checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from isodream_rl.modules import PolicyInput
from isodream_rl.modules.isodream_v2 import (
    IsoDreamV2Actor,
    IsoDreamV2Config,
    IsoDreamV2Policy,
    IsoDreamV2Value,
    IsoDreamV2WorldModel,
)
from isodream_rl.objectives.isodream_v2 import (
    IsoDreamV2ActorLoss,
    IsoDreamV2Imagination,
    IsoDreamV2ModelLoss,
    IsoDreamV2ValueLoss,
    make_target_updater,
)
from isodream_rl.trainers.builders import make_adam
from isodream_rl.trainers.components import RunComponents, WorldModelAlone, make_replay_parts
from isodream_rl.trainers.config import RunConfig, world_model_overrides
from isodream_rl.trainers.learners import resolved
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper


def make_world_model_config(cfg: RunConfig, *, action_dim: int) -> IsoDreamV2Config:
    """``IsoDreamV2Config`` of the size preset with the algorithm's branch switches."""
    cfg = resolved(cfg)
    return IsoDreamV2Config.from_preset(cfg.model.size, action_dim=action_dim, **world_model_overrides(cfg))


def make_world_model_loss(cfg: RunConfig, *, action_dim: int, extra_terms=()) -> IsoDreamV2ModelLoss:
    """The world model and its loss (eq. 5) with the algorithm's weights and free-branch mode, plus
    ``extra_terms`` (see :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ModelLoss`)."""
    cfg = resolved(cfg)
    world_model = IsoDreamV2WorldModel(
        make_world_model_config(cfg, action_dim=action_dim), device=cfg.train.device
    )
    algo = cfg.algo
    return IsoDreamV2ModelLoss(
        world_model,
        lambda_reward=algo.lambda_reward,
        lambda_inverse=algo.lambda_inverse,
        free_nats=algo.free_nats,
        kl_balance=algo.kl_balance,
        free_branch_loss=algo.free_branch_loss,
        extra_terms=extra_terms,
    )


def make_world_model(cfg: RunConfig, *, action_dim: int, device: torch.device | str) -> IsoDreamV2WorldModel:
    """The world model of ``cfg`` (its size preset, ``model.<field>`` settings and branch switches) on ``device``,
    as a run builds it (to read a checkpoint's weights into)."""
    return IsoDreamV2WorldModel(make_world_model_config(cfg, action_dim=action_dim), device=device)


def make_world_model_alone(cfg: RunConfig, *, action_dim: int) -> WorldModelAlone:
    """The world model of ``cfg`` trained alone (``mode=world_model``): its loss (eq. 5,
    :func:`make_world_model_loss`) and :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper` with no
    actor and no value, Adam at ``train.world_model_lr`` (``adam_eps``), gradients clipped to ``train.grad_clip``.
    """
    cfg = resolved(cfg)
    train = cfg.train
    model_loss = make_world_model_loss(cfg, action_dim=action_dim)
    stepper = IsoDreamOptimizationStepper(
        model_loss=model_loss,
        world_model_optimizer=make_adam(model_loss.parameters(), lr=train.world_model_lr, eps=train.adam_eps),
        sequence_length=train.sequence_length,
        grad_clip=train.grad_clip,
        max_nonfinite=train.max_nonfinite_updates,
    )
    world_model = model_loss.world_model
    return WorldModelAlone(
        world_model=world_model,
        model_loss=model_loss,
        stepper=stepper,
        precision=world_model.config.precision,
    )


@dataclass
class Behavior:
    """The behavior side of a run (paper §3.3-3.4): policy input, actor, value, their losses and the policy."""

    policy_input: PolicyInput
    actor_loss: IsoDreamV2ActorLoss
    value_loss: IsoDreamV2ValueLoss
    target_updater: object
    policy: IsoDreamV2Policy


def make_behavior(cfg: RunConfig, world_model: IsoDreamV2WorldModel) -> Behavior:
    """Future-state attention (or plain [s, h]), actor, value with its slow target, losses and acting policy."""
    cfg = resolved(cfg)
    algo, model, device = cfg.algo, cfg.model, cfg.train.device
    policy_input = PolicyInput.for_world_model(
        world_model, mode=algo.policy_input, window=algo.attention_window, width=model.attention_dim
    )
    imagination = IsoDreamV2Imagination(world_model, policy_input, horizon=algo.horizon)
    value_loss = IsoDreamV2ValueLoss(
        IsoDreamV2Value(in_features=policy_input.out_features, num_cells=model.value_units, device=device),
        imagination,
    )
    actor = IsoDreamV2Actor(
        in_features=policy_input.out_features,
        action_dim=world_model.config.action_dim,
        num_cells=model.actor_units,
        device=device,
    )
    actor_loss = IsoDreamV2ActorLoss(
        actor,
        imagination,
        value_loss,
        gamma=algo.gamma,
        lmbda=algo.lmbda,
        entropy_bonus=algo.actor_entropy,
        loc_penalty=algo.actor_loc_penalty,
        attention_through_actor=algo.attention_through_actor,
    )
    return Behavior(
        policy_input=policy_input,
        actor_loss=actor_loss,
        value_loss=value_loss,
        target_updater=make_target_updater(value_loss, period=algo.slow_target_every),
        policy=IsoDreamV2Policy(world_model, actor, policy_input, exploration_noise=algo.exploration_noise),
    )


class IsoDreamV2Components(RunComponents):
    """Models, losses, optimisers, stepper and replay buffer of a run of the DreamerV2-style learner.

    The interface of :class:`~isodream_rl.trainers.components.RunComponents`.

    Args:
        cfg: the run configuration.
        action_dim: width of the env's action.
        scratch_dir: folder of the replay buffer's memmap files.

    Attributes:
        model_loss, world_model, behavior (:class:`Behavior`), stepper
        (:class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`), replay_buffer, preparation, returns
        (the replay and episode-return hooks).
    """

    def __init__(self, cfg: RunConfig, *, action_dim: int, scratch_dir: Path) -> None:
        cfg = resolved(cfg)
        train = cfg.train
        self.algo = cfg.algo.name
        self.model_loss = make_world_model_loss(cfg, action_dim=action_dim)
        self.world_model = self.model_loss.world_model
        self.behavior = make_behavior(cfg, self.world_model)
        groups = self.behavior.actor_loss.parameter_groups()
        self.stepper = IsoDreamOptimizationStepper(
            model_loss=self.model_loss,
            world_model_optimizer=make_adam(
                groups["world_model"], lr=train.world_model_lr, eps=train.adam_eps
            ),
            actor_loss=self.behavior.actor_loss,
            value_loss=self.behavior.value_loss,
            actor_optimizer=make_adam(groups["actor"], lr=train.actor_lr, eps=train.adam_eps),
            value_optimizer=make_adam(groups["value"], lr=train.value_lr, eps=train.adam_eps),
            target_updater=self.behavior.target_updater,
            sequence_length=train.sequence_length,
            grad_clip=train.grad_clip,
            max_nonfinite=train.max_nonfinite_updates,
            world_model_warmup=train.world_model_warmup,
        )
        self.replay_buffer, self.preparation, self.returns = make_replay_parts(cfg, scratch_dir=scratch_dir)

    def modules(self) -> dict[str, torch.nn.Module]:
        """The trained modules, by checkpoint name (the actor and value losses hold the actor, the value, its slow
        target and the attention)."""
        return {
            "world_model": self.world_model,
            "actor_loss": self.behavior.actor_loss,
            "value_loss": self.behavior.value_loss,
        }
