"""Trains the behavior learner of a run on :class:`~isodream_rl.evaluation.ExactSpritesModel` (no model error).

:func:`train_behavior_on_exact_model` builds the behavior of a :class:`~isodream_rl.trainers.RunConfig` on the
exact model of sprites ``reach`` and trains it as a real run does, optionally with an early fixed-direction
reward error:

- the DreamerV2-style learner (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``: every ``algo`` not in
  :data:`~isodream_rl.trainers.learners.ISODREAM_ALGOS`):
  :func:`~isodream_rl.trainers.isodream_v2.make_behavior` (the actor, value, losses and their settings, as a real run has them), trained the way
  :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper` does after its world-model step;
- ``algo=isodream`` (the default) and its ablations, DreamerV3's learner:
  :func:`~isodream_rl.evaluation.exact_sprites_behavior.make_exact_model_behavior`
  (the actor and two-hot critic of ``make_actor`` / ``make_value``, ``DreamerV3ActorLoss`` (REINFORCE)
  and ``DreamerV3ValueLoss`` with DreamerV3's settings, the exact continuation ``1 - 1/333``), a
  ``DreamerV3Optimizer`` per group (:func:`~isodream_rl.trainers.dreamer_v3.make_dreamer_v3_optimizers`) and
  the slow critic's ``SoftUpdate``, the way :class:`~isodream_rl.trainers.dreamer_v3.DreamerV3OptimizationStepper`
  does after its world-model step.

It returns the curve of the deterministic policy's 200-step return beside the scripted controller and the best
constant action. ``bench/exact_model.py`` compares learner settings with it; ``tests/test_exact_model.py`` holds
the library's defaults to it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from isodream_rl.evaluation.exact_sprites import ExactSpritesModel, reference_returns
from isodream_rl.evaluation.exact_sprites_behavior import make_exact_model_behavior
from isodream_rl.modules.dreamer_v3 import DreamerV3Settings
from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS
from isodream_rl.trainers.builders import make_adam
from isodream_rl.trainers.config import RunConfig
from isodream_rl.trainers.dreamer_v3 import make_dreamer_v3_optimizers
from isodream_rl.trainers.isodream_v2 import make_behavior
from isodream_rl.trainers.learners import ISODREAM_ALGOS, resolved
from isodream_rl.trainers.stepper import loss_sum


@dataclass
class ExactModelResult:
    """The curve of :func:`train_behavior_on_exact_model` and the reference returns on the same starts."""

    updates: list[int] = field(default_factory=list)
    returns: list[float] = field(default_factory=list)
    reaches: list[float] = field(default_factory=list)
    cosine: list[float] = field(default_factory=list)
    entropy: list[float] = field(default_factory=list)
    grad_norm_actor: list[float] = field(default_factory=list)
    mean_abs_action: list[float] = field(default_factory=list)
    scripted_return: float = 0.0
    constant_return: float = 0.0
    wall_s: float = 0.0

    def normalised(self, value: float) -> float:
        """``(R - R_constant) / (R_scripted - R_constant)``."""
        return (value - self.constant_return) / (self.scripted_return - self.constant_return)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def train_behavior_on_exact_model(
    cfg: RunConfig,
    *,
    updates: int = 750,
    batch: int = 512,
    reward_error: float = 0.0,
    error_updates: int = 0,
    error_direction: tuple[float, float] = (1.0, 0.0),
    eval_every: int = 50,
    eval_episodes: int = 16,
    seed: int = 0,
    model_kwargs: dict[str, Any] | None = None,
    progress: bool = False,
    settings: DreamerV3Settings | None = None,
) -> ExactModelResult:
    """Trains the behavior of ``cfg`` (a :class:`~isodream_rl.trainers.RunConfig`) on :class:`ExactSpritesModel`.

    Each update imagines ``cfg.algo.horizon`` steps from ``batch`` random starts (the replay posteriors of a
    real run: ``B * T = 512`` at ``size=bench``) and steps the actor and the value (+ policy input) optimisers on
    the sum of their losses, then the slow value target, as the run's stepper does after its world-model step:
    Adam clipped at ``cfg.train.grad_clip`` and the hard copy every ``algo.slow_target_every`` updates
    (:class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`), or with ``cfg.algo.name`` in
    :data:`~isodream_rl.trainers.learners.ISODREAM_ALGOS` (``algo=isodream``, the default, and its
    ablations) DreamerV3's optimisers (adaptive clipping, learning-rate warm-up) and the slow critic's
    ``SoftUpdate`` (:class:`~isodream_rl.trainers.dreamer_v3.DreamerV3OptimizationStepper`; module docstring).
    For the first ``error_updates`` updates the model's reward carries ``reward_error`` along
    ``error_direction``. Every ``eval_every`` updates (and after the last) the deterministic policy (the actor's
    mode; DreamerV3's actor: its mean) plays ``eval_episodes`` episodes of 200 steps on the exact model.

    Args:
        cfg: the run's settings; ``cfg.algo.policy_input`` must be ``"controllable"`` (the model has no
            noncontrollable branch). Its behavior settings, widths and learning rates are used as they are
            (DreamerV3's learner: ``model.actor_units`` / ``value_units``, ``algo.horizon``,
            ``train.actor_lr`` / ``value_lr``; DreamerV3's ``settings`` replace the rest).
        updates: behavior updates.
        batch: start states per update.
        reward_error, error_updates, error_direction: the early model error.
        eval_every, eval_episodes: the evaluation schedule.
        seed: seeds torch (the networks and the imagined actions) and the model's starts.
        model_kwargs: extra :class:`ExactSpritesModel` arguments (``sprite_size`` ...).
        progress: print one line per evaluation.
        settings: DreamerV3's settings (``None``: the default learner's table,
            :data:`~isodream_rl.modules.isodream.settings.ISODREAM_SETTINGS`); the DreamerV2-style learner does not
            read them.
    """
    if cfg.algo.policy_input != "controllable":
        raise ValueError(
            f"the exact model has no noncontrollable branch: algo.policy_input must be 'controllable', got "
            f"{cfg.algo.policy_input!r}"
        )
    torch.manual_seed(seed)
    model = ExactSpritesModel(
        reward_error=reward_error, error_direction=error_direction, seed=seed, **(model_kwargs or {})
    )
    learner = exact_model_learner(cfg, model, settings=settings)
    result = ExactModelResult()
    result.scripted_return, result.constant_return = reference_returns(model, episodes=eval_episodes)
    start_time = time.perf_counter()
    _evaluate(result, model, learner, step=0, metrics=None, episodes=eval_episodes, progress=progress)
    for step in range(1, updates + 1):
        model.reward_error = reward_error if step <= error_updates else 0.0
        metrics = _update(learner, model, batch=batch)
        if step % eval_every == 0 or step == updates:
            _evaluate(
                result, model, learner, step=step, metrics=metrics, episodes=eval_episodes, progress=progress
            )
    result.wall_s = time.perf_counter() - start_time
    return result


def _update(learner: ExactModelLearner, model: ExactSpritesModel, *, batch: int) -> TensorDict:
    """One behavior update from ``batch`` random starts of ``model``: both losses backpropagated, each optimiser's
    gradients clipped and stepped, the slow value updated; the actor loss's entries with the actor's gradient norm
    and the mean absolute imagined action."""
    state, belief = model.initial_state(batch)
    start = TensorDict(dict(zip(learner.start_keys, (state, belief))), [batch])
    actor_losses, imagined = learner.actor_loss(start)
    value_losses, _ = learner.value_loss(imagined)
    loss = loss_sum(actor_losses) + loss_sum(value_losses)
    optimizers = learner.optimizers
    for opt in optimizers.values():
        opt.zero_grad(set_to_none=True)
    loss.backward()
    norms = {
        name: nn.utils.clip_grad_norm_([p for g in opt.param_groups for p in g["params"]], learner.grad_clip)
        for name, opt in optimizers.items()
    }
    for opt in optimizers.values():
        opt.step()
    learner.target_updater.step()
    metrics = actor_losses.detach().clone()
    metrics["grad_norm_actor"] = norms["actor"].detach()
    metrics["mean_abs_action"] = imagined["action"].abs().mean()
    return metrics


def _evaluate(
    result: ExactModelResult,
    model: ExactSpritesModel,
    learner: ExactModelLearner,
    *,
    step: int,
    metrics: TensorDict | None,
    episodes: int,
    progress: bool,
) -> None:
    """Play ``episodes`` episodes of the deterministic policy on ``model`` and append them (and ``metrics``, the
    update's) to ``result``; with ``progress``, one line."""
    scores = model.episode_returns(learner.policy, episodes=episodes)
    result.updates.append(step)
    result.returns.append(scores["return"])
    result.reaches.append(scores["reaches"])
    result.cosine.append(scores["cosine"])
    if metrics is not None:
        result.entropy.append(float(metrics["actor_entropy"]))
        result.grad_norm_actor.append(float(metrics["grad_norm_actor"]))
        result.mean_abs_action.append(float(metrics["mean_abs_action"]))
    if progress:
        print(
            f"update {step}: return {scores['return']:.1f} (scripted {result.scripted_return:.1f}), "
            f"cosine {scores['cosine']:.2f}, entropy {result.entropy[-1] if result.entropy else math.nan:.2f}",
            flush=True,
        )


@dataclass
class ExactModelLearner:
    """What the loop of :func:`train_behavior_on_exact_model` steps: the losses, an optimiser per group (its
    gradients clipped at ``grad_clip`` first), the slow value's updater and the deterministic policy
    ``policy(state, belief) -> action``."""

    actor_loss: nn.Module
    value_loss: nn.Module
    optimizers: dict[str, torch.optim.Optimizer]
    grad_clip: float
    target_updater: Any
    policy: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    start_keys: tuple = (("next", "state"), ("next", "belief"))
    """Where the actor loss reads the start states (the DreamerV2-style loss: the posteriors' ``next`` keys)."""


def exact_model_learner(
    cfg: RunConfig, model: ExactSpritesModel, *, settings: DreamerV3Settings | None = None
) -> ExactModelLearner:
    """The behavior learner of ``cfg.algo.name`` on ``model`` (module docstring): DreamerV3's for ``algo=isodream``
    and its ablations (:data:`~isodream_rl.trainers.learners.ISODREAM_ALGOS`; ``settings``:
    DreamerV3's, ``None`` for the library's), the DreamerV2-style one for every other name."""
    if cfg.algo.name in ISODREAM_ALGOS:
        return _dreamer_v3_learner(cfg, model, settings or ISODREAM_SETTINGS)
    return _dreamer_v2_learner(cfg, model)


def _dreamer_v2_learner(cfg: RunConfig, model: ExactSpritesModel) -> ExactModelLearner:
    """The run's DreamerV2-style behavior (``make_behavior``), Adam per group clipped at ``train.grad_clip``, the
    actor's mode as the policy."""
    cfg = resolved(cfg)
    behavior = make_behavior(cfg, model)
    actor_loss, value_loss = behavior.actor_loss, behavior.value_loss
    actor = actor_loss.actor
    train = cfg.train
    return ExactModelLearner(
        actor_loss=actor_loss,
        value_loss=value_loss,
        optimizers={
            "actor": make_adam(actor_loss.parameters(), lr=train.actor_lr, eps=train.adam_eps),
            "value": make_adam(value_loss.parameters(), lr=train.value_lr, eps=train.adam_eps),
        },
        grad_clip=train.grad_clip,
        target_updater=behavior.target_updater,
        policy=lambda state, belief: actor.mode(torch.cat([state, belief], dim=-1)),
    )


def _dreamer_v3_learner(
    cfg: RunConfig, model: ExactSpritesModel, settings: DreamerV3Settings
) -> ExactModelLearner:
    """``algo=isodream``'s behavior (DreamerV3's learner) on the exact model, a ``DreamerV3Optimizer`` per group
    (its own adaptive clipping: the loop only measures the norms, as ``DreamerV3OptimizationStepper``), the
    actor's mean (``tanh(loc)``) as the policy."""
    behavior = make_exact_model_behavior(
        model,
        actor_units=cfg.model.actor_units,
        value_units=cfg.model.value_units,
        horizon=cfg.algo.horizon,
        settings=settings,
    )
    actor = behavior.actor

    def policy(state: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return actor(TensorDict({"state": state, "belief": belief}, state.shape[:-1]))["action"]

    train = cfg.train
    return ExactModelLearner(
        actor_loss=behavior.losses.actor_loss,
        value_loss=behavior.losses.value_loss,
        optimizers=make_dreamer_v3_optimizers(
            behavior.parameter_groups(),
            rates={"actor": train.actor_lr, "value": train.value_lr},
            settings=settings,
        ),
        grad_clip=math.inf,
        target_updater=behavior.losses.target_updater,
        policy=policy,
        start_keys=("state", "belief"),
    )
