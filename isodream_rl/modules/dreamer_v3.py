"""DreamerV3's settings and the pieces of a DreamerV3 agent that TorchRL lacks.

- :class:`DreamerV3Settings`: DreamerV3's settings (Hafner et al. 2023, https://arxiv.org/abs/2301.04104) as
  TorchRL's DreamerV3 reproduction sets them, one home per value;
- :class:`WindowInputCheck`: the one-line errors the other algorithms' world models give on a bad ``[B, T]``
  replay batch, as a DreamerV3 world model's first module;
- :class:`DreamerV3ContinuousActor`: the bounded-normal actor of TorchRL's reproduction (TorchRL ships DreamerV3's
  discrete actor only), built from ``DreamerV3MLP``; :func:`bounded_normal_actor` and :func:`two_hot_value` wrap
  an actor and a critic network as TorchRL's DreamerV3 losses read them;
- :class:`SequenceActingPolicy`: the acting policy around an acting sequence (encoder, filter, actor).

Both ``algo=torchrl_dreamer_v3`` (:mod:`isodream_rl.baselines.torchrl_dreamer_v3`) and Iso-Dream's DreamerV3
learner use them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

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
from torchrl.modules import DreamerV3MLP, IndependentNormal, SymExpTwoHot

from isodream_rl.modules.carried_state import CarriedStatePolicy
from isodream_rl.modules.pixels import check_pixel_values, check_pixels

#: The observation key of the world model (uint8 pixels of the step's outcome).
PIXELS = ("next", "pixels")


@dataclass(frozen=True)
class DreamerV3Settings:
    """DreamerV3's settings (Hafner et al. 2023): the fields of each DreamerV3 learner's table, which names every
    value (:data:`TORCHRL_DREAMER_V3_SETTINGS`, ``algo=torchrl_dreamer_v3``'s;
    :data:`~isodream_rl.modules.isodream.settings.ISODREAM_SETTINGS`, the default learner's)."""

    num_categoricals: int
    """Categorical variables of the stochastic state."""
    unimix: float
    """Uniform mixture of every categorical (latents, KL)."""
    num_blocks: int
    """Blocks of the block GRU and of the decoder's input projection."""
    prior_layers: int
    """Hidden layers of the prior's logit MLP."""
    num_bins: int
    """Two-hot bins of the reward and value heads."""
    free_bits: float
    """Free nats of each KL term (on the sum over the categoricals)."""
    lambda_dynamic: float
    """Weight of the dynamics KL (trains the prior)."""
    lambda_representation: float
    """Weight of the representation KL (trains the posterior)."""
    continuation_horizon: float
    """The continuation head learns ``1 - 1 / horizon`` on non-terminal steps: DreamerV3's discount."""
    lmbda: float
    """lambda of the lambda-returns."""
    entropy_bonus: float
    """eta, the actor's entropy weight."""
    return_normalization_rate: float
    """EMA rate of the 5th / 95th return percentiles."""
    return_normalization_min_scale: float
    """Floor of the return-normalisation divisor."""
    slow_critic_regularization: float
    """Weight of the critic's regression towards its slow copy."""
    slow_critic_tau: float
    """Rate of the slow critic's ``SoftUpdate``."""
    replay_value_loss_weight: float
    """Weight of the critic loss on replayed posteriors."""
    policy_min_std: float
    """Lower bound of the actor's std."""
    policy_max_std: float
    """Upper bound of the actor's std."""
    agc: float
    """Adaptive gradient clipping: largest gradient norm per unit of parameter norm."""
    optimizer_eps: float
    """Epsilon of the optimiser's RMS denominator."""
    lr_warmup: int
    """Updates of linear learning-rate warm-up (the first update has learning rate 0)."""


#: ``algo=torchrl_dreamer_v3``'s settings: DreamerV3's as TorchRL's DreamerV3 reproduction sets them.
TORCHRL_DREAMER_V3_SETTINGS = DreamerV3Settings(
    num_categoricals=32,
    unimix=0.01,
    num_blocks=8,
    prior_layers=2,
    num_bins=255,
    free_bits=1.0,
    lambda_dynamic=1.0,
    lambda_representation=0.1,
    continuation_horizon=333.0,
    lmbda=0.95,
    entropy_bonus=3e-4,
    return_normalization_rate=0.01,
    return_normalization_min_scale=1.0,
    slow_critic_regularization=1.0,
    slow_critic_tau=0.02,
    replay_value_loss_weight=0.3,
    policy_min_std=0.1,
    policy_max_std=1.0,
    agc=0.3,
    optimizer_eps=1e-20,
    lr_warmup=1000,
)


class WindowInputCheck(TensorDictModuleBase):
    """Refuses a bad ``[B, T]`` replay batch with the one-line errors of the other algorithms' world models.

    Reads uint8 ``("next", "pixels")`` ``[B, T, 3, 64, 64]`` (or floats in [0, 1]), ``"action"`` ``[B, T, A]`` and
    ``"is_init"`` ``[B, T, 1]``; writes nothing. One min/max of float pixels; uint8 pixels are not scanned.

    Args:
        action_dim: width of ``"action"``.
    """

    def __init__(self, *, action_dim: int) -> None:
        super().__init__()
        self.action_dim = action_dim
        self.in_keys = [PIXELS, "action", "is_init"]
        self.out_keys = []

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims != 2:
            raise ValueError(
                f"the DreamerV3 world model expects a [B, T] tensordict (replay windows), got batch_size "
                f"{tuple(tensordict.batch_size)}; reshape flat samples with td.reshape(-1, T)"
            )
        pixels, action = tensordict.get(PIXELS, None), tensordict.get("action", None)
        if pixels is None or action is None:
            missing = [str(k) for k, v in ((PIXELS, pixels), ("action", action)) if v is None]
            raise KeyError(f"the DreamerV3 world model needs {missing} in its input tensordict")
        check_pixels(pixels, name="('next', 'pixels')")
        if action.dim() != 3 or action.shape[-1] != self.action_dim:
            raise ValueError(
                f"'action' must have shape [B, T, {self.action_dim}] for this world model, got {tuple(action.shape)}"
            )
        if tensordict.batch_size[1] < 2:
            raise ValueError(
                "the DreamerV3 world model needs windows of at least 2 steps (the replay-value target reads the "
                f"next step; one step teaches no dynamics), got T={tensordict.batch_size[1]}: sample longer windows"
            )
        if tensordict.get("is_init", None) is None:
            raise ValueError(
                "the DreamerV3 world model needs 'is_init' [B, T, 1] bool (True where an episode starts; TorchRL's "
                "InitTracker writes it): without it windows never reset. Pass torch.zeros(B, T, 1, "
                "dtype=torch.bool) for windows inside one episode"
            )
        check_pixel_values(pixels, name="('next', 'pixels')")
        if not bool(torch.isfinite(action).all()):
            raise ValueError("'action' holds NaN or inf values: check the policy or the replay data")
        return tensordict


class DreamerV3ContinuousActor(nn.Module):
    """DreamerV3's bounded-normal actor: ``loc = tanh(mean)``, ``scale = (max - min) sigmoid(s + 2) + min``.

    A ``DreamerV3MLP`` trunk (RMS norm, SiLU) on its inputs concatenated on the last dim (``[belief, state]`` in
    ``algo=torchrl_dreamer_v3``) and two linear heads whose initial weights are scaled by 0.01, as TorchRL's
    DreamerV3 reproduction builds it.

    Args:
        in_features: width of the concatenated inputs (``[belief, state]``: ``D + S``).
        action_dim: width of the action.
        num_cells: width of the trunk's hidden layers.
        depth: hidden layers of the trunk. Defaults to 3.
        min_std: lower bound of the std. Defaults to 0.1.
        max_std: upper bound of the std. Defaults to 1.0.
        device: where the parameters live.

    Examples:
        >>> actor = DreamerV3ContinuousActor(12, 2, num_cells=8)
        >>> loc, scale = actor(torch.zeros(4, 8), torch.zeros(4, 4))
        >>> loc.shape, bool(((scale >= 0.1) & (scale <= 1.0)).all())
        (torch.Size([4, 2]), True)
    """

    def __init__(
        self,
        in_features: int,
        action_dim: int,
        *,
        num_cells: int,
        depth: int = 3,
        min_std: float = 0.1,
        max_std: float = 1.0,
        device=None,
    ) -> None:
        super().__init__()
        self.trunk = DreamerV3MLP(in_features, None, depth=depth, num_cells=num_cells, device=device)
        self.mean = DreamerV3MLP(num_cells, action_dim, depth=0, outscale=0.01, device=device)
        self.std = DreamerV3MLP(num_cells, action_dim, depth=0, outscale=0.01, device=device)
        self.min_std, self.max_std = min_std, max_std

    def forward(self, *features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``[*B, F_1]``, ..., ``[*B, F_k]`` (e.g. ``belief`` ``[*B, D]``, ``state`` ``[*B, S]``; concatenated on the
        last dim, ``sum F_i = in_features``) -> ``loc`` ``[*B, A]`` in (-1, 1), ``scale`` ``[*B, A]`` in [min, max]."""
        hidden = self.trunk(*features)
        scale = (self.max_std - self.min_std) * torch.sigmoid(self.std(hidden) + 2.0) + self.min_std
        return self.mean(hidden).tanh(), scale


def bounded_normal_actor(net: TensorDictModule) -> ProbabilisticTensorDictSequential:
    """The DreamerV3 actor around ``net`` (a ``TensorDictModule`` writing ``"loc"`` and ``"scale"``, e.g. a
    :class:`DreamerV3ContinuousActor`): an ``IndependentNormal`` sampled under ``RANDOM`` exploration (its mean
    otherwise), writing ``"action"`` and ``"action_log_prob"``, as TorchRL's DreamerV3 losses read it."""
    return ProbabilisticTensorDictSequential(
        net,
        ProbabilisticTensorDictModule(
            in_keys=["loc", "scale"],
            out_keys=["action"],
            default_interaction_type=InteractionType.RANDOM,
            distribution_class=IndependentNormal,
            return_log_prob=True,
            log_prob_key="action_log_prob",
        ),
    )


def continuation_probability(logit: Callable, *, in_keys: list) -> TensorDictSequential:
    """The continuation model of ``DreamerV3ActorLoss`` around ``logit`` (the continuation head's logit from
    ``in_keys``): ``"continue_logits"``, then their sigmoid, ``"continuation"``."""
    return TensorDictSequential(
        TensorDictModule(logit, in_keys=in_keys, out_keys=["continue_logits"]),
        TensorDictModule(torch.sigmoid, in_keys=["continue_logits"], out_keys=["continuation"]),
    )


def two_hot_value(net: nn.Module, *, in_keys: list, num_bins: int) -> TensorDictSequential:
    """DreamerV3's two-hot critic around ``net`` (its inputs read from ``in_keys``, ``num_bins`` logits out):
    ``"state_value_logits"``, decoded to ``"state_value"`` by ``SymExpTwoHot``."""
    return TensorDictSequential(
        TensorDictModule(net, in_keys=in_keys, out_keys=["state_value_logits"]),
        TensorDictModule(SymExpTwoHot(num_bins), in_keys=["state_value_logits"], out_keys=["state_value"]),
    )


class SequenceActingPolicy(CarriedStatePolicy):
    """An acting policy whose TorchRL acting sequence ``module`` reads ``"pixels"``, ``"is_init"`` and the carried
    ``"state"``, ``"belief"``, ``"previous_action"`` (resetting them at ``is_init`` itself) and writes the new
    ``"state"``, ``"belief"`` and the sampled (or, under a deterministic exploration type, mean) ``"action"``: the
    action is clamped to [-1, 1] and becomes the next ``previous_action`` (a
    :class:`~isodream_rl.modules.isodream_v2.policy.CarriedStatePolicy`: prime the env with :meth:`make_tensordict_primer`).

    Args:
        module: the acting sequence.
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        action_dim: width of ``"action"``.
        pixels_key: the observation key. Defaults to ``"pixels"``.
        action_key: where the action is written. Defaults to ``"action"``.
    """

    def __init__(
        self,
        module: TensorDictModuleBase,
        *,
        state_dim: int,
        belief_dim: int,
        action_dim: int,
        pixels_key: str = "pixels",
        action_key: str = "action",
    ) -> None:
        super().__init__(
            module,
            widths={"state": state_dim, "belief": belief_dim, "previous_action": action_dim},
            pixels_key=pixels_key,
            action_key=action_key,
        )

    def act(
        self, pixels: torch.Tensor, carried: dict[str, torch.Tensor], reset: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """The acting sequence; the action clamped to [-1, 1], also the next ``previous_action``."""
        n = pixels.shape[0]
        if reset is None:
            reset = torch.zeros(n, 1, dtype=torch.bool, device=pixels.device)
        work = TensorDict(
            {"pixels": pixels, "is_init": reset, **carried}, batch_size=[n], device=pixels.device
        )
        self.module(work)
        action = work.get("action").clamp(-1.0, 1.0)
        return {
            self.action_key: action,
            "state": work.get("state"),
            "belief": work.get("belief"),
            "previous_action": action,
        }
