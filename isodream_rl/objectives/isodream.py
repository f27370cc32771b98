"""Iso-Dream's objectives on DreamerV3's learner: TorchRL's DreamerV3 losses over the decoupled world model.

- World model (eq. 5): ``DreamerV3ModelLoss`` on :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel`
  (dynamics / representation KL of both branches with free bits, squared error of the composite, two-hot reward,
  continuation) plus the inverse-dynamics term (:class:`~isodream_rl.objectives.InverseDynamicsLoss`):
  :class:`IsoDreamModelLoss`.
- Imagination (Algorithm 1, lines 7-12): a TorchRL ``DreamerEnv`` whose transition steps the controllable branch
  with the action and slides the window of the action-free branch one step, so that at imagined step ``j`` the
  window holds ``z_{j .. j+tau-1}`` of one action-free chain rolled from the start state (the paper's ``L + tau``
  rollout, generated as it is read): :class:`IsoDreamTransition`, :func:`isodream_imagination_env`.
- Behaviour: ``DreamerV3ActorLoss`` (REINFORCE, percentile return normalisation, entropy on normalised returns,
  continuation-weighted lambda-returns) and ``DreamerV3ValueLoss`` (two-hot critic, slow-critic regulariser), the
  actor and the critic reading ``e_t`` (eqs. 6-7), composed by ``DreamerV3Loss`` with the replay-value term:
  :func:`make_isodream`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.modules import WorldModelWrapper
from torchrl.objectives import DreamerV3ActorLoss, DreamerV3Loss, DreamerV3ModelLoss, DreamerV3ValueLoss
from torchrl.objectives.utils import SoftUpdate

from isodream_rl.modules.dreamer_v3 import DreamerV3Settings, continuation_probability
from isodream_rl.modules.isodream.behavior import IsoDreamPolicy, make_actor, make_value
from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS
from isodream_rl.modules.isodream.world_model import IsoDreamConfig, IsoDreamWorldModel
from isodream_rl.objectives.dreamer_v3_behavior import (
    dreamer_v3_model_loss_settings,
    make_dreamer_v3_behavior,
    make_dreamer_v3_loss,
)
from isodream_rl.objectives.imagination_env import latent_dreamer_env
from isodream_rl.objectives.inverse_dynamics import InverseDynamicsLoss


class IsoDreamModelLoss(DreamerV3ModelLoss):
    """Eq. 5 on DreamerV3's terms: ``DreamerV3ModelLoss`` plus ``loss_model_inverse`` (the inverse-dynamics term).

    ``DreamerV3ModelLoss`` as TorchRL's DreamerV3 reproduction configures it for pixels (separate dynamics and
    representation KL with 1 free nat on their sum, here over both branches' categoricals; squared error of the
    composite on ``pixels / 255``; two-hot reward; continuation trained to ``1 - 1 / horizon``), its output kept
    with its graph for the replay-value term. The subclass only adds the inverse-dynamics term, which
    ``DreamerV3ModelLoss`` has no slot for.

    Args:
        world_model: the :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel`.
        lambda_inverse: weight of the inverse-dynamics term (``alpha`` of eq. 5; the default learner's, from
            :data:`~isodream_rl.modules.isodream.settings.ISODREAM_SETTINGS`, on the same per-frame squared-error
            scale as the image term).
        settings: DreamerV3's settings (the default learner's table).

    Returns (``forward``):
        ``(losses, tensordict)``: ``loss_model_reco``, ``loss_model_reward``, ``loss_model_dynamic``,
        ``loss_model_representation``, ``loss_model_continue``, ``loss_model_inverse`` (with the cell) and the
        diagnostics ``mask_control_mean`` / ``mask_free_mean`` / ``mask_static_mean``; the world model's output.
    """

    def __init__(
        self,
        world_model: IsoDreamWorldModel,
        *,
        lambda_inverse: float = ISODREAM_SETTINGS.lambda_inverse,
        settings: DreamerV3Settings = ISODREAM_SETTINGS,
    ) -> None:
        super().__init__(world_model, **dreamer_v3_model_loss_settings(settings))
        self.inverse_loss = (
            InverseDynamicsLoss(lambda_inverse=lambda_inverse)
            if world_model.config.inverse_dynamics
            else None
        )

    def forward(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        losses, output = super().forward(tensordict)
        if self.inverse_loss is not None:
            losses.set("loss_model_inverse", self.inverse_loss(output)["loss_inverse"].reshape(1))
        for name in ("control", "free", "static"):
            mask = output.get(("next", f"mask_{name}"), None)
            if mask is not None:
                losses.set(f"mask_{name}_mean", mask.detach().mean().reshape(1))
        return losses, output


class IsoDreamTransition(nn.Module):
    """One imagined step (Algorithm 1, line 10): the controllable prior with the action; the window of the
    action-free chain slides by one (its new last entry one action-free prior step from the old last).

    Shapes: packed ``state`` ``[*N, S]``, ``belief`` ``[*N, D]``, ``action`` ``[*N, A]``, ``free_window``
    ``[*N, tau, F]`` -> the next ``state``, ``belief``, ``free_window`` (``z`` of the next step is the window's
    first entry).
    """

    def __init__(self, world_model: IsoDreamWorldModel) -> None:
        super().__init__()
        self.world_model = world_model

    def forward(self, state, belief, action, free_window=None):
        model = self.world_model
        s, _ = model.split_state(state)
        h, _ = model.split_belief(belief)
        _, s, h = model.control_prior(s, h, action)
        if free_window is None:
            return s, h
        width = model.config.free.state_dim
        last = free_window[..., -1, :]
        z, h_free = model.free_step(last[..., :width], last[..., width:])
        free_window = torch.cat(
            [free_window[..., 1:, :], torch.cat([z, h_free], dim=-1).unsqueeze(-2)], dim=-2
        )
        first = free_window[..., 0, :]
        state = torch.cat([s, first[..., :width]], dim=-1)
        belief = torch.cat([h, first[..., width:]], dim=-1)
        return state, belief, free_window


class IsoDreamImaginationEnv(DreamerEnv):
    """TorchRL's ``DreamerEnv`` whose reset also rolls the action-free window from each start state (the
    ``DreamerV3ActorLoss`` resets the env on the replayed posteriors, which carry ``state`` and ``belief`` only)."""

    def __init__(self, *args, free_window: nn.Module | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.__dict__["_free_window"] = free_window

    def _reset(self, tensordict=None, **kwargs):
        tensordict = super()._reset(tensordict, **kwargs)
        model = self.__dict__["_free_window"]
        if model is not None and tensordict.get("free_window", None) is None:
            _, z = model.split_state(tensordict.get("state"))
            _, h_free = model.split_belief(tensordict.get("belief"))
            tensordict.set("free_window", model.free_window(z, h_free))
        return tensordict


def isodream_imagination_env(world_model: IsoDreamWorldModel, *, device=None) -> IsoDreamImaginationEnv:
    """Imagination on the packed latent (and the window, with the action-free branch), the reward head's decoded
    two-hot reward as the reward."""
    cfg = world_model.config
    transition_keys = ["state", "belief"] + (["free_window"] if cfg.free_branch else [])
    extra = {"free_window": (cfg.attention_window, cfg.free.feature_dim)} if cfg.free_branch else None
    return latent_dreamer_env(
        WorldModelWrapper(
            TensorDictModule(
                IsoDreamTransition(world_model),
                in_keys=["state", "belief", "action", *transition_keys[2:]],
                out_keys=transition_keys,
            ),
            TensorDictModule(
                world_model.reward, in_keys=["state", "belief"], out_keys=["reward_logits", "reward"]
            ),
        ),
        action_spec=Bounded(-1.0, 1.0, (cfg.action_dim,), device=device),
        state_dim=cfg.packed_state_dim,
        belief_dim=cfg.packed_belief_dim,
        extra_observations=extra,
        env_class=IsoDreamImaginationEnv,
        env_kwargs={"free_window": world_model if cfg.free_branch else None},
        device=device,
    )


@dataclass
class IsoDreamLearner:
    """Iso-Dream on DreamerV3's learner: networks, losses, slow-critic updater, imagination env, acting policy."""

    world_model: IsoDreamWorldModel
    actor: ProbabilisticTensorDictSequential
    value: TensorDictSequential
    model_based_env: DreamerEnv
    model_loss: IsoDreamModelLoss
    actor_loss: DreamerV3ActorLoss
    value_loss: DreamerV3ValueLoss
    loss_module: DreamerV3Loss
    target_updater: SoftUpdate
    policy: IsoDreamPolicy

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The trained parameters, each once: ``world_model``, ``actor`` (with its attention), ``value`` (with its
        attention; not the slow copy)."""
        return {
            "world_model": list(self.world_model.parameters()),
            "actor": list(self.actor.parameters()),
            "value": list(self.value_loss.parameters()),
        }


def make_isodream(
    config: IsoDreamConfig,
    *,
    policy_input: str = "attention",
    attention_dim: int = 64,
    actor_units: int = 128,
    value_units: int = 128,
    horizon: int = 15,
    lambda_inverse: float = ISODREAM_SETTINGS.lambda_inverse,
    device: str | torch.device = "cpu",
) -> IsoDreamLearner:
    """Iso-Dream's world model, actor and critic composed with TorchRL's DreamerV3 losses (module docstring).

    Args:
        config: the world model's widths and switches (with DreamerV3's settings in ``config.settings``).
        policy_input: ``e_t``'s mode (:class:`~isodream_rl.modules.isodream.behavior.PolicyFeatures`).
        attention_dim: width of the attention's projections.
        actor_units: width of the actor's 3 hidden layers.
        value_units: width of the critic's 3 hidden layers.
        horizon: L, the imagination horizon.
        lambda_inverse: weight of the inverse-dynamics term.
        device: where the modules live.

    Returns:
        :class:`IsoDreamLearner`; ``loss_module(td)`` on a ``[B, T]`` replay batch (root packed ``"state"`` /
        ``"belief"`` zeros) returns every ``loss_*`` term.
    """
    settings = config.settings
    world_model = IsoDreamWorldModel(config, device=device)
    heads = {"mode": policy_input, "attention_dim": attention_dim, "device": device}
    actor = make_actor(config, units=actor_units, **heads)
    value = make_value(config, units=value_units, **heads)
    model_based_env = isodream_imagination_env(world_model, device=device)
    model_loss = IsoDreamModelLoss(world_model, lambda_inverse=lambda_inverse, settings=settings)
    continuation = continuation_probability(world_model.continuation_logit, in_keys=["state", "belief"])
    behavior = make_dreamer_v3_behavior(
        actor, value, model_based_env, continuation=continuation, horizon=horizon, settings=settings
    )
    loss_module = make_dreamer_v3_loss(model_loss, behavior, settings=settings)
    return IsoDreamLearner(
        world_model=world_model,
        actor=actor,
        value=value,
        model_based_env=model_based_env,
        model_loss=model_loss,
        actor_loss=behavior.actor_loss,
        value_loss=behavior.value_loss,
        loss_module=loss_module,
        target_updater=behavior.target_updater,
        policy=IsoDreamPolicy(world_model, actor),
    )


__all__ = [
    "IsoDreamImaginationEnv",
    "IsoDreamLearner",
    "IsoDreamModelLoss",
    "IsoDreamTransition",
    "isodream_imagination_env",
    "make_isodream",
]
