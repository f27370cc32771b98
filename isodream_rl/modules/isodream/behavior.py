"""The actor, the critic and the acting policy of Iso-Dream's DreamerV3 learner (paper eqs. 6-7, Algorithm 1).

Both read ``e_t`` (eq. 7) from the packed latent of :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel`
(``state = [s, z]``, ``belief = [h, h']``) and, in ``"attention"`` mode, the window ``free_window`` ``[*N, tau, F]``
of ``z`` rolled ``tau - 1`` steps ahead: ``e = Attention([s, h], window)`` (eq. 6,
:class:`~isodream_rl.modules.FutureStateAttention`). On ``e`` sit DreamerV3's heads: the bounded-normal actor
(:class:`~isodream_rl.modules.dreamer_v3.DreamerV3ContinuousActor`) and a two-hot critic (``DreamerV3MLP`` +
``SymExpTwoHot``), each with an attention of its own. Their RMS norms run as
:class:`~isodream_rl.modules.fast_paths.FastRMSNorm` (the same function, fewer passes) when the world model's
``IsoDreamConfig.fast_paths`` is true (the default), as TorchRL's otherwise.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import (
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
)
from torch import nn
from torchrl.modules import DreamerV3MLP

from isodream_rl.modules.attention import POLICY_INPUTS, FutureStateAttention
from isodream_rl.modules.dreamer_v3 import (
    DreamerV3ContinuousActor,
    SequenceActingPolicy,
    bounded_normal_actor,
    two_hot_value,
)
from isodream_rl.modules.fast_paths import use_fast_rms_norms
from isodream_rl.modules.isodream.world_model import FREE_ACTION_DIM, IsoDreamConfig, IsoDreamWorldModel


class PolicyFeatures(nn.Module):
    """``e_t`` (eq. 7) from the packed latent.

    In ``"attention"`` mode the query is the controllable features ``[s, h]`` and the keys and values are the
    stochastic states ``z`` of the window (eq. 6 attends over the noncontrollable states): the window also holds
    each entry's belief ``h'`` (the chain continues from it, and the reward reads it), which the attention leaves
    out, as it would multiply the attention's cost by about ``(S_z + D_z) / S_z``.

    Args:
        config: the world model's :class:`~isodream_rl.modules.isodream.world_model.IsoDreamConfig`.
        mode: ``"attention"`` (eq. 6), ``"controllable"`` (``[h, s]``, the DMC setting) or ``"concat"``
            (``[h, s, h', z]``).
        attention_dim: width of the attention's projections.
        device: where the parameters live.

    Shapes:
        ``state`` ``[*N, S]``, ``belief`` ``[*N, D]`` (packed), ``free_window`` ``[*N, tau, S_z + D_z]``
        (attention mode only) -> ``[*N, feature_dim]``.
    """

    def __init__(
        self, config: IsoDreamConfig, *, mode: str = "attention", attention_dim: int = 64, device=None
    ) -> None:
        super().__init__()
        if mode not in POLICY_INPUTS:
            raise ValueError(f"unknown policy_input {mode!r}; valid: {POLICY_INPUTS}")
        if mode != "controllable" and not config.free_branch:
            raise ValueError(
                f"policy_input={mode!r} reads the noncontrollable branch, which this model lacks"
            )
        self.mode = mode
        control, free = config.control, config.free
        self.state_dim, self.deter, self.free_state_dim = control.state_dim, control.deter, free.state_dim
        self.feature_dim = control.feature_dim + (free.feature_dim if mode == "concat" else 0)
        self.attention = (
            FutureStateAttention(
                query_dim=control.feature_dim, key_dim=free.state_dim, width=attention_dim, device=device
            )
            if mode == "attention"
            else None
        )

    @property
    def in_keys(self) -> list[str]:
        """The tensordict keys :meth:`forward` reads, in order."""
        return ["state", "belief", "free_window"] if self.mode == "attention" else ["state", "belief"]

    def forward(
        self, state: torch.Tensor, belief: torch.Tensor, free_window: torch.Tensor | None = None
    ) -> torch.Tensor:
        s, h = state[..., : self.state_dim], belief[..., : self.deter]
        if self.mode == "controllable":
            return torch.cat([h, s], dim=-1)
        if self.mode == "concat":
            return torch.cat([h, s, belief[..., self.deter :], state[..., self.state_dim :]], dim=-1)
        return self.attention(torch.cat([s, h], dim=-1), free_window[..., : self.free_state_dim])


class _OnFeatures(nn.Module):
    """``head(features(state, belief[, window]))``."""

    def __init__(self, features: PolicyFeatures, head: nn.Module) -> None:
        super().__init__()
        self.features, self.head = features, head

    def forward(self, *inputs: torch.Tensor):
        return self.head(self.features(*inputs))


def _on_features(features: PolicyFeatures, head: nn.Module, *, fast_paths: bool) -> _OnFeatures:
    """``_OnFeatures(features, head)``, its RMS norms the fused ones
    (:func:`~isodream_rl.modules.fast_paths.use_fast_rms_norms`) when ``fast_paths`` is true and TorchRL's
    otherwise: the same parameters and state-dict keys either way."""
    module = _OnFeatures(features, head)
    return use_fast_rms_norms(module) if fast_paths else module


def make_actor(
    config: IsoDreamConfig, *, mode: str, attention_dim: int, units: int, device=None
) -> ProbabilisticTensorDictSequential:
    """The actor ``pi(a | e_t)``: features, DreamerV3's bounded-normal head (3 hidden layers of ``units``)
    (:func:`~isodream_rl.modules.dreamer_v3.bounded_normal_actor`)."""
    settings = config.settings
    features = PolicyFeatures(config, mode=mode, attention_dim=attention_dim, device=device)
    head = DreamerV3ContinuousActor(
        features.feature_dim,
        config.action_dim,
        num_cells=units,
        min_std=settings.policy_min_std,
        max_std=settings.policy_max_std,
        device=device,
    )
    net = TensorDictModule(
        _on_features(features, head, fast_paths=config.fast_paths),
        in_keys=features.in_keys,
        out_keys=["loc", "scale"],
    )
    return bounded_normal_actor(net)


def make_value(
    config: IsoDreamConfig, *, mode: str, attention_dim: int, units: int, device=None
) -> TensorDictSequential:
    """The critic ``v(e_t)``: features, a two-hot ``DreamerV3MLP`` (3 hidden layers, output initialised to zero)
    (:func:`~isodream_rl.modules.dreamer_v3.two_hot_value`)."""
    bins = config.settings.num_bins
    features = PolicyFeatures(config, mode=mode, attention_dim=attention_dim, device=device)
    head = DreamerV3MLP(features.feature_dim, bins, depth=3, num_cells=units, outscale=0.0, device=device)
    return two_hot_value(
        _on_features(features, head, fast_paths=config.fast_paths), in_keys=features.in_keys, num_bins=bins
    )


class IsoDreamStateEstimator(TensorDictModuleBase):
    """The acting filter of both branches (eqs. 2-3) and the look-ahead window (Algorithm 1, line 3).

    Reads ``"state"``/``"belief"`` (packed, the previous step's), ``"previous_action"``, ``"encoded_latents"``
    (the encoder on the current frame) and ``"is_init"``; zeroes the three where ``is_init``; advances each branch's
    belief (the controllable one with the previous action, the action-free one with none) and samples its
    posterior; writes the packed ``"state"``, ``"belief"`` and, with the action-free branch, ``"free_window"``
    ``[*N, tau, F]`` (``z`` rolled ``tau - 1`` prior steps ahead). As TorchRL's ``RSSMStateEstimatorV3``, one branch
    at a time.

    Args:
        world_model: the trained :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel` (shared).
    """

    def __init__(self, world_model: IsoDreamWorldModel) -> None:
        super().__init__()
        self.world_model = world_model
        self.in_keys = ["state", "belief", "previous_action", "encoded_latents", "is_init"]
        self.out_keys = ["state", "belief"] + (["free_window"] if world_model.config.free_branch else [])

    def forward(self, tensordict: TensorDict) -> TensorDict:
        model = self.world_model
        state, belief, action, embed, reset = (tensordict.get(key) for key in self.in_keys)
        reset = reset.reshape(*tensordict.batch_size, 1)
        state, belief, action = (torch.where(reset, 0, x) for x in (state, belief, action))
        s, z = model.split_state(state)
        h, h_free = model.split_belief(belief)
        h = model.control_prior._update_belief(s, h, action)
        _, s = model.control_posterior(h, embed)
        states, beliefs = [s], [h]
        if z is not None:
            zero = action.new_zeros(*action.shape[:-1], FREE_ACTION_DIM)
            h_free = model.free_prior._update_belief(z, h_free, zero)
            _, z = model.free_posterior(h_free, embed)
            states.append(z)
            beliefs.append(h_free)
            tensordict.set("free_window", model.free_window(z, h_free).float())
        tensordict.set("state", torch.cat(states, dim=-1).float())
        tensordict.set("belief", torch.cat(beliefs, dim=-1).float())
        return tensordict


class IsoDreamPolicy(SequenceActingPolicy):
    """Iso-Dream's acting policy on the DreamerV3 learner: encoder, :class:`IsoDreamStateEstimator`, actor, as a
    :class:`~isodream_rl.modules.dreamer_v3.SequenceActingPolicy` carrying the packed ``state``, ``belief`` and
    ``previous_action``.

    Args:
        world_model: the trained world model (shared).
        actor: the actor of :func:`make_actor` (shared).
    """

    def __init__(self, world_model: IsoDreamWorldModel, actor: ProbabilisticTensorDictSequential) -> None:
        cfg = world_model.config
        module = TensorDictSequential(
            TensorDictModule(world_model.encoder, in_keys=["pixels"], out_keys=["encoded_latents"]),
            IsoDreamStateEstimator(world_model),
            actor,
        )
        super().__init__(
            module,
            state_dim=cfg.packed_state_dim,
            belief_dim=cfg.packed_belief_dim,
            action_dim=cfg.action_dim,
        )


__all__ = [
    "IsoDreamPolicy",
    "IsoDreamStateEstimator",
    "PolicyFeatures",
    "make_actor",
    "make_value",
]
