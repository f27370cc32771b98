"""DreamerV3's behaviour losses on any imagination env: TorchRL's ``DreamerV3ActorLoss`` and ``DreamerV3ValueLoss``
with DreamerV3's settings, and the slow critic's ``SoftUpdate``.

:func:`make_dreamer_v3_behavior` composes them as :func:`~isodream_rl.objectives.isodream.make_isodream`
(``algo=isodream``) and :func:`~isodream_rl.baselines.torchrl_dreamer_v3.make_torchrl_dreamer_v3`
(``algo=torchrl_dreamer_v3``) do: REINFORCE with the 5th-95th percentile return normalisation, the entropy bonus
on normalised returns, TD(lambda) with ``gamma = 1`` (the continuation model's probabilities discount), a two-hot
critic with the slow-critic regulariser. It takes the actor, the critic, the imagination ``DreamerEnv`` and the
continuation model as arguments, so that the same learner trains on a world model's imagination or on
:class:`~isodream_rl.evaluation.ExactSpritesModel` (:mod:`isodream_rl.evaluation.exact_sprites_behavior`).
"""

from __future__ import annotations

from dataclasses import dataclass

from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModuleBase, TensorDictSequential
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.objectives import DreamerV3ActorLoss, DreamerV3Loss, DreamerV3ModelLoss, DreamerV3ValueLoss
from torchrl.objectives.utils import SoftUpdate, ValueEstimators

from isodream_rl.modules.dreamer_v3 import DreamerV3Settings


@dataclass
class DreamerV3Behavior:
    """DreamerV3's behaviour learner: the actor and critic losses and the slow critic's updater."""

    actor_loss: DreamerV3ActorLoss
    value_loss: DreamerV3ValueLoss
    target_updater: SoftUpdate


def make_dreamer_v3_behavior(
    actor: ProbabilisticTensorDictSequential,
    value: TensorDictSequential,
    model_based_env: DreamerEnv,
    *,
    continuation: TensorDictModuleBase,
    horizon: int = 15,
    settings: DreamerV3Settings,
) -> DreamerV3Behavior:
    """``DreamerV3ActorLoss`` + ``DreamerV3ValueLoss`` + ``SoftUpdate`` with DreamerV3's settings (module docstring).

    Args:
        actor: the actor (writes ``"action"`` and ``"action_log_prob"``).
        value: the two-hot critic (writes ``"state_value_logits"`` and ``"state_value"``).
        model_based_env: the imagination env (``DreamerEnv``: reset on ``"state"`` / ``"belief"``, writes the
            reward).
        continuation: writes ``"continuation"``, the probability that an imagined state continues (the discount
            of the lambda-returns: DreamerV3's continuation head learns ``1 - 1 / settings.continuation_horizon``
            on non-terminal steps).
        horizon: L, the imagination horizon.
        settings: DreamerV3's settings (:class:`~isodream_rl.modules.dreamer_v3.DreamerV3Settings`).
    """
    actor_loss = DreamerV3ActorLoss(
        actor,
        value,
        model_based_env,
        continuation_model=continuation,
        imagination_horizon=horizon,
        entropy_bonus=settings.entropy_bonus,
        use_reinforce=True,
        return_normalization_rate=settings.return_normalization_rate,
        return_normalization_min_scale=settings.return_normalization_min_scale,
    )
    actor_loss.make_value_estimator(ValueEstimators.TDLambda, gamma=1.0, lmbda=settings.lmbda)
    value_loss = DreamerV3ValueLoss(
        value,
        value_loss="two_hot",
        num_value_bins=settings.num_bins,
        actor_loss=actor_loss,
        slow_critic_regularization=settings.slow_critic_regularization,
    )
    return DreamerV3Behavior(
        actor_loss=actor_loss,
        value_loss=value_loss,
        target_updater=SoftUpdate(value_loss, tau=settings.slow_critic_tau),
    )


__all__ = ["DreamerV3Behavior", "make_dreamer_v3_behavior"]


def make_dreamer_v3_loss(
    model_loss: DreamerV3ModelLoss,
    behavior: DreamerV3Behavior,
    *,
    settings: DreamerV3Settings,
) -> DreamerV3Loss:
    """``DreamerV3Loss`` over a world-model loss and :func:`make_dreamer_v3_behavior`'s losses: the world model,
    imagination from every posterior, actor, critic, and the critic on the replayed posteriors (weight
    ``settings.replay_value_loss_weight``, returns discounted by ``1 - 1 / settings.continuation_horizon``)."""
    return DreamerV3Loss(
        model_loss,
        behavior.actor_loss,
        behavior.value_loss,
        replay_value_loss_weight=settings.replay_value_loss_weight,
        continuation_horizon=settings.continuation_horizon,
        lmbda=settings.lmbda,
    )


def dreamer_v3_model_loss_settings(settings: DreamerV3Settings) -> dict:
    """``DreamerV3ModelLoss``'s keyword arguments as TorchRL's reproduction configures it for pixels: separate
    dynamics and representation KL, squared error on ``pixels / 255`` (no symlog), two-hot reward, continuation
    trained to ``1 - 1 / continuation_horizon``; the output keeps its graph for the replay-value term."""
    return {
        "kl_mode": "separate",
        "lambda_dynamic": settings.lambda_dynamic,
        "lambda_representation": settings.lambda_representation,
        "unimix": settings.unimix,
        "free_bits": settings.free_bits,
        "lambda_continue": 1.0,
        "continue_target_scale": 1.0 - 1.0 / settings.continuation_horizon,
        "reco_symlog": False,
        "num_reward_bins": settings.num_bins,
        "detach_output": False,
    }
