"""DreamerV3's behaviour learner (``algo=isodream``) on :class:`~isodream_rl.evaluation.ExactSpritesModel`.

:func:`make_exact_model_behavior` puts the learner of ``algo=isodream`` on the exact model of sprites
``reach``: the actor and the two-hot critic of :func:`~isodream_rl.modules.isodream.behavior.make_actor` /
:func:`~isodream_rl.modules.isodream.behavior.make_value` on the model's ``[s, h]`` (policy input
``"controllable"``: the model has no noncontrollable branch), and the losses of
:func:`~isodream_rl.objectives.dreamer_v3_behavior.make_dreamer_v3_behavior` with the exact model as the
imagination ``DreamerEnv`` (:func:`exact_imagination_env`: its step and reward, the reward error included).

The continuation. Sprites ``reach`` never terminates, so the exact continuation head is the constant that
DreamerV3's continuation head learns on non-terminal steps, ``1 - 1 / settings.continuation_horizon``
(:func:`exact_continuation`); with the TD(lambda) estimator's ``gamma = 1`` it discounts the lambda-returns and
weighs the imagined steps as a trained continuation head would.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.modules import WorldModelWrapper

from isodream_rl.evaluation.exact_sprites import ExactSpritesModel
from isodream_rl.modules.dreamer_v3 import DreamerV3Settings
from isodream_rl.modules.isodream.behavior import make_actor, make_value
from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS
from isodream_rl.objectives.dreamer_v3_behavior import DreamerV3Behavior, make_dreamer_v3_behavior
from isodream_rl.objectives.imagination_env import latent_dreamer_env


@dataclass(frozen=True)
class ExactWidths:
    """A branch's widths as :class:`~isodream_rl.modules.isodream.world_model.BranchWidths` gives them to the actor and
    critic: ``state_dim`` and ``deter`` (the belief), here the exact model's."""

    state_dim: int
    deter: int

    @property
    def feature_dim(self) -> int:
        """Width of ``[s, h]``."""
        return self.state_dim + self.deter


@dataclass(frozen=True)
class ExactModelConfig:
    """What :func:`~isodream_rl.modules.isodream.behavior.make_actor` and ``make_value`` read of an
    :class:`~isodream_rl.modules.isodream.world_model.IsoDreamConfig`, at the exact model's widths: ``s`` the 4
    positions, ``h`` the last reward, no action-free branch."""

    action_dim: int
    control: ExactWidths
    settings: DreamerV3Settings = ISODREAM_SETTINGS
    free_branch: bool = False
    free: ExactWidths = field(default_factory=lambda: ExactWidths(0, 0))
    fast_paths: bool = True
    """The actor's and critic's RMS norms as the fused ones (``IsoDreamConfig.fast_paths``)."""

    @classmethod
    def of(
        cls, model: ExactSpritesModel, settings: DreamerV3Settings = ISODREAM_SETTINGS
    ) -> ExactModelConfig:
        cfg = model.config
        return cls(
            action_dim=cfg.action_dim, control=ExactWidths(cfg.state_dim, cfg.belief_dim), settings=settings
        )


class _ExactTransition(nn.Module):
    """``(state, belief, action) -> (next state, next belief)``: the model's step; the belief is its reward."""

    def __init__(self, model: ExactSpritesModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, state: torch.Tensor, belief: torch.Tensor, action: torch.Tensor):
        _, _, next_state, reward = self.model.imagine_step(state, belief, action)
        return next_state, reward


class _ExactReward(nn.Module):
    """The model's reward head on ``[s, h]``: the reward of the step that reached the state."""

    def __init__(self, model: ExactSpritesModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, state: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        return self.model.reward_head(self.model.reward_features(state, belief))


class _Constant(nn.Module):
    """``[*N, 1]`` filled with ``value``, shaped after the input's batch dims."""

    def __init__(self, value: float) -> None:
        super().__init__()
        self.value = value

    def forward(self, belief: torch.Tensor) -> torch.Tensor:
        return torch.full((*belief.shape[:-1], 1), self.value, dtype=belief.dtype, device=belief.device)


def exact_imagination_env(model: ExactSpritesModel, *, device=None) -> DreamerEnv:
    """Imagination on the exact model: a ``DreamerEnv`` whose step is :meth:`ExactSpritesModel.imagine_step`
    (``state`` the positions, ``belief`` the step's reward) and whose reward is the model's reward head."""
    cfg = model.config
    return latent_dreamer_env(
        WorldModelWrapper(
            TensorDictModule(
                _ExactTransition(model), in_keys=["state", "belief", "action"], out_keys=["state", "belief"]
            ),
            TensorDictModule(_ExactReward(model), in_keys=["state", "belief"], out_keys=["reward"]),
        ),
        action_spec=Bounded(-1.0, 1.0, (cfg.action_dim,), device=device),
        state_dim=cfg.state_dim,
        belief_dim=cfg.belief_dim,
        device=device,
    )


def exact_continuation(settings: DreamerV3Settings = ISODREAM_SETTINGS) -> TensorDictModule:
    """The exact continuation of a task that never terminates: ``1 - 1 / settings.continuation_horizon``, what
    DreamerV3's continuation head learns on non-terminal steps (module docstring)."""
    return TensorDictModule(
        _Constant(1.0 - 1.0 / settings.continuation_horizon), in_keys=["belief"], out_keys=["continuation"]
    )


@dataclass
class ExactModelBehavior:
    """The default learner on the exact model: the networks, the imagination env and the losses."""

    actor: ProbabilisticTensorDictSequential
    value: TensorDictSequential
    model_based_env: DreamerEnv
    losses: DreamerV3Behavior

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The trained parameters: ``actor``, ``value`` (not the slow copy), as
        :meth:`~isodream_rl.objectives.isodream.IsoDreamLearner.parameter_groups` has them."""
        return {"actor": list(self.actor.parameters()), "value": list(self.losses.value_loss.parameters())}


def make_exact_model_behavior(
    model: ExactSpritesModel,
    *,
    actor_units: int = 128,
    value_units: int = 128,
    horizon: int = 15,
    settings: DreamerV3Settings = ISODREAM_SETTINGS,
) -> ExactModelBehavior:
    """``algo=isodream``'s actor, critic and losses on the exact model (module docstring).

    Args:
        model: the exact model (its ``reward_error`` is read at every step).
        actor_units: width of the actor's 3 hidden layers.
        value_units: width of the critic's 3 hidden layers.
        horizon: L, the imagination horizon.
        settings: DreamerV3's settings.
    """
    config = ExactModelConfig.of(model, settings)
    heads = {"mode": "controllable", "attention_dim": 1}
    actor = make_actor(config, units=actor_units, **heads)
    value = make_value(config, units=value_units, **heads)
    env = exact_imagination_env(model)
    losses = make_dreamer_v3_behavior(
        actor, value, env, continuation=exact_continuation(settings), horizon=horizon, settings=settings
    )
    return ExactModelBehavior(actor=actor, value=value, model_based_env=env, losses=losses)


__all__ = [
    "ExactModelBehavior",
    "ExactModelConfig",
    "exact_continuation",
    "exact_imagination_env",
    "make_exact_model_behavior",
]
