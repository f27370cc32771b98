"""Iso-Dream's decoupled world model (paper eqs. 2-5) built from TorchRL's DreamerV3 pieces.

The same decomposition as :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` (an action-conditioned RSSM for the
controllable state ``s``, an action-free RSSM for the noncontrollable state ``z``, a static background, three
decoders composed by softmax masks, an inverse-dynamics cell), with DreamerV3's parts in place of DreamerV2's:
``DreamerV3ImageEncoder`` (RMS norm, SiLU), two block-GRU RSSMs with categorical latents and 1 % unimix
(``RSSMPriorV3`` / ``RSSMPosteriorV3``, each rolled by its own ``RSSMRolloutV3``), three ``DreamerV3ImageDecoder``
(RGB + mask logit), a symlog two-hot reward head and a continuation head (``DreamerV3MLP``).

Why a module of its own rather than a ``TensorDictSequential`` of TorchRL modules: ``RSSMRolloutV3`` reads and
writes the fixed keys ``state``/``belief``, so each branch is rolled on a tensordict of its own and the two are
packed afterwards; and the composition (eq. 4) takes three decoders at once.

Packed keys. Everything downstream (``DreamerV3ModelLoss``, ``DreamerV3Loss``, the imagination env, the actor and
the critic) sees one latent: ``state = [s, z]`` and ``belief = [h, h']`` (controllable first), and the prior /
posterior logits of both branches concatenated along the categoricals (``[*B, T, 2K, C]``), so that the KL terms of
``DreamerV3ModelLoss`` are the sum of both branches' (eq. 5's two KL terms, with one free-bits floor on their sum).
:meth:`IsoDreamWorldModel.split_state` / :meth:`IsoDreamWorldModel.split_belief` undo the packing.

The action-free prior (eq. 3) is ``RSSMPriorV3`` fed a constant zero action of width 1: its block GRU then sees
the bias of its action projection only, so its dynamics do not depend on the actions (``RSSMPriorV3`` needs an
action input).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.modules import (
    DreamerV3ImageDecoder,
    DreamerV3ImageEncoder,
    DreamerV3MLP,
    RSSMPosteriorV3,
    RSSMPriorV3,
    RSSMRolloutV3,
    SymExpTwoHot,
)
from torchrl.modules.models.model_based import _straight_through_categorical

from isodream_rl.modules.composition import DECODER_STATES as DECODER_INPUTS
from isodream_rl.modules.composition import MaskComposition
from isodream_rl.modules.dreamer_v3 import DreamerV3Settings, WindowInputCheck
from isodream_rl.modules.fast_paths import FusedMaskComposition, use_fast_rms_norms
from isodream_rl.modules.inverse_dynamics import InverseDynamicsCell
from isodream_rl.modules.isodream.settings import ISODREAM_SETTINGS

PIXELS = ("next", "pixels")
#: Width of the constant zero action of the action-free prior.
FREE_ACTION_DIM = 1


def _next(key: str) -> tuple[str, str]:
    return ("next", key)


def dreamer_v3_classes(hidden: int) -> int:
    """Classes of each categorical by DreamerV3's size rule, ``hidden / 16`` (at least 2: one class carries no
    information and no gradient)."""
    return max(2, (hidden + 8) // 16)


@dataclass(frozen=True)
class BranchWidths:
    """One latent branch's widths: DreamerV3's ``hidden`` (``deter = 8 hidden``) and its categoricals."""

    hidden: int
    """DreamerV3's ``hidden``: the RSSM's hidden layers."""
    num_categoricals: int
    """Categorical variables of the stochastic state."""
    classes: int
    """Classes of each categorical (both branches have the same, so that their logits stack)."""

    @property
    def deter(self) -> int:
        """Belief width."""
        return 8 * self.hidden

    @property
    def state_dim(self) -> int:
        """The one-hot ``state`` width: categoricals x classes."""
        return self.num_categoricals * self.classes

    @property
    def feature_dim(self) -> int:
        """Width of the branch's features ``[state, belief]``."""
        return self.state_dim + self.deter


@dataclass(frozen=True)
class IsoDreamConfig:
    """Widths and switches of :class:`IsoDreamWorldModel`."""

    action_dim: int
    """Width of the action."""
    hidden: int
    """DreamerV3's ``hidden`` of the controllable branch (:class:`BranchWidths`)."""
    image_depth: int
    """Base channel count of the encoder and of each decoder."""
    units: int
    """Width of the reward, continuation and inverse-dynamics hidden layers."""
    free_hidden: int | None = None
    """``hidden`` of the action-free branch; ``None``: ``hidden``."""
    attention_window: int = 3
    """tau: the noncontrollable states a window holds (the current one and ``tau - 1`` predicted)."""
    free_branch: bool = True
    """The action-free branch (``z``)."""
    static_branch: bool = True
    """The static background branch."""
    inverse_dynamics: bool = True
    """The inverse-dynamics cell (predicts ``a_t`` from ``[s_t, s_{t+1}]``)."""
    reward_uses_free: bool = True
    """The reward and continuation heads read ``[h, s, h', z]`` (CARLA, sprites) rather than ``[h, s]``."""
    static_frames: int = 1
    """K: the frames whose embeddings give a window's background."""
    static_mask_bias: float = 3.0
    """Initial bias of the static branch's mask logit (a learned parameter): 3 starts training with the background
    owning 91 % of every pixel, so that the dynamic branches take only the pixels it cannot explain (what moves)
    instead of one of them taking the still background and leaving the agent to the static image."""
    control_decoder_input: str = "posterior"
    """What the controllable decoder draws from (:data:`DECODER_INPUTS`): ``"posterior"`` (default), ``s_t ~
    q(s_t | h_t, o_t)`` (the authors' DMC code); ``"prior"``, its one-step prior ``s~_t ~ p(s_t | h_t)``, ``h_t``
    made from the previous posterior and the action ``a_{t-1}`` (eq. 4's text, §3.2)."""
    free_decoder_input: str = "prior"
    """What the action-free decoder draws from (:data:`DECODER_INPUTS`): ``"prior"`` (default), its one-step prior
    ``z~_t ~ p(z_t | h'_t)``, ``h'_t`` made from the previous posterior without the action, so that it cannot draw
    what the actions moved since (the authors' DMC code, where this branch is a one-step predictor);
    ``"posterior"``: ``z_t ~ q(z_t | h'_t, o_t)`` (eq. 4's text), with which the agent can land in this branch.

    A decoder that draws its prior draws the posterior where no previous posterior exists (a window's first step,
    an episode's start)."""
    settings: DreamerV3Settings = ISODREAM_SETTINGS
    """DreamerV3's settings (unimix, categoricals, bins, blocks): the default learner's."""
    fast_paths: bool = True
    """The CPU fast paths of :mod:`~isodream_rl.modules.fast_paths`: eq. 4 as one autograd node
    (:class:`~isodream_rl.modules.fast_paths.FusedMaskComposition`) and the fused RMS norms
    (:func:`~isodream_rl.modules.fast_paths.use_fast_rms_norms`) of the world model, the actor and the critic. The
    same values as the reference forms within float tolerance, and the same parameters and state-dict keys, so a
    checkpoint loads either way; ``False`` builds the reference forms
    (:class:`~isodream_rl.modules.composition.MaskComposition`, TorchRL's RMS norms)."""

    def __post_init__(self) -> None:
        for name in ("control_decoder_input", "free_decoder_input"):
            if getattr(self, name) not in DECODER_INPUTS:
                raise ValueError(f"{name} must be one of {DECODER_INPUTS}, got {getattr(self, name)!r}")

    @property
    def control(self) -> BranchWidths:
        """The controllable branch's widths: DreamerV3's size rule at ``hidden``."""
        return BranchWidths(self.hidden, self.settings.num_categoricals, dreamer_v3_classes(self.hidden))

    @property
    def free(self) -> BranchWidths:
        """The action-free branch's widths (also when the branch is off): ``free_hidden``, the controllable
        branch's classes and as many categoricals as ``free_hidden`` is a fraction of ``hidden``, rounded to a
        multiple of the block GRU's blocks (its input, ``state`` and ``belief``, splits into them)."""
        hidden = self.free_hidden or self.hidden
        blocks = self.settings.num_blocks
        categoricals = blocks * max(1, round(self.settings.num_categoricals * hidden / self.hidden / blocks))
        return BranchWidths(hidden, categoricals, dreamer_v3_classes(self.hidden))

    @property
    def packed_state_dim(self) -> int:
        """Width of the packed ``state`` ``[s, z]``."""
        return self.control.state_dim + (self.free.state_dim if self.free_branch else 0)

    @property
    def packed_belief_dim(self) -> int:
        """Width of the packed ``belief`` ``[h, h']``."""
        return self.control.deter + (self.free.deter if self.free_branch else 0)

    @property
    def head_feature_dim(self) -> int:
        """Width of the reward / continuation heads' input."""
        free = self.free.feature_dim if self.reward_uses_free and self.free_branch else 0
        return self.control.feature_dim + free


def make_rssm(
    widths: BranchWidths, *, action_dim: int, embed_dim: int, settings: DreamerV3Settings, device=None
):
    """One branch's ``RSSMPriorV3`` (block GRU) and ``RSSMPosteriorV3`` (RMS-normed), DreamerV3's settings."""
    categorical = {"num_categoricals": widths.num_categoricals, "num_classes": widths.classes}
    prior = RSSMPriorV3(
        action_shape=(action_dim,),
        hidden_dim=widths.hidden,
        rnn_hidden_dim=widths.deter,
        action_dim=action_dim,
        recurrent_model="block_gru",
        num_blocks=settings.num_blocks,
        prior_num_layers=settings.prior_layers,
        unimix=settings.unimix,
        device=device,
        **categorical,
    )
    posterior = RSSMPosteriorV3(
        hidden_dim=widths.hidden,
        rnn_hidden_dim=widths.deter,
        obs_embed_dim=embed_dim,
        use_rms_norm=True,
        unimix=settings.unimix,
        device=device,
        **categorical,
    )
    return prior, posterior


def branch_rollout(prior: RSSMPriorV3, posterior: RSSMPosteriorV3) -> RSSMRolloutV3:
    """``RSSMRolloutV3`` over one branch with TorchRL's standard keys (its tensor fast path), reset at ``is_init``."""
    return RSSMRolloutV3(
        TensorDictModule(
            prior,
            in_keys=["state", "belief", "action"],
            out_keys=[_next(k) for k in ("prior_logits", "state", "belief")],
        ),
        TensorDictModule(
            posterior,
            in_keys=[_next("belief"), _next("encoded_latents")],
            out_keys=[_next("posterior_logits"), _next("state")],
        ),
        reset_key="is_init",
    )


class IsoDreamWorldModel(TensorDictModuleBase):
    """The decoupled world model on DreamerV3's parts (paper eqs. 2-5; see the module docstring).

    Reads ``("next", "pixels")`` uint8 ``[B, T, 3, 64, 64]`` (or floats in [0, 1]), ``"action"`` ``[B, T, A]``,
    ``"is_init"`` ``[B, T, 1]`` and root ``"state"`` ``[B, T, S]`` / ``"belief"`` ``[B, T, D]`` (packed; each
    window starts from their first step; zeros when absent, as in training).

    Writes under ``"next"``: the packed ``state`` / ``belief`` and ``prior_logits`` / ``posterior_logits``
    ``[B, T, 2K, C]``; ``reco_pixels`` (the composite, eq. 4, in [0, 1] units) ``[B, T, 3, 64, 64]``,
    ``reco_control`` / ``reco_free`` (the components) and ``mask_control`` / ``mask_free`` / ``mask_static``
    ``[B, T, 1, 64, 64]``; ``reward_logits`` ``[B, T, bins]`` and the decoded ``reward`` ``[B, T, 1]``;
    ``continue_pred`` (logit) ``[B, T, 1]``; ``action_pred`` ``[B, T, A]`` with ``action_pred_valid``
    ``[B, T, 1]`` (inverse dynamics, eq. 5's action term; predicts ``action[t]`` from the posteriors before and
    after it); ``free_window`` ``[B, T, tau, F]`` (``z`` of the step and ``tau - 1`` prior steps rolled from it,
    for the critic on replayed states); and root ``background`` ``[B, T, 3, 64, 64]`` with the static branch.

    Args:
        config: widths and switches (:class:`IsoDreamConfig`).
        device: where the parameters live.

    Examples:
        >>> config = IsoDreamConfig(action_dim=2, hidden=16, image_depth=2, units=16)
        >>> model = IsoDreamWorldModel(config)
        >>> td = TensorDict({
        ...     ("next", "pixels"): torch.zeros(2, 3, 3, 64, 64, dtype=torch.uint8),
        ...     "action": torch.zeros(2, 3, 2), "is_init": torch.zeros(2, 3, 1, dtype=torch.bool),
        ...     "state": torch.zeros(2, 3, config.packed_state_dim),
        ...     "belief": torch.zeros(2, 3, config.packed_belief_dim)}, [2, 3])
        >>> model(td)["next", "reco_pixels"].shape
        torch.Size([2, 3, 3, 64, 64])
    """

    def __init__(self, config: IsoDreamConfig, *, device: torch.device | str | None = None) -> None:
        super().__init__()
        self.config = cfg = config
        settings = cfg.settings
        self.check = WindowInputCheck(action_dim=cfg.action_dim)
        self.encoder = DreamerV3ImageEncoder(depth=cfg.image_depth, device=device)
        embed = self.encoder.output_features((3, 64, 64))
        self.control_prior, self.control_posterior = make_rssm(
            cfg.control, action_dim=cfg.action_dim, embed_dim=embed, settings=settings, device=device
        )
        self.control_rollout = branch_rollout(self.control_prior, self.control_posterior)
        single = not (cfg.free_branch or cfg.static_branch)
        decoder = {"depth": cfg.image_depth, "num_blocks": settings.num_blocks, "device": device}
        channels = 3 if single else 4
        self.control_decoder = DreamerV3ImageDecoder(
            cfg.control.feature_dim, image_shape=(channels, 64, 64), **decoder
        )
        if cfg.free_branch:
            self.free_prior, self.free_posterior = make_rssm(
                cfg.free, action_dim=FREE_ACTION_DIM, embed_dim=embed, settings=settings, device=device
            )
            self.free_rollout = branch_rollout(self.free_prior, self.free_posterior)
            self.free_decoder = DreamerV3ImageDecoder(
                cfg.free.feature_dim, image_shape=(4, 64, 64), **decoder
            )
        else:
            self.free_prior = self.free_posterior = self.free_rollout = self.free_decoder = None
        self.static_decoder = (
            DreamerV3ImageDecoder(
                cfg.static_frames * embed, image_shape=(4, 64, 64), **{**decoder, "num_blocks": 1}
            )
            if cfg.static_branch
            else None
        )
        if self.static_decoder is not None:
            with torch.no_grad():
                self.static_decoder.layers[-1].bias[3] += cfg.static_mask_bias
        # Composed in the decoders' units (pixels / 255, see MaskComposition's pixel_range): the same eq. 4 without
        # shifting three [B, T, 4, 64, 64] outputs into [-0.5, 0.5] and four results back; with the fast paths as
        # one autograd node (FusedMaskComposition), without a clamp node and a slice gradient per branch.
        composition = FusedMaskComposition if cfg.fast_paths else MaskComposition
        self.composition = composition(mask_mode="softmax", pixel_range=(0.0, 1.0))
        self.reward_head = DreamerV3MLP(
            cfg.head_feature_dim, settings.num_bins, depth=1, num_cells=cfg.units, outscale=0.0, device=device
        )
        self.reward_decode = SymExpTwoHot(settings.num_bins)
        self.continuation_head = DreamerV3MLP(
            cfg.head_feature_dim, 1, depth=1, num_cells=cfg.units, device=device
        )
        self.inverse_cell = (
            InverseDynamicsCell(
                in_features=cfg.control.state_dim,
                action_dim=cfg.action_dim,
                num_cells=cfg.units,
                device=device,
            )
            if cfg.inverse_dynamics
            else None
        )
        self.in_keys = [PIXELS, "action", "is_init", "state", "belief"]
        out = [
            "state",
            "belief",
            "prior_logits",
            "posterior_logits",
            "reco_pixels",
            "reco_control",
            "mask_control",
        ]
        out += ["reward_logits", "reward", "continue_pred"]
        if cfg.free_branch:
            out += ["reco_free", "mask_free", "free_window"]
        if cfg.static_branch:
            out += ["mask_static"]
        if cfg.inverse_dynamics:
            out += ["action_pred", "action_pred_valid"]
        self.out_keys = [_next(k) for k in out] + (["background"] if cfg.static_branch else [])
        if cfg.fast_paths:
            # TorchRL's RMS norms (encoder, decoders, RSSM heads, reward / continuation heads) as one fused forward
            # kernel and a hand-written backward (fast_paths.FastRMSNorm): the same function, parameters and keys
            use_fast_rms_norms(self)

    # ------------------------------------------------------------------ packing
    def split_state(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Packed ``[*N, S]`` -> ``(s [*N, S_c], z [*N, S_z] or None)``."""
        width = self.config.control.state_dim
        return state[..., :width], (state[..., width:] if self.config.free_branch else None)

    def split_belief(self, belief: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Packed ``[*N, D]`` -> ``(h [*N, D_c], h' [*N, D_z] or None)``."""
        width = self.config.control.deter
        return belief[..., :width], (belief[..., width:] if self.config.free_branch else None)

    def head_features(self, state: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """The reward / continuation heads' input from the packed latent: ``[h, s]`` or ``[h, s, h', z]``."""
        s, z = self.split_state(state)
        h, h_free = self.split_belief(belief)
        if self.config.reward_uses_free and z is not None:
            return torch.cat([h, s, h_free, z], dim=-1)
        return torch.cat([h, s], dim=-1)

    def reward(self, state: torch.Tensor, belief: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(logits [*N, bins], decoded reward [*N, 1])`` of the reward head on a packed latent."""
        logits = self.reward_head(self.head_features(state, belief))
        return logits, self.reward_decode(logits)

    def continuation_logit(self, state: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """The continuation head's logit ``[*N, 1]`` on a packed latent."""
        return self.continuation_head(self.head_features(state, belief))

    # ------------------------------------------------------------------ the action-free branch
    def free_step(
        self, free_state: torch.Tensor, free_belief: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One step of the action-free prior (eq. 3): ``(z, h')`` ``[*N, S_z]``, ``[*N, D_z]`` -> the next ones."""
        zero = free_state.new_zeros(*free_state.shape[:-1], FREE_ACTION_DIM)
        _, free_state, free_belief = self.free_prior(free_state, free_belief, zero)
        return free_state, free_belief

    def free_window(self, free_state: torch.Tensor, free_belief: torch.Tensor) -> torch.Tensor:
        """``[z_t, h'_t]`` and ``tau - 1`` action-free prior steps rolled from it: ``[*N, tau, S_z + D_z]`` (the
        attention's window, eq. 6). The rolled steps carry no gradient."""
        window = [torch.cat([free_state, free_belief], dim=-1)]
        with torch.no_grad():
            state, belief = free_state.detach(), free_belief.detach()
            for _ in range(self.config.attention_window - 1):
                state, belief = self.free_step(state, belief)
                window.append(torch.cat([state, belief], dim=-1))
        return torch.stack(window, dim=-2)

    # ------------------------------------------------------------------ forward
    def _roll(self, rollout: RSSMRolloutV3, tensordict, *, state, belief, action, embed) -> TensorDictBase:
        branch = TensorDict(
            {
                "state": state,
                "belief": belief,
                "action": action,
                "is_init": tensordict.get("is_init"),
                _next("encoded_latents"): embed,
            },
            tensordict.batch_size,
        )
        return rollout(branch)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        cfg = self.config
        self.check(tensordict)
        pixels = tensordict.get(PIXELS)
        for key, width in (("state", cfg.packed_state_dim), ("belief", cfg.packed_belief_dim)):
            if tensordict.get(key, None) is None:  # each window starts from zeros, as in training
                tensordict.set(key, pixels.new_zeros(*tensordict.batch_size, width, dtype=torch.float32))
        embed = self.encoder(pixels)
        s0, z0 = self.split_state(tensordict.get("state"))
        h0, hz0 = self.split_belief(tensordict.get("belief"))
        action = tensordict.get("action")
        control = self._roll(
            self.control_rollout, tensordict, state=s0, belief=h0, action=action, embed=embed
        )
        s, h = control.get(_next("state")), control.get(_next("belief"))
        states, beliefs = [s], [h]
        prior, posterior = [control.get(_next("prior_logits"))], [control.get(_next("posterior_logits"))]
        # steps without a previous posterior in the window: its first step and episode starts
        starts = tensordict.get("is_init").reshape(*s.shape[:2], 1).clone()
        starts[:, 0] = True
        outputs = {
            "control": self.control_decoder(self._drawn(s, prior[0], starts, cfg.control_decoder_input), h)
        }
        if cfg.free_branch:
            zero = action.new_zeros(*action.shape[:-1], FREE_ACTION_DIM)
            free = self._roll(self.free_rollout, tensordict, state=z0, belief=hz0, action=zero, embed=embed)
            z, hz = free.get(_next("state")), free.get(_next("belief"))
            states.append(z)
            beliefs.append(hz)
            prior.append(free.get(_next("prior_logits")))
            posterior.append(free.get(_next("posterior_logits")))
            outputs["free"] = self.free_decoder(self._drawn(z, prior[-1], starts, cfg.free_decoder_input), hz)
            tensordict.set(_next("free_window"), self.free_window(z, hz))
        if cfg.static_branch:
            batch, time = embed.shape[:2]
            frames = embed[:, : cfg.static_frames]
            if time < cfg.static_frames:
                frames = torch.cat(
                    [frames, frames[:, -1:].expand(batch, cfg.static_frames - time, -1)], dim=1
                )
            outputs["static"] = self.static_decoder(frames.reshape(batch, -1)).unsqueeze(1)
        # in pixels / 255 units, the decoders' (they add 0.5) and the loss's: components clamped to [0, 1]
        composite, masks, colors = self.composition.compose_decoded(outputs)
        state, belief = torch.cat(states, dim=-1), torch.cat(beliefs, dim=-1)
        reward_logits, reward = self.reward(state, belief)
        new = {
            "state": state,
            "belief": belief,
            "prior_logits": torch.cat(prior, dim=-2),
            "posterior_logits": torch.cat(posterior, dim=-2),
            "reco_pixels": composite,
            "reco_control": colors["control"],
            "mask_control": masks["control"],
            "reward_logits": reward_logits,
            "reward": reward,
            "continue_pred": self.continuation_logit(state, belief),
        }
        if cfg.free_branch:
            new.update(reco_free=colors["free"], mask_free=masks["free"])
        if cfg.static_branch:
            new["mask_static"] = masks["static"]
            tensordict.set("background", colors["static"].expand_as(composite))
        if cfg.inverse_dynamics:
            new.update(self._inverse(s, starts))
        for key, value in new.items():
            tensordict.set(_next(key), value)
        return tensordict

    @torch.no_grad()
    def open_loop(self, window: TensorDictBase, *, context: int = 5) -> TensorDictBase:
        """Filter ``context`` steps of ``window``, imagine the rest (the controllable branch with the window's
        actions, the action-free one alone), decode every step with each branch.

        The output is that of :func:`~isodream_rl.trainers.openloop.open_loop_prediction` for the DreamerV2-style
        model: a ``[B, T]`` tensordict with ``pixels`` (truth, uint8), ``reco_pixels``, ``reco_control``,
        ``reco_free``, ``background`` in ``[-0.5, 0.5]``, the masks and ``imagined`` ``[B, T]`` bool.
        """
        cfg = self.config
        batch, time = window.shape
        if not 2 <= context < time:
            raise ValueError(
                f"context must be in [2, {time - 1}] for a window of {time} steps, got {context}"
            )
        was_training = self.training
        self.eval()
        observed = window[:, :context].select("action", PIXELS, "is_init", strict=False).clone()
        filtered = self(observed).get("next")
        s, z = self.split_state(filtered.get("state"))
        h, h_free = self.split_belief(filtered.get("belief"))
        controls, frees = [torch.cat([s, h], -1)], [torch.cat([z, h_free], -1)] if z is not None else []
        s, h = s[:, -1], h[:, -1]
        if z is not None:
            z, h_free = z[:, -1], h_free[:, -1]
        action = window.get("action").float()
        for t in range(context, time):
            _, s, h = self.control_prior(s, h, action[:, t])
            controls.append(torch.cat([s, h], -1)[:, None])
            if z is not None:
                z, h_free = self.free_step(z, h_free)
                frees.append(torch.cat([z, h_free], -1)[:, None])
        decoded = {"control": self.control_decoder(torch.cat(controls, 1))}
        if z is not None:
            decoded["free"] = self.free_decoder(torch.cat(frees, 1))
        if cfg.static_branch:
            decoded["static"] = self.static_decoder(
                self.encoder(window.get(PIXELS)[:, : cfg.static_frames]).reshape(batch, -1)
            ).unsqueeze(1)
        composite, masks, colors = self.composition.compose_decoded(decoded)
        composite, colors = composite - 0.5, {k: v - 0.5 for k, v in colors.items()}  # [-0.5, 0.5] units
        self.train(was_training)
        out = TensorDict(
            {
                "pixels": window.get(PIXELS),
                "reco_pixels": composite,
                "reco_control": colors["control"],
                "imagined": (torch.arange(time, device=composite.device) >= context).expand(batch, time),
            },
            [batch, time],
        )
        if "free" in colors:
            out["reco_free"] = colors["free"]
        if "static" in colors:
            out["background"] = colors["static"].expand(batch, time, -1, -1, -1)
        for name, mask in masks.items():
            out[f"mask_{name}"] = mask
        return out

    def _drawn(
        self, posterior: torch.Tensor, prior_logits: torch.Tensor, starts: torch.Tensor, source: str
    ) -> torch.Tensor:
        """The state a branch's decoder draws at each step (:attr:`IsoDreamConfig.control_decoder_input`,
        :attr:`IsoDreamConfig.free_decoder_input`).

        Args:
            posterior: the branch's posterior ``[B, T, S]``.
            prior_logits: its prior's logits ``[B, T, K, C]`` (from the belief that the previous posterior made).
            starts: ``[B, T, 1]`` steps without a previous posterior (the window's first step, episode starts).
            source: ``"prior"`` or ``"posterior"``.

        Returns:
            ``[B, T, S]``: with ``"prior"``, a straight-through sample of the prior (with the RSSM's unimix) where a
            previous posterior exists in the window and the posterior elsewhere (the first step, episode starts);
            with ``"posterior"``, the posterior.
        """
        if source == "posterior":
            return posterior
        prior = _straight_through_categorical(prior_logits, self.config.settings.unimix).flatten(-2)
        return torch.where(starts, posterior, prior)

    def _inverse(self, s: torch.Tensor, starts: torch.Tensor) -> dict[str, torch.Tensor]:
        """``action_pred[t]`` from ``[s_t, s_{t+1}]`` (the posteriors before and after ``action[t]``, i.e. ``("next",
        "state")`` at ``t - 1`` and ``t``); valid where both lie in one episode of the window (``t >= 1``, no
        reset at ``t``: the rollout zeroes a reset step's action)."""
        previous = torch.cat([torch.zeros_like(s[:, :1]), s[:, :-1]], dim=1)
        predicted = self.inverse_cell(previous, s)
        return {"action_pred": predicted, "action_pred_valid": ~starts}
