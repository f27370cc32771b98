"""``algo=torchrl_dreamer_v3``: TorchRL's DreamerV3, composed as TorchRL's DreamerV3 reproduction, at our sizes.

The world-model agent a TorchRL user picks today (Hafner et al. 2023, https://arxiv.org/abs/2301.04104), through
the collector, ``SliceSampler`` replay, evaluation, checkpoints and ``summary.json`` of an Iso-Dream run:

- world model (``DreamerV3ModelLoss``): ``DreamerV3ImageEncoder`` on uint8 ``("next", "pixels")``,
  ``RSSMPriorV3`` (block GRU) / ``RSSMPosteriorV3`` (RMS-normed) with categorical latents in an
  ``RSSMRolloutV3`` that resets at ``is_init``, ``DreamerV3ImageDecoder``, a two-hot reward head
  (``DreamerV3MLP`` + ``SymExpTwoHot``) and a continuation head;
- behaviour: imagination in a ``DreamerEnv`` on the same prior and reward head, ``DreamerV3ActorLoss``
  (REINFORCE, percentile return normalisation in ``PercentileValueNorm``, entropy 3e-4, continuation-weighted
  lambda-returns), ``DreamerV3ValueLoss`` (two-hot critic, slow-critic regulariser with a ``SoftUpdate``
  target), the replay-value term of ``DreamerV3Loss``;
- ``DreamerV3Optimizer`` (adaptive gradient clipping, RMS-scaled momentum, linear warm-up) on the sum of all
  ``loss_*`` terms, one per parameter group (world model, actor, value): TorchRL's optimiser keeps one update
  counter per group and is otherwise per parameter, so this is the update of one optimiser with three groups,
  and it lets the world model train alone during ``train.world_model_warmup`` while the actor's and value's
  counters (bias correction, learning-rate warm-up) start when they do;
- acting: the encoder, ``RSSMStateEstimatorV3`` and the actor, with ``previous_action`` carried.

Widths. DreamerV3 scales with one knob, as its presets ``size1m`` ... ``size400m`` do: ``hidden`` (RSSM hidden
layers, reward and continuation heads), ``deter = 8 hidden`` (GRU state), 32 categoricals of ``hidden / 16``
classes, image depth ``hidden / 16``. Here ``hidden = 1.875 x`` our preset's ``hidden_dim`` (rounded to a
multiple of 8), fitted so that the DreamerV3 world model has as many parameters as Iso-Dream's three-branch
world model of the DreamerV2-style learner (``algo=isodream_v2``, sprites, 2 actions; ``isodream`` in the
update-speed JSONs measured before ``algo=isodream`` became DreamerV3's learner), at ``size=bench`` and
``size=small``: -1.5 % and +6.0 %.
Actor and value are ``model.actor_units`` / ``model.value_units`` wide, 3 hidden layers each, on
``[belief, state]`` (1216 features at bench, where DreamerV2's read 96): wider first layers than ours. Trained
parameters (world model / actor / value; the slow critic is not counted, Iso-Dream's value includes the
attention):

=========  ======  ==============================  =================================  ========================
size       hidden  torchrl_dreamer_v3              isodream_v2                        dreamerv2 world model
=========  ======  ==============================  =================================  ========================
``bench``  120     1.840 M / 0.190 M / 0.222 M     1.869 M / 0.062 M / 0.070 M        0.443 M
``small``  240     7.147 M / 0.748 M / 0.813 M     6.745 M / 0.240 M / 0.338 M        1.472 M
=========  ======  ==============================  =================================  ========================

``bench/update_speed.py`` writes these counts beside its timings; at ``tiny``, ``paper`` and ``quickstart`` the
rule gives 0.14 M, 17.6 M and 0.14 M world models (not fitted there).

DreamerV3's own settings are TorchRL's, as its DreamerV3 reproduction (``sota-implementations/dreamer_v3``) sets
them where a class default keeps an older behaviour for compatibility: unimix 0.01 (class default 0), separate
dynamics / representation KL with weights 1 / 0.1 and 1 free nat on their sum (class default ``"balanced"``),
REINFORCE (class default: reparameterised), a two-hot critic (class default: symlog MSE) with slow-critic
regularisation 1 and target rate 0.02 (class default 0), a continuation head trained to ``1 - 1/333`` with
``gamma = 1`` in the lambda-returns; symlog/two-hot reward with 255 bins, return normalisation (5th-95th
percentile, rate 0.01, floor 1), entropy 3e-4, lambda 0.95, replay-value weight 0.3, policy std in [0.1, 1],
zero-initialised reward and value outputs, actor outputs scaled by 0.01. All of them sit in
:class:`~isodream_rl.modules.dreamer_v3.DreamerV3Settings`.

Where this departs from TorchRL's settings, and why:

- learning rates: the run's ``train.world_model_lr`` / ``actor_lr`` / ``value_lr`` (one per parameter group)
  instead of DreamerV3's 4e-5 for all: the budget is the run's (a few thousand updates, where DreamerV3's
  rate is set for hundreds of thousands), as ``algo=torchrl_dreamer`` trains with the run's rates rather than
  TorchRL's Dreamer example's. The optimiser's own settings (clip 0.3, eps 1e-20, 1000-update warm-up) are
  TorchRL's (:data:`~isodream_rl.modules.dreamer_v3.TORCHRL_DREAMER_V3_SETTINGS`); ``train.adam_eps`` and
  ``train.grad_clip`` are refused (:func:`~isodream_rl.trainers.learners.unread_setting_errors`).
- discount: ``algo.gamma`` is refused; the continuation head's ``1 - 1/333`` discounts, as in DreamerV3.
- actions: the acting policy clamps its sample to [-1, 1], where TorchRL's reproduction clips in the env and
  stores the raw sample; the world model sees the same either way (``RSSMPriorV3``'s block GRU divides an
  action by ``max(|a|, 1)``).
- widths (above), and fp32 only (``model.precision=bf16`` is refused: TorchRL's DreamerV3 autocasts on
  CUDA only).

Local pieces, where TorchRL's did not fit (those Iso-Dream's DreamerV3 learner shares live in the lower layers):

- :class:`~isodream_rl.modules.dreamer_v3.DreamerV3ContinuousActor`: TorchRL ships DreamerV3's discrete actor only
  (``DreamerV3DiscreteActor``); this is its reproduction's bounded-normal actor, built from ``DreamerV3MLP``.
- :class:`~isodream_rl.modules.dreamer_v3.WindowInputCheck`: the one-line errors the other algos give on a bad
  batch (pixel range, NaN, no ``is_init``, one-step windows), as the world model's first module.
- :class:`TorchRLDreamerV3Policy`: our envs carry the recurrent state under TorchRL's ``("next", ...)``
  convention through a primer, and evaluation reads ``make_tensordict_primer``; it wraps TorchRL's acting
  sequence (which it runs unchanged).
- :class:`~isodream_rl.trainers.dreamer_v3.DreamerV3OptimizationStepper`: TorchRL's
  ``DreamerV3OptimizationStepper`` has no skipping of non-finite updates, no update counter and no fixed metric
  keys, which the run's hooks and checkpoints read; this one runs the same loss, optimiser and target update
  inside :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`, on the optimisers of
  :func:`~isodream_rl.trainers.dreamer_v3.make_dreamer_v3_optimizers`.
- :class:`TorchRLDreamerV3Components`: the interface of :class:`~isodream_rl.trainers.components.RunComponents`,
  registered as ``algo=torchrl_dreamer_v3`` (:mod:`isodream_rl.trainers.registry`) when this module is imported.

Composing it found no bug in TorchRL 0.14.1's DreamerV3 classes that needed a local fix. Two behaviours to know:
``RSSMRolloutV3`` zeroes state, belief and the transition's action where ``is_init`` is set, so a window (or an
episode) starts one step later than the acting ``RSSMStateEstimatorV3`` starts it (Iso-Dream's filter resets the
same way, docs/concepts.md); ``DreamerV3Optimizer`` counts updates per parameter group, so a group that joins late
must be its own optimiser (above).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict.nn import (
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
)
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.modules import (
    DreamerV3ImageDecoder,
    DreamerV3ImageEncoder,
    DreamerV3MLP,
    RSSMPosteriorV3,
    RSSMPriorV3,
    RSSMRolloutV3,
    RSSMStateEstimatorV3,
    SymExpTwoHot,
    WorldModelWrapper,
)
from torchrl.objectives import DreamerV3ActorLoss, DreamerV3Loss, DreamerV3ModelLoss, DreamerV3ValueLoss
from torchrl.objectives.utils import SoftUpdate

from isodream_rl.baselines.common import BaselineComponents, preset_widths
from isodream_rl.modules.dreamer_v3 import (
    PIXELS,
    TORCHRL_DREAMER_V3_SETTINGS,
    DreamerV3ContinuousActor,
    DreamerV3Settings,
    SequenceActingPolicy,
    WindowInputCheck,
    bounded_normal_actor,
    continuation_probability,
    two_hot_value,
)
from isodream_rl.modules.isodream.world_model import BranchWidths, dreamer_v3_classes, make_rssm
from isodream_rl.objectives.dreamer_v3_behavior import (
    dreamer_v3_model_loss_settings,
    make_dreamer_v3_behavior,
    make_dreamer_v3_loss,
)
from isodream_rl.objectives.imagination_env import latent_dreamer_env
from isodream_rl.trainers.config import ConfigError, RunConfig
from isodream_rl.trainers.dreamer_v3 import dreamer_v3_checkpoint_modules, make_dreamer_v3_stepper
from isodream_rl.trainers.learners import model_fields_read
from isodream_rl.trainers.registry import register_algorithm

#: ``hidden`` of DreamerV3's size rule per unit of our preset's ``hidden_dim`` (fitted to Iso-Dream's counts).
HIDDEN_PER_HIDDEN_DIM = 1.875
#: The size-preset field this baseline reads (``SIZE_PRESETS`` merged with the ``model.<field>`` settings), from
#: its settings table.
SIZE_KEYS = tuple(name for name in model_fields_read("torchrl_dreamer_v3") if name != "precision")


@dataclass(frozen=True)
class DreamerV3Widths:
    """Widths of DreamerV3's size rule (one knob, ``hidden``) and of the actor and value MLPs."""

    hidden: int
    """RSSM hidden layers, reward and continuation heads (DreamerV3's ``rssm.hidden`` and ``units``)."""
    actor_units: int
    """Width of the actor's 3 hidden layers."""
    value_units: int
    """Width of the value's 3 hidden layers."""

    @property
    def deter(self) -> int:
        """GRU state width (``belief``)."""
        return 8 * self.hidden

    @property
    def classes(self) -> int:
        """Classes of each categorical, also the image encoder's base depth (:func:`dreamer_v3_classes`)."""
        return dreamer_v3_classes(self.hidden)

    def state_dim(self, settings: DreamerV3Settings) -> int:
        """Width of the one-hot ``state``: categoricals x classes."""
        return settings.num_categoricals * self.classes

    @classmethod
    def from_run(cls, cfg: RunConfig) -> DreamerV3Widths:
        """The widths for ``cfg``'s size preset (the ``model.<field>`` settings applied) and actor / value units.

        Raises:
            ValueError: an unknown size preset.
            ConfigError: a precision other than fp32.
        """
        hidden_dim = preset_widths(cfg, SIZE_KEYS)["hidden_dim"]
        precision = cfg.model.precision or "fp32"
        if precision != "fp32":
            raise ConfigError(
                f"invalid training configuration: algo=torchrl_dreamer_v3 trains in fp32 only (TorchRL's DreamerV3 "
                f"autocasts on CUDA only), got model.precision={precision!r}: drop the override"
            )
        hidden = 8 * max(1, round(HIDDEN_PER_HIDDEN_DIM * hidden_dim / 8))
        return cls(hidden=hidden, actor_units=cfg.model.actor_units, value_units=cfg.model.value_units)


# ---------------------------------------------------------------------------------------------- world model
@dataclass
class DreamerV3Parts:
    """The networks, shared by the world model, imagination, the losses and the acting policy."""

    encoder: DreamerV3ImageEncoder
    prior: RSSMPriorV3
    posterior: RSSMPosteriorV3
    decoder: DreamerV3ImageDecoder
    reward: DreamerV3MLP
    continuation: DreamerV3MLP


def _parts(
    *, action_dim: int, widths: DreamerV3Widths, settings: DreamerV3Settings, device
) -> DreamerV3Parts:
    depth, hidden, deter = widths.classes, widths.hidden, widths.deter
    latent = widths.state_dim(settings) + deter
    encoder = DreamerV3ImageEncoder(depth=depth, device=device)
    prior, posterior = make_rssm(
        BranchWidths(hidden, settings.num_categoricals, widths.classes),
        action_dim=action_dim,
        embed_dim=encoder.output_features((3, 64, 64)),
        settings=settings,
        device=device,
    )
    return DreamerV3Parts(
        encoder=encoder,
        prior=prior,
        posterior=posterior,
        decoder=DreamerV3ImageDecoder(latent, depth=depth, num_blocks=settings.num_blocks, device=device),
        reward=DreamerV3MLP(
            latent, settings.num_bins, depth=1, num_cells=hidden, outscale=0.0, device=device
        ),
        continuation=DreamerV3MLP(latent, 1, depth=1, num_cells=hidden, device=device),
    )


def _next(key: str) -> tuple[str, str]:
    return ("next", key)


def _world_model(parts: DreamerV3Parts, *, action_dim: int, num_bins: int) -> TensorDictSequential:
    """Input check, encoder, RSSM rollout (reset at ``is_init``), decoder, reward and continuation heads."""
    return TensorDictSequential(
        WindowInputCheck(action_dim=action_dim),
        TensorDictModule(parts.encoder, in_keys=[PIXELS], out_keys=[_next("encoded_latents")]),
        RSSMRolloutV3(
            TensorDictModule(
                parts.prior,
                in_keys=["state", "belief", "action"],
                out_keys=[_next("prior_logits"), _next("state"), _next("belief")],
            ),
            TensorDictModule(
                parts.posterior,
                in_keys=[_next("belief"), _next("encoded_latents")],
                out_keys=[_next("posterior_logits"), _next("state")],
            ),
            reset_key="is_init",
        ),
        TensorDictModule(
            parts.decoder, in_keys=[_next("state"), _next("belief")], out_keys=[_next("reco_pixels")]
        ),
        TensorDictModule(
            parts.reward, in_keys=[_next("belief"), _next("state")], out_keys=[_next("reward_logits")]
        ),
        TensorDictModule(
            SymExpTwoHot(num_bins), in_keys=[_next("reward_logits")], out_keys=[_next("reward")]
        ),
        TensorDictModule(
            parts.continuation, in_keys=[_next("belief"), _next("state")], out_keys=[_next("continue_pred")]
        ),
    )


def _model_based_env(
    parts: DreamerV3Parts, *, action_dim: int, state_dim: int, belief_dim: int, num_bins: int, device
) -> DreamerEnv:
    """Imagination: the prior steps ``state``/``belief``, the reward head gives the (decoded) reward; the specs
    set by :func:`~isodream_rl.objectives.imagination_env.latent_dreamer_env`."""
    return latent_dreamer_env(
        WorldModelWrapper(
            TensorDictModule(
                parts.prior, in_keys=["state", "belief", "action"], out_keys=["_", "state", "belief"]
            ),
            TensorDictSequential(
                TensorDictModule(parts.reward, in_keys=["belief", "state"], out_keys=["reward_logits"]),
                TensorDictModule(SymExpTwoHot(num_bins), in_keys=["reward_logits"], out_keys=["reward"]),
            ),
        ),
        action_spec=Bounded(-1.0, 1.0, (action_dim,), device=device),
        state_dim=state_dim,
        belief_dim=belief_dim,
        device=device,
    )


# ---------------------------------------------------------------------------------------------- behaviour
def _actor(*, latent: int, action_dim: int, units: int, settings: DreamerV3Settings, device):
    net = DreamerV3ContinuousActor(
        latent,
        action_dim,
        num_cells=units,
        min_std=settings.policy_min_std,
        max_std=settings.policy_max_std,
        device=device,
    )
    return bounded_normal_actor(TensorDictModule(net, in_keys=["belief", "state"], out_keys=["loc", "scale"]))


def _value(*, latent: int, units: int, num_bins: int, device) -> TensorDictSequential:
    net = DreamerV3MLP(latent, num_bins, depth=3, num_cells=units, outscale=0.0, device=device)
    return two_hot_value(net, in_keys=["belief", "state"], num_bins=num_bins)


class TorchRLDreamerV3Policy(SequenceActingPolicy):
    """Acting policy around TorchRL's DreamerV3 acting sequence (encoder, ``RSSMStateEstimatorV3``, actor).

    At each env step: ``DreamerV3ImageEncoder`` on uint8 ``"pixels"`` ``[*B, 3, 64, 64]``;
    ``RSSMStateEstimatorV3`` advances ``belief`` from the carried ``state``, ``belief`` and ``previous_action``
    (all zeroed where ``"is_init"``) and samples the posterior ``state``; the actor samples the action (exploration
    type ``RANDOM`` or unset) or gives ``tanh(mean)`` (``DETERMINISTIC``/``MODE``/``MEAN``, e.g. evaluation), clamped
    to [-1, 1]. The posterior samples its categoricals in both cases, as TorchRL's estimator does.

    Writes ``"action"`` and, following TorchRL's recurrent convention, ``("next", "state")``, ``("next",
    "belief")`` and ``("next", "previous_action")``; prime the env with :meth:`make_tensordict_primer` (a
    :class:`~isodream_rl.modules.dreamer_v3.SequenceActingPolicy`). Runs without gradients, on the device of
    ``module``'s parameters; any batch shape (or none).

    Args:
        module: the acting sequence described above (reads ``"pixels"``, ``"is_init"`` and the carried keys;
            writes ``"state"``, ``"belief"``, ``"action"``).
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        action_dim: width of ``"action"``.
        pixels_key: the observation key. Defaults to ``"pixels"``.
        action_key: where the action is written. Defaults to ``"action"``.
    """


@dataclass
class TorchRLDreamerV3Learner:
    """TorchRL's DreamerV3 learner: networks, losses, slow-critic updater, imagination env and acting policy."""

    world_model: TensorDictSequential
    actor: ProbabilisticTensorDictSequential
    value: TensorDictSequential
    model_based_env: DreamerEnv
    model_loss: DreamerV3ModelLoss
    actor_loss: DreamerV3ActorLoss
    value_loss: DreamerV3ValueLoss
    loss_module: DreamerV3Loss
    target_updater: SoftUpdate
    policy: TorchRLDreamerV3Policy

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The trained parameters, each once: ``world_model``, ``actor``, ``value`` (not its slow copy)."""
        return {
            "world_model": list(self.world_model.parameters()),
            "actor": list(self.actor.parameters()),
            "value": list(self.value_loss.parameters()),
        }


def dreamer_v3_model_loss(
    world_model: TensorDictModuleBase, *, settings: DreamerV3Settings = TORCHRL_DREAMER_V3_SETTINGS
) -> DreamerV3ModelLoss:
    """``DreamerV3ModelLoss`` as TorchRL's reproduction configures it for pixels: separate dynamics and
    representation KL, squared error on ``pixels / 255`` (no symlog), two-hot reward, continuation trained to
    ``1 - 1 / continuation_horizon``; the output keeps its graph for the replay-value term."""
    return DreamerV3ModelLoss(world_model, **dreamer_v3_model_loss_settings(settings))


def make_torchrl_dreamer_v3(
    *,
    action_dim: int,
    widths: DreamerV3Widths,
    horizon: int = 15,
    settings: DreamerV3Settings = TORCHRL_DREAMER_V3_SETTINGS,
    device: str | torch.device = "cpu",
) -> TorchRLDreamerV3Learner:
    """TorchRL's DreamerV3 modules and losses composed as its reproduction composes them, at ``widths``.

    Args:
        action_dim: width of the action (in [-1, 1]).
        widths: the widths (:class:`DreamerV3Widths`).
        horizon: imagination horizon.
        settings: DreamerV3's settings (:class:`~isodream_rl.modules.dreamer_v3.DreamerV3Settings`).
        device: where the modules live.

    Returns:
        :class:`TorchRLDreamerV3Learner`; ``loss_module(td)`` on a ``[B, T]`` replay batch (root ``"state"``/
        ``"belief"`` zeros) returns every ``loss_*`` term.
    """
    state_dim, belief_dim = widths.state_dim(settings), widths.deter
    latent = state_dim + belief_dim
    parts = _parts(action_dim=action_dim, widths=widths, settings=settings, device=device)
    world_model = _world_model(parts, action_dim=action_dim, num_bins=settings.num_bins)
    model_based_env = _model_based_env(
        parts,
        action_dim=action_dim,
        state_dim=state_dim,
        belief_dim=belief_dim,
        num_bins=settings.num_bins,
        device=device,
    )
    actor = _actor(
        latent=latent, action_dim=action_dim, units=widths.actor_units, settings=settings, device=device
    )
    value = _value(latent=latent, units=widths.value_units, num_bins=settings.num_bins, device=device)
    model_loss = dreamer_v3_model_loss(world_model, settings=settings)
    continuation = continuation_probability(parts.continuation, in_keys=["belief", "state"])
    behavior = make_dreamer_v3_behavior(
        actor, value, model_based_env, continuation=continuation, horizon=horizon, settings=settings
    )
    loss_module = make_dreamer_v3_loss(model_loss, behavior, settings=settings)
    acting = TensorDictSequential(
        TensorDictModule(parts.encoder, in_keys=["pixels"], out_keys=["encoded_latents"]),
        RSSMStateEstimatorV3(parts.prior, parts.posterior),
        actor,
    )
    return TorchRLDreamerV3Learner(
        world_model=world_model,
        actor=actor,
        value=value,
        model_based_env=model_based_env,
        model_loss=model_loss,
        actor_loss=behavior.actor_loss,
        value_loss=behavior.value_loss,
        loss_module=loss_module,
        target_updater=behavior.target_updater,
        policy=TorchRLDreamerV3Policy(
            acting, state_dim=state_dim, belief_dim=belief_dim, action_dim=action_dim
        ),
    )


# ---------------------------------------------------------------------------------------------- run components
@dataclass
class TorchRLDreamerV3Behavior:
    """What the run reads of the behaviour side: the acting policy (and the losses, for inspection)."""

    policy: TorchRLDreamerV3Policy
    actor_loss: DreamerV3ActorLoss
    value_loss: DreamerV3ValueLoss


@register_algorithm("torchrl_dreamer_v3")
class TorchRLDreamerV3Components(BaselineComponents):
    """Models, losses, optimiser, stepper and replay buffer of an ``algo=torchrl_dreamer_v3`` run.

    The interface of :class:`~isodream_rl.trainers.components.RunComponents` over TorchRL's DreamerV3
    (:func:`make_torchrl_dreamer_v3`): widths from :meth:`DreamerV3Widths.from_run`; ``algo.horizon``;
    ``train.world_model_lr``/``actor_lr``/``value_lr`` as the optimiser's three parameter groups,
    ``world_model_warmup``, ``max_nonfinite_updates``, ``device``. The replay buffer, its preparation hook and the
    episode-return hook are the Iso-Dream run's.

    Args:
        cfg: the run configuration.
        action_dim: width of the env's action.
        scratch_dir: folder of the replay buffer's memmap files.
        settings: DreamerV3's settings. Defaults to TorchRL's
            (:class:`~isodream_rl.modules.dreamer_v3.DreamerV3Settings`).

    Attributes:
        learner (:class:`TorchRLDreamerV3Learner`), model_loss (``DreamerV3ModelLoss``), world_model (``None``: no
        open-loop prediction in the evaluation), behavior (:class:`TorchRLDreamerV3Behavior`), stepper
        (:class:`~isodream_rl.trainers.dreamer_v3.DreamerV3OptimizationStepper`), replay_buffer, preparation, returns.
    """

    algo = "torchrl_dreamer_v3"

    def __init__(
        self,
        cfg: RunConfig,
        *,
        action_dim: int,
        scratch_dir: Path,
        settings: DreamerV3Settings = TORCHRL_DREAMER_V3_SETTINGS,
    ) -> None:
        train = cfg.train
        widths = DreamerV3Widths.from_run(cfg)
        self.learner = make_torchrl_dreamer_v3(
            action_dim=action_dim,
            widths=widths,
            horizon=cfg.algo.horizon,
            settings=settings,
            device=train.device,
        )
        self.model_loss = self.learner.model_loss
        self.world_model = None
        self.behavior = TorchRLDreamerV3Behavior(
            policy=self.learner.policy, actor_loss=self.learner.actor_loss, value_loss=self.learner.value_loss
        )
        self.stepper = make_dreamer_v3_stepper(
            cfg,
            self.learner,
            state_dim=widths.state_dim(settings),
            belief_dim=widths.deter,
            settings=settings,
        )
        self.set_replay_parts(cfg, scratch_dir=scratch_dir)

    def modules(self) -> dict[str, nn.Module]:
        """The trained modules and the return normalisation's statistics, by checkpoint name
        (:func:`~isodream_rl.trainers.dreamer_v3.dreamer_v3_checkpoint_modules`)."""
        return dreamer_v3_checkpoint_modules(self.learner)
