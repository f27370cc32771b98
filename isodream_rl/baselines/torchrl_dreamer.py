"""``algo=torchrl_dreamer``: TorchRL's own Dreamer, composed as TorchRL's Dreamer example, at our model sizes.

What a TorchRL user would train instead of Iso-Dream: ``ObsEncoder``/``ObsDecoder``, ``RSSMPrior``/``RSSMPosterior``
in a ``WorldModelWrapper`` trained by ``DreamerModelLoss``; ``DreamerActor`` (``TanhNormal``) trained by
``DreamerActorLoss`` through imagination in a ``DreamerEnv``; an MLP value trained by ``DreamerValueLoss``; an
acting policy filtering the observations with the posterior plus ``AdditiveGaussianModule`` noise. Same module
wiring, keys and heads (``IndependentNormal(scale=1)`` decoder, reward and value; ``TanhNormal`` actor) as
TorchRL's Dreamer example, with the widths of our size preset and the collector, replay buffer, evaluation and
budget of an Iso-Dream run.

Local pieces, where TorchRL's did not fit:

- :class:`ResettingRSSMRollout`: ``RSSMRollout`` never resets its carried state, and our replay windows cross
  episode boundaries (marked by ``is_init``).
- :class:`TorchRLDreamerPolicy`: our envs give uint8 pixels and no ``ToTensorImage``; TorchRL's acting sequence
  neither resets at ``is_init`` nor writes ``("next", "state")``, and its posterior samples even in evaluation.
- :class:`TorchRLDreamerOptimizationStepper`: the example's training loop (three optimisers) is a script, not
  an ``OptimizationStepper``; it also turns our replay sample into what ``DreamerModelLoss`` reads.
- :class:`TorchRLDreamerComponents`: the interface of :class:`~isodream_rl.trainers.components.RunComponents`,
  registered as ``algo=torchrl_dreamer`` (:mod:`isodream_rl.trainers.registry`) when this module is imported.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import (
    InteractionType,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
)
from torch import nn
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type
from torchrl.modules import (
    MLP,
    AdditiveGaussianModule,
    DreamerActor,
    IndependentNormal,
    ObsDecoder,
    ObsEncoder,
    RSSMPosterior,
    RSSMPrior,
    RSSMRollout,
    SafeModule,
    SafeProbabilisticModule,
    SafeProbabilisticTensorDictSequential,
    SafeSequential,
    TanhNormal,
    WorldModelWrapper,
)
from torchrl.objectives import DreamerActorLoss, DreamerModelLoss, DreamerValueLoss
from torchrl.objectives.utils import ValueEstimators

from isodream_rl.baselines.common import BaselineComponents, preset_widths
from isodream_rl.modules.carried_state import CarriedStatePolicy
from isodream_rl.objectives.imagination_env import latent_dreamer_env
from isodream_rl.trainers.builders import make_adam
from isodream_rl.trainers.config import RunConfig
from isodream_rl.trainers.learners import model_fields_read, resolved
from isodream_rl.trainers.registry import register_algorithm
from isodream_rl.trainers.stepper import ZeroStateStepper

#: The size-preset fields this baseline reads (``SIZE_PRESETS`` merged with the ``model.<field>`` settings), from
#: its settings table.
SIZE_KEYS = tuple(name for name in model_fields_read("torchrl_dreamer") if name != "precision")
#: Std of the acting policy's additive Gaussian noise (TorchRL's example: ``networks.exploration_noise``).
EXPLORATION_NOISE = 0.3

_SAMPLING = (None, ExplorationType.RANDOM)


def dreamer_sizes(cfg: RunConfig) -> dict[str, int]:
    """Widths of the run's size preset, the ``model.<field>`` settings applied: ``depth`` (TorchRL's ``channels``),
    ``state_dim``, ``belief_dim`` (``rnn_hidden_dim``), ``hidden_dim``, ``units`` (reward MLP)."""
    return preset_widths(cfg, SIZE_KEYS)


# ---------------------------------------------------------------------------------------------- world model
class ResettingRSSMRollout(RSSMRollout):
    """TorchRL's ``RSSMRollout`` whose carried ``state``/``belief`` restart from zeros where ``reset_key`` is set.

    Over a ``[*B, T]`` tensordict, step ``t`` runs the prior on ``(state_t, belief_t, action_t)`` and the
    posterior on ``(("next", "belief"), ("next", "encoded_latents"))``; the posterior's ``("next", "state")`` and
    the prior's ``("next", "belief")`` become ``state_{t+1}``/``belief_{t+1}``, as in ``RSSMRollout``. Before each
    step, ``state_t`` and ``belief_t`` are zeroed where ``reset_key`` (``[*B, T, 1]`` bool) is ``True``: a new
    episode starts from the zero state the acting policy's primer gives at reset. The root ``state``/``belief``
    of the output are the (reset) values each step consumed. The input needs root ``state``/``belief`` at its first
    step (the rest are ignored); the loop is plain Python (no ``use_scan``/``compile_step``).

    Args:
        rssm_prior: ``TensorDictModule`` of an ``RSSMPrior`` (keys as in ``RSSMRollout``).
        rssm_posterior: ``TensorDictModule`` of an ``RSSMPosterior``.
        reset_key: ``[*B, T, 1]`` bool marking the steps whose observation starts an episode. Defaults to
            ``"is_init"``; a missing key resets nothing.
    """

    def __init__(
        self, rssm_prior: TensorDictModule, rssm_posterior: TensorDictModule, *, reset_key: str = "is_init"
    ) -> None:
        super().__init__(rssm_prior, rssm_posterior)
        self.reset_key = reset_key
        if reset_key not in self.in_keys:
            self.in_keys = [*self.in_keys, reset_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        steps = tensordict.exclude(*self.out_keys).unbind(-1)
        output_keys = list(steps[0].keys(include_nested=True, leaves_only=True)) + list(self.out_keys)
        state, belief = steps[0].get("state"), steps[0].get("belief")
        outputs = []
        for step in steps:
            reset = step.get(self.reset_key, None)
            if reset is not None:
                reset = reset.bool()
                state, belief = state.masked_fill(reset, 0.0), belief.masked_fill(reset, 0.0)
            step.set("state", state)
            step.set("belief", belief)
            self._step(step)
            outputs.append(step.select(*output_keys, strict=False))
            state, belief = step.get(("next", "state")), step.get(("next", "belief"))
        return torch.stack(outputs, tensordict.ndim - 1)


def _world_model(
    *, encoder: nn.Module, decoder: nn.Module, prior: RSSMPrior, posterior: RSSMPosterior, reward: nn.Module
) -> WorldModelWrapper:
    """The example's world model (``WorldModelWrapper``), with :class:`ResettingRSSMRollout` for ``RSSMRollout``."""
    rollout = ResettingRSSMRollout(
        TensorDictModule(
            prior,
            in_keys={"state": "state", "belief": "belief", "action": "action", "noise": "prior_noise"},
            out_keys=[("next", "prior_mean"), ("next", "prior_std"), "_", ("next", "belief")],
            out_to_in_map=True,
        ),
        TensorDictModule(
            posterior,
            in_keys={
                "belief": ("next", "belief"),
                "obs_embedding": ("next", "encoded_latents"),
                "noise": "posterior_noise",
            },
            out_keys=[("next", "posterior_mean"), ("next", "posterior_std"), ("next", "state")],
            out_to_in_map=True,
        ),
    )
    decoder_head = ProbabilisticTensorDictSequential(
        TensorDictModule(decoder, in_keys=[("next", "state"), ("next", "belief")], out_keys=["loc"]),
        ProbabilisticTensorDictModule(
            in_keys=["loc"],
            out_keys=[("next", "reco_pixels")],
            distribution_class=IndependentNormal,
            distribution_kwargs={"scale": 1.0, "event_dim": 3},
        ),
    )
    transition = TensorDictSequential(
        TensorDictModule(encoder, in_keys=[("next", "pixels")], out_keys=[("next", "encoded_latents")]),
        rollout,
        decoder_head,
    )
    reward_head = ProbabilisticTensorDictSequential(
        TensorDictModule(reward, in_keys=[("next", "state"), ("next", "belief")], out_keys=[("next", "loc")]),
        ProbabilisticTensorDictModule(
            in_keys=[("next", "loc")],
            out_keys=[("next", "reward")],
            distribution_class=IndependentNormal,
            distribution_kwargs={"scale": 1.0, "event_dim": 1},
        ),
    )
    return WorldModelWrapper(transition, reward_head)


def _model_based_env(
    *, prior: RSSMPrior, reward: nn.Module, action_spec: Bounded, state_dim: int, belief_dim: int, device
) -> DreamerEnv:
    """The example's imagination env (``DreamerEnv``, no decoder), its specs set by
    :func:`~isodream_rl.objectives.imagination_env.latent_dreamer_env`."""
    transition = SafeSequential(
        SafeModule(prior, in_keys=["state", "belief", "action"], out_keys=["_", "_", "state", "belief"])
    )
    reward_head = SafeProbabilisticTensorDictSequential(
        SafeModule(reward, in_keys=["state", "belief"], out_keys=["loc"]),
        SafeProbabilisticModule(
            in_keys=["loc"],
            out_keys=["reward"],
            distribution_class=IndependentNormal,
            distribution_kwargs={"scale": 1.0, "event_dim": 1},
        ),
    )
    return latent_dreamer_env(
        WorldModelWrapper(transition, reward_head),
        action_spec=action_spec,
        state_dim=state_dim,
        belief_dim=belief_dim,
        device=device,
    )


# ---------------------------------------------------------------------------------------------- behaviour
class TorchRLDreamerPolicy(CarriedStatePolicy):
    """Acting policy around TorchRL's Dreamer acting sequence (the example's ``actor_realworld`` + noise).

    ``module`` is a ``TensorDictSequential``: ``ObsEncoder`` (float ``"pixels"`` -> ``"encoded_latents"``),
    ``RSSMPosterior`` (``"belief"``, ``"encoded_latents"`` -> ``"state"``), ``DreamerActor`` + ``TanhNormal``
    (-> ``"action"``), ``RSSMPrior`` (-> ``("next", "belief")``), then ``AdditiveGaussianModule``. This wrapper
    (a :class:`~isodream_rl.modules.isodream_v2.policy.CarriedStatePolicy`, carrying ``"state"``/``"belief"``) feeds it and
    keeps the env's tensordict clean:

    - uint8 ``"pixels"`` ``[*B, 3, 64, 64]`` become floats in [0, 1] (TorchRL's example: ``ToTensorImage``);
    - the carried ``"state"``/``"belief"`` restart from zeros where ``"is_init"``;
    - under exploration type ``RANDOM`` (or unset) the actor samples and the noise is added, as the example's
      collector (which sets ``RANDOM``) acts; under ``DETERMINISTIC``/``MODE``/``MEAN`` (evaluation) the actor
      gives ``tanh(loc)``, no noise is added, and the posterior gives its mean (``RSSMPosterior``'s
      ``noise`` argument set to zeros), so evaluation is deterministic; as in the example, the prior advances the
      belief with the actor's action from before the noise is added (the env gets the noisy one);
    - only ``"action"`` (in [-1, 1]) and the next recurrent state ``("next", "state")``,
      ``("next", "belief")`` are written, following TorchRL's recurrent convention; prime the env with
      :meth:`make_tensordict_primer` (as TorchRL's example primes its env).

    Runs without gradients, on the device of ``module``'s parameters; any batch shape (or none).

    Args:
        module: the acting sequence described above.
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        pixels_key: the observation key. Defaults to ``"pixels"``.
        action_key: where the action is written. Defaults to ``"action"``.
    """

    def __init__(
        self,
        module: TensorDictModuleBase,
        *,
        state_dim: int,
        belief_dim: int,
        pixels_key: str = "pixels",
        action_key: str = "action",
    ) -> None:
        super().__init__(
            module,
            widths={"state": state_dim, "belief": belief_dim},
            pixels_key=pixels_key,
            action_key=action_key,
        )
        self.state_dim, self.belief_dim = state_dim, belief_dim

    def act(
        self, pixels: torch.Tensor, carried: dict[str, torch.Tensor], reset: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """The acting sequence on float pixels, the carried state zeroed where ``reset``; the posterior's mean
        outside exploration."""
        if reset is not None:
            carried = {k: v.masked_fill(reset, 0.0) for k, v in carried.items()}
        work = TensorDict(
            {"pixels": pixels.float().div(255), **carried}, batch_size=[pixels.shape[0]], device=pixels.device
        )
        if exploration_type() not in _SAMPLING:
            work.set("posterior_noise", torch.zeros_like(carried["state"]))
        self.module(work)
        return {
            self.action_key: work.get(self.action_key),
            "state": work.get("state"),
            "belief": work.get(("next", "belief")),
        }


def _tanh_normal_actor(actor: DreamerActor, action_spec: Bounded) -> SafeProbabilisticTensorDictSequential:
    """The example's actor head: ``DreamerActor`` on ``"state"``, ``"belief"`` -> ``"loc"``, ``"scale"`` ->
    ``TanhNormal(tanh_loc=True)`` ``"action"``, sampled by default (``InteractionType.RANDOM``)."""
    loc_scale = Composite(loc=Unbounded(action_spec.shape), scale=Unbounded(action_spec.shape))
    return SafeProbabilisticTensorDictSequential(
        SafeModule(actor, in_keys=["state", "belief"], out_keys=["loc", "scale"], spec=loc_scale),
        SafeProbabilisticModule(
            in_keys=["loc", "scale"],
            out_keys=["action"],
            default_interaction_type=InteractionType.RANDOM,
            distribution_class=TanhNormal,
            distribution_kwargs={"tanh_loc": True},
            spec=Composite(action=action_spec.clone().cpu()),
        ),
    )


def _acting_sequence(
    *,
    encoder: nn.Module,
    posterior: RSSMPosterior,
    actor: DreamerActor,
    prior: RSSMPrior,
    action_spec: Bounded,
    exploration_noise: float,
    device,
) -> TensorDictSequential:
    """The example's real-world actor (encoder, posterior, actor, prior) followed by its ``AdditiveGaussianModule``.

    Two changes: the actor's default interaction is ``RANDOM`` (the example's collector sets ``RANDOM`` anyway;
    this makes an unset exploration type act the same), and the posterior reads ``"posterior_noise"`` (as the
    example's world model does) so that :class:`TorchRLDreamerPolicy` can take its mean.
    """
    real_world = SafeSequential(
        SafeModule(encoder, in_keys=["pixels"], out_keys=["encoded_latents"]),
        TensorDictModule(
            posterior,
            in_keys={"belief": "belief", "obs_embedding": "encoded_latents", "noise": "posterior_noise"},
            out_keys=["_", "_", "state"],
            out_to_in_map=True,
        ),
        _tanh_normal_actor(actor, action_spec),
        SafeModule(
            prior, in_keys=["state", "belief", "action"], out_keys=["_", "_", "_", ("next", "belief")]
        ),
    )
    return TensorDictSequential(
        real_world,
        AdditiveGaussianModule(
            spec=action_spec,
            sigma_init=1.0,
            sigma_end=1.0,
            annealing_num_steps=1,
            mean=0.0,
            std=exploration_noise,
            device=device,
        ),
    )


@dataclass
class TorchRLDreamerBehavior:
    """The behaviour side: actor (``actor_simulator`` of the example), value, imagination env, losses, policy."""

    actor: ProbabilisticTensorDictSequential
    value: ProbabilisticTensorDictSequential
    model_based_env: DreamerEnv
    actor_loss: DreamerActorLoss
    value_loss: DreamerValueLoss
    policy: TorchRLDreamerPolicy


def _rssm_parts(
    action_spec: Bounded, *, depth: int, state_dim: int, belief_dim: int, hidden_dim: int, device
) -> tuple[ObsEncoder, ObsDecoder, RSSMPrior, RSSMPosterior]:
    """TorchRL's Dreamer encoder, decoder, prior and posterior at the given widths (:func:`make_torchrl_dreamer`)."""
    encoder = ObsEncoder(channels=depth, num_layers=4, in_channels=3, device=device)
    decoder = ObsDecoder(
        channels=depth, num_layers=4, latent_dim=state_dim + belief_dim, out_channels=3, device=device
    )
    prior = RSSMPrior(
        action_spec,
        hidden_dim=hidden_dim,
        rnn_hidden_dim=belief_dim,
        state_dim=state_dim,
        action_dim=action_spec.shape[-1],
        device=device,
    )
    posterior = RSSMPosterior(
        hidden_dim=hidden_dim,
        state_dim=state_dim,
        rnn_hidden_dim=belief_dim,
        obs_embed_dim=32 * depth,
        device=device,
    )
    return encoder, decoder, prior, posterior


def _normal_value(*, latent_dim: int, units: int, device) -> ProbabilisticTensorDictSequential:
    """The value of TorchRL's Dreamer example: a 3-layer ``units``-wide ELU MLP on ``[state, belief]`` with an
    ``IndependentNormal(scale=1)`` head."""
    return ProbabilisticTensorDictSequential(
        TensorDictModule(
            MLP(
                in_features=latent_dim,
                out_features=1,
                depth=3,
                num_cells=units,
                activation_class=nn.ELU,
                device=device,
            ),
            in_keys=["state", "belief"],
            out_keys=["loc"],
        ),
        ProbabilisticTensorDictModule(
            in_keys=["loc"],
            out_keys=["state_value"],
            distribution_class=IndependentNormal,
            distribution_kwargs={"scale": 1.0, "event_dim": 1},
        ),
    )


def _behavior(
    *,
    actor_module: nn.Module,
    actor: ProbabilisticTensorDictSequential,
    value: ProbabilisticTensorDictSequential,
    model_based_env: DreamerEnv,
    encoder: nn.Module,
    posterior: RSSMPosterior,
    prior: RSSMPrior,
    action_spec: Bounded,
    horizon: int,
    gamma: float,
    lmbda: float,
    exploration_noise: float,
    state_dim: int,
    belief_dim: int,
    device,
) -> TorchRLDreamerBehavior:
    """The behaviour side of :func:`make_torchrl_dreamer` (same arguments): the actor and value losses and the
    acting policy around the encoder, posterior, actor and prior."""
    # DreamerActor's MLP is lazy: one dry pass sizes it before the optimisers collect the parameters.
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        probe = TensorDict(
            {"state": torch.zeros(1, state_dim), "belief": torch.zeros(1, belief_dim)}, [1], device=device
        )
        value(actor(probe))

    actor_loss = DreamerActorLoss(
        actor, value, model_based_env, imagination_horizon=horizon, discount_loss=True
    )
    actor_loss.make_value_estimator(ValueEstimators.TDLambda, gamma=gamma, lmbda=lmbda)
    value_loss = DreamerValueLoss(value, discount_loss=True, gamma=gamma)
    policy = TorchRLDreamerPolicy(
        _acting_sequence(
            encoder=encoder,
            posterior=posterior,
            actor=actor_module,
            prior=prior,
            action_spec=action_spec,
            exploration_noise=exploration_noise,
            device=device,
        ),
        state_dim=state_dim,
        belief_dim=belief_dim,
    )
    return TorchRLDreamerBehavior(
        actor=actor,
        value=value,
        model_based_env=model_based_env,
        actor_loss=actor_loss,
        value_loss=value_loss,
        policy=policy,
    )


def make_torchrl_dreamer(
    *,
    action_dim: int,
    depth: int,
    state_dim: int,
    belief_dim: int,
    hidden_dim: int,
    units: int,
    actor_units: int,
    value_units: int,
    horizon: int = 15,
    gamma: float = 0.99,
    lmbda: float = 0.95,
    lambda_reward: float = 1.0,
    free_nats: float = 3.0,
    exploration_noise: float = EXPLORATION_NOISE,
    device: str | torch.device = "cpu",
) -> tuple[DreamerModelLoss, TorchRLDreamerBehavior]:
    """TorchRL's Dreamer modules and losses as its example builds them, at the given widths.

    World model: ``ObsEncoder(channels=depth)`` on ``("next", "pixels")`` (float, [0, 1]) -> ``RSSMPrior``/
    ``RSSMPosterior`` (``hidden_dim``, ``belief_dim``, ``state_dim``) in a :class:`ResettingRSSMRollout` ->
    ``ObsDecoder(channels=depth)`` and a 2-layer ``units``-wide ELU reward MLP, both ``IndependentNormal
    (scale=1)`` heads, in a ``WorldModelWrapper`` trained by ``DreamerModelLoss``. Imagination: a
    ``DreamerEnv`` on the same prior and reward MLP. Actor: ``DreamerActor(depth=3, num_cells=actor_units)``
    with ``TanhNormal(tanh_loc=True)``; value: 3-layer ``value_units``-wide ELU MLP with an
    ``IndependentNormal(scale=1)`` head; ``DreamerActorLoss`` (TD(lambda) estimator, discounted) and
    ``DreamerValueLoss`` (discounted).

    Args:
        action_dim: width of the action (in [-1, 1]).
        depth: channels of the first convolution (TorchRL's ``channels``).
        state_dim: width of the stochastic state.
        belief_dim: width of the GRU state (TorchRL's ``rnn_hidden_dim``).
        hidden_dim: width of the RSSM's hidden layers.
        units: width of the reward MLP.
        actor_units: width of the actor MLP.
        value_units: width of the value MLP.
        horizon: imagination horizon.
        gamma: discount of the lambda-returns (and of the value loss).
        lmbda: lambda of the lambda-returns.
        lambda_reward: weight of the reward loss.
        free_nats: free nats of the KL.
        exploration_noise: std of the acting policy's additive Gaussian noise.
        device: where the modules live.

    Returns:
        ``(model_loss, behavior)``; ``model_loss.world_model`` is the ``WorldModelWrapper``.
    """
    action_spec = Bounded(-1.0, 1.0, (action_dim,), device=device)
    widths = {"depth": depth, "state_dim": state_dim, "belief_dim": belief_dim, "hidden_dim": hidden_dim}
    encoder, decoder, prior, posterior = _rssm_parts(action_spec, **widths, device=device)
    latent_dim = state_dim + belief_dim
    reward = MLP(
        in_features=latent_dim,
        out_features=1,
        depth=2,
        num_cells=units,
        activation_class=nn.ELU,
        device=device,
    )
    world_model = _world_model(
        encoder=encoder, decoder=decoder, prior=prior, posterior=posterior, reward=reward
    )
    model_loss = DreamerModelLoss(world_model, lambda_reward=lambda_reward, free_nats=free_nats)

    model_based_env = _model_based_env(
        prior=prior,
        reward=reward,
        action_spec=action_spec,
        state_dim=state_dim,
        belief_dim=belief_dim,
        device=device,
    )
    actor_module = DreamerActor(
        out_features=action_dim, depth=3, num_cells=actor_units, activation_class=nn.ELU, device=device
    )
    actor = _tanh_normal_actor(actor_module, action_spec)
    value = _normal_value(latent_dim=latent_dim, units=value_units, device=device)
    behavior = _behavior(
        actor_module=actor_module,
        actor=actor,
        value=value,
        model_based_env=model_based_env,
        encoder=encoder,
        posterior=posterior,
        prior=prior,
        action_spec=action_spec,
        horizon=horizon,
        gamma=gamma,
        lmbda=lmbda,
        exploration_noise=exploration_noise,
        state_dim=state_dim,
        belief_dim=belief_dim,
        device=device,
    )
    return model_loss, behavior


# ---------------------------------------------------------------------------------------------- optimisation
class TorchRLDreamerOptimizationStepper(ZeroStateStepper):
    """One update of TorchRL's Dreamer example's training loop, as a TorchRL ``OptimizationStepper``.

    Per :meth:`step` on a flat ``[B * T]`` replay sample (``"action"``, ``"is_init"``, uint8
    ``("next", "pixels")``, ``("next", "reward")``):

    1. :meth:`prepare` (:class:`~isodream_rl.trainers.stepper.ZeroStateStepper`), on the model's device: pixels to
       floats in [0, 1] (the example's ``ToTensorImage``), zero ``"state"``/``"belief"`` (the example's primer
       values); reshaped to windows ``[B, T]``;
    2. ``DreamerModelLoss`` -> backward of ``kl + reco + reward`` -> clip -> world-model Adam step;
    3. ``DreamerActorLoss`` on the world-model output flattened to ``[B * T]`` (imagination from the root
       ``state``/``belief`` each step consumed, as the example) -> backward -> clip -> actor Adam step;
    4. ``DreamerValueLoss`` on the (detached) imagined rollout -> backward -> clip -> value Adam step.

    The world-model and value losses run under ``DETERMINISTIC`` exploration (the decoder, reward and value
    heads give their means: what the example gets with no exploration type set); the actor loss sets
    ``RANDOM`` itself, so its imagined rewards and next values are samples of the unit-variance heads, as in
    the example (an additive noise: the actor's gradient is that of the means). Gradient clipping, non-finite
    skipping (an update stops at its first non-finite loss or gradient norm; ``max_nonfinite`` in a row raise),
    counters, metric keys and checkpoint state are those of
    :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`.

    Args:
        model_loss: ``DreamerModelLoss``.
        actor_loss: ``DreamerActorLoss``.
        value_loss: ``DreamerValueLoss``.
        world_model_optimizer: optimiser of the world model.
        actor_optimizer: optimiser of the actor.
        value_optimizer: optimiser of the value network.
        sequence_length: T, the replay window length.
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        grad_clip: max gradient norm per optimiser.
        max_nonfinite: non-finite updates in a row that stop the run.
        autocast_dtype: ``torch.bfloat16`` to run the losses under autocast (the example's ``autocast``), or
            ``None``.
    """

    def __init__(
        self,
        *,
        model_loss: DreamerModelLoss,
        actor_loss: DreamerActorLoss,
        value_loss: DreamerValueLoss,
        world_model_optimizer: torch.optim.Optimizer,
        actor_optimizer: torch.optim.Optimizer,
        value_optimizer: torch.optim.Optimizer,
        sequence_length: int,
        state_dim: int,
        belief_dim: int,
        grad_clip: float = 100.0,
        max_nonfinite: int = 5,
        autocast_dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__(
            model_loss=model_loss,
            world_model_optimizer=world_model_optimizer,
            sequence_length=sequence_length,
            actor_loss=actor_loss,
            value_loss=value_loss,
            actor_optimizer=actor_optimizer,
            value_optimizer=value_optimizer,
            grad_clip=grad_clip,
            max_nonfinite=max_nonfinite,
            state_dim=state_dim,
            belief_dim=belief_dim,
        )
        self.autocast_dtype = autocast_dtype

    def loss_inputs(self, sub_batch: TensorDictBase) -> TensorDictBase:
        """What ``DreamerModelLoss`` reads of a flat ``[N]`` replay sample: ``"action"``, ``"is_init"`` ``[N, 1]``,
        ``("next", "pixels")`` float ``[N, 3, 64, 64]`` in [0, 1], ``("next", "reward")`` ``[N, 1]`` (:meth:`prepare`
        adds zero ``"state"``/``"belief"``: only each window's first step is read; the rollout carries its own
        state from there)."""
        return TensorDict(
            {
                "action": sub_batch.get("action").float(),
                "is_init": sub_batch.get("is_init").bool(),
                ("next", "pixels"): sub_batch.get(("next", "pixels")).float().div(255),
                ("next", "reward"): sub_batch.get(("next", "reward")).float(),
            },
            batch_size=[sub_batch.numel()],
        )

    def _autocast(self):
        if self.autocast_dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=self.autocast_dtype)

    @torch.no_grad()
    def _discover_keys(self, batch: TensorDictBase) -> None:
        """The metric names of a full update, from the three losses on a ``[1, 2]`` slice of the first batch
        (the actor loss reads flat starts: ``RSSMPrior``'s ``GRUCell`` takes at most one batch dimension)."""
        model_losses, model_out = self.model_loss(batch)
        actor_losses, imagined = self.actor_loss(model_out.reshape(-1))
        value_losses, _ = self.value_loss(imagined)
        self._metric_keys = [
            *model_losses.keys(),
            "grad_norm_world_model",
            *actor_losses.keys(),
            "grad_norm_actor",
            *value_losses.keys(),
            "grad_norm_value",
            "nonfinite_skipped",
        ]

    def _update(self, name: str, loss: torch.Tensor, metrics: dict[str, torch.Tensor]) -> bool:
        return self._backward(loss, [name]) and self._clip_and_step([name], metrics)

    def _run(self, batch: TensorDictBase, metrics: dict[str, torch.Tensor]) -> bool:
        with self._autocast(), set_exploration_type(ExplorationType.DETERMINISTIC):
            model_losses, model_out = self.model_loss(batch)
        metrics.update({k: v.detach().float() for k, v in model_losses.items()})
        model_total = sum(v for k, v in model_losses.items() if k.startswith("loss"))
        if not self._update("world_model", model_total.squeeze(), metrics):
            return False
        with self._autocast():
            actor_losses, imagined = self.actor_loss(model_out.reshape(-1))
        metrics.update({k: v.detach().float() for k, v in actor_losses.items()})
        if not self._update("actor", actor_losses["loss_actor"], metrics):
            return False
        with self._autocast(), set_exploration_type(ExplorationType.DETERMINISTIC):
            value_losses, _ = self.value_loss(imagined)
        metrics.update({k: v.detach().float() for k, v in value_losses.items()})
        return self._update("value", value_losses["loss_value"], metrics)


# ---------------------------------------------------------------------------------------------- run components
@register_algorithm("torchrl_dreamer")
class TorchRLDreamerComponents(BaselineComponents):
    """Models, losses, optimisers, stepper and replay buffer of an ``algo=torchrl_dreamer`` run.

    The interface of :class:`~isodream_rl.trainers.components.RunComponents` over TorchRL's Dreamer
    (:func:`make_torchrl_dreamer`): widths from ``SIZE_PRESETS[model.size]`` + ``model.<field>``,
    ``model.actor_units``/``value_units``; ``algo.horizon``, ``gamma``, ``lmbda``, ``lambda_reward``,
    ``free_nats``; ``train.*_lr``, ``adam_eps``, ``grad_clip``, ``max_nonfinite_updates``, ``device``;
    ``model.precision: bf16`` runs the losses under bf16 autocast. The replay buffer, its preparation
    hook and the episode-return hook are the Iso-Dream run's.

    Args:
        cfg: the run configuration.
        action_dim: width of the env's action.
        scratch_dir: folder of the replay buffer's memmap files.
        exploration_noise: std of the acting policy's additive Gaussian noise (TorchRL's example: 0.3).

    Attributes:
        model_loss (DreamerModelLoss), world_model (``None``: no open-loop prediction in the evaluation),
        dreamer_world_model (the ``WorldModelWrapper``), behavior (:class:`TorchRLDreamerBehavior`), stepper
        (:class:`TorchRLDreamerOptimizationStepper`), replay_buffer, preparation, returns.
    """

    algo = "torchrl_dreamer"

    def __init__(
        self,
        cfg: RunConfig,
        *,
        action_dim: int,
        scratch_dir: Path,
        exploration_noise: float = EXPLORATION_NOISE,
    ) -> None:
        cfg = resolved(cfg)
        train, algo, model = cfg.train, cfg.algo, cfg.model
        sizes = dreamer_sizes(cfg)
        precision = model.precision or "fp32"
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"model.precision must be 'fp32' or 'bf16', got {precision!r}")
        self.model_loss, self.behavior = make_torchrl_dreamer(
            action_dim=action_dim,
            **sizes,
            actor_units=model.actor_units,
            value_units=model.value_units,
            horizon=algo.horizon,
            gamma=algo.gamma,
            lmbda=algo.lmbda,
            lambda_reward=algo.lambda_reward,
            free_nats=algo.free_nats,
            exploration_noise=exploration_noise,
            device=train.device,
        )
        self.dreamer_world_model = self.model_loss.world_model
        self.world_model = None
        self.stepper = TorchRLDreamerOptimizationStepper(
            model_loss=self.model_loss,
            actor_loss=self.behavior.actor_loss,
            value_loss=self.behavior.value_loss,
            world_model_optimizer=make_adam(
                self.dreamer_world_model.parameters(), lr=train.world_model_lr, eps=train.adam_eps
            ),
            actor_optimizer=make_adam(
                self.behavior.actor.parameters(), lr=train.actor_lr, eps=train.adam_eps
            ),
            value_optimizer=make_adam(
                self.behavior.value.parameters(), lr=train.value_lr, eps=train.adam_eps
            ),
            sequence_length=train.sequence_length,
            state_dim=sizes["state_dim"],
            belief_dim=sizes["belief_dim"],
            grad_clip=train.grad_clip,
            max_nonfinite=train.max_nonfinite_updates,
            autocast_dtype=torch.bfloat16 if precision == "bf16" else None,
        )
        self.set_replay_parts(cfg, scratch_dir=scratch_dir)

    def modules(self) -> dict[str, nn.Module]:
        """The trained modules, by checkpoint name (the policy, imagination env and losses share them)."""
        return {
            "world_model": self.dreamer_world_model,
            "actor": self.behavior.actor,
            "value": self.behavior.value,
        }
