"""The assembled three-branch Iso-Dream world model (paper §3.2, Fig. 2a).

Data convention (TorchRL's Dreamer): a replay window is a ``[B, T]`` tensordict whose root holds the
step-``t`` inputs (``"action"`` a_t, ``"is_init"``) and whose ``"next"`` holds what follows
(``("next", "pixels")`` o_{t+1}, ``("next", "reward")``). Step ``t`` consumes the posterior at ``t`` and
``a_t`` and filters ``o_{t+1}``, so every latent output lives under ``"next"``.
"""

from __future__ import annotations

import contextlib

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from isodream_rl.modules.composition import MaskComposition
from isodream_rl.modules.fast_paths import FusedMaskComposition
from isodream_rl.modules.inverse_dynamics import InverseDynamicsCell
from isodream_rl.modules.isodream_v2.config import IsoDreamV2Config
from isodream_rl.modules.isodream_v2.decoder import ConvDecoder
from isodream_rl.modules.isodream_v2.encoder import BranchedEncoder
from isodream_rl.modules.isodream_v2.fast_paths import FastConvDecoder, fast_filter_window
from isodream_rl.modules.isodream_v2.heads import make_discount_head, make_reward_head
from isodream_rl.modules.isodream_v2.rssm import ActionConditionedRSSM, ActionFreeRSSM, filter_window
from isodream_rl.modules.pixels import IMAGE_SHAPE, check_pixel_values, check_pixels


def _next(key: str) -> tuple[str, str]:
    return ("next", key)


class IsoDreamV2WorldModel(TensorDictModuleBase):
    """Encoder, decoupled RSSM, masked decoders, inverse-dynamics cell and reward/discount heads.

    Args:
        config: a :class:`~isodream_rl.modules.isodream_v2.config.IsoDreamV2Config`.
        device: where to create the parameters.
        check_inputs: check every batch at the boundary (one min/max of the pixels, a finiteness check of the
            actions): float pixels outside ``[0, 1]``, NaN/inf pixels or actions, a missing ``"is_init"`` and
            windows shorter than 2 steps raise a ``ValueError`` saying what to fix. ``False`` skips the value
            checks (shapes are always checked) for speed once the data pipeline is trusted.

    Reads (``[B, T]`` batch, ``T >= 2``):
        ``("next", "pixels")`` uint8 ``[B, T, 3, 64, 64]`` (or float in ``[0, 1]``), ``"action"``
        ``[B, T, A]``, and ``"is_init"`` ``[B, T, 1]`` bool: where set, both branches' states and the action
        fed to the transition are zeroed at that step (an episode starts inside the window). Every window
        starts from zero states.

    Writes (under ``"next"``, ``[B, T, ...]``):
        controllable branch ``state`` s_t, ``belief`` h_t, ``prior_state`` s~_t, ``prior_mean``,
        ``prior_std``, ``posterior_mean``, ``posterior_std`` (each ``[..., S]`` or ``[..., D]``); the same
        with a ``free_`` prefix for the noncontrollable branch (z_t, h'_t); ``reco_pixels`` (eq. 4),
        ``reco_control``, ``reco_free`` ``[..., 3, 64, 64]``; ``mask_control``, ``mask_free``,
        ``mask_static`` ``[..., 1, 64, 64]``; ``reward_pred`` ``[..., 1]``;
        ``discount_logit`` ``[..., 1]`` (with the discount head); ``action_pred`` ``[..., A]`` with
        ``action_pred_valid`` ``[..., 1]`` (step 0 and reset steps have no previous state in the window). The
        root gets ``"background"`` o^b ``[B, T, 3, 64, 64]`` (one image per window, expanded over ``T``).
        Images are in ``[-0.5, 0.5]`` space, the targets' ``x / 255 - 0.5``.

    ``config.fast_paths`` picks, once, how the decoders, the composition and the filter are computed: the CPU
    fast paths of :mod:`~isodream_rl.modules.fast_paths` (``True``) or the reference forms (``False``:
    :class:`~isodream_rl.modules.isodream_v2.decoder.ConvDecoder`, :class:`~isodream_rl.modules.composition.MaskComposition`,
    :func:`~isodream_rl.modules.isodream_v2.rssm.filter_window`). Both have the same parameters and state dict and give the
    same values and gradients within float tolerance.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from isodream_rl.modules import IsoDreamV2WorldModel, IsoDreamV2Config
        >>> wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
        >>> td = TensorDict({"action": torch.zeros(2, 5, 2), "is_init": torch.zeros(2, 5, 1, dtype=torch.bool),
        ...                  ("next", "pixels"): torch.zeros(2, 5, 3, 64, 64, dtype=torch.uint8)}, [2, 5])
        >>> wm(td)["next", "reco_pixels"].shape
        torch.Size([2, 5, 3, 64, 64])
    """

    def __init__(
        self, config: IsoDreamV2Config, *, device: torch.device | str | None = None, check_inputs: bool = True
    ):
        super().__init__()
        self.config = cfg = config
        self.check_inputs = check_inputs
        fast = cfg.fast_paths
        decoder_class = FastConvDecoder if fast else ConvDecoder
        heads = (
            ("control",) + (("free",) if cfg.free_branch else ()) + (("static",) if cfg.static_branch else ())
        )
        self.encoder = BranchedEncoder(depth=cfg.depth, heads=heads, device=device)
        embed = self.encoder.embed_dim
        rssm_kwargs = {
            "state_dim": cfg.state_dim,
            "belief_dim": cfg.belief_dim,
            "hidden_dim": cfg.hidden_dim,
            "embed_dim": embed,
            "min_std": cfg.min_std,
            "layer_norm_gru": cfg.layer_norm_gru,
            "device": device,
        }
        self.control_rssm = ActionConditionedRSSM(action_dim=cfg.action_dim, **rssm_kwargs)
        self.free_rssm = ActionFreeRSSM(**rssm_kwargs) if cfg.free_branch else None
        # the joint filter of both branches over a window (eq. 3), called as filter_window(control, free, ...)
        self.filter_window = fast_filter_window if fast else filter_window
        feature_dim = cfg.state_dim + cfg.belief_dim
        single = not (cfg.free_branch or cfg.static_branch)
        # A lone controllable branch needs no mask channel: it is the whole image (DreamerV2).
        self.control_decoder = decoder_class(
            in_features=feature_dim, out_channels=3 if single else 4, depth=cfg.depth, device=device
        )
        self.free_decoder = (
            decoder_class(in_features=feature_dim, out_channels=4, depth=cfg.depth, device=device)
            if cfg.free_branch
            else None
        )
        # The static branch has a mask logit of its own only in softmax mode.
        self.static_decoder = (
            decoder_class(
                in_features=cfg.static_frames * embed,
                out_channels=4 if cfg.mask_mode == "softmax" else 3,
                depth=cfg.depth,
                device=device,
            )
            if cfg.static_branch
            else None
        )
        if cfg.static_mask_bias and cfg.static_branch and cfg.mask_mode == "softmax":
            self.shift_static_mask_bias(cfg.static_mask_bias)
        self.composition = (FusedMaskComposition if fast else MaskComposition)(
            mask_mode=cfg.mask_mode,
            clamp_components=cfg.clamp_components,
            clamp_gradient=cfg.clamp_gradient,
        )
        self.inverse_cell = (
            InverseDynamicsCell(
                in_features=cfg.state_dim if cfg.inverse_input == "state" else embed,
                action_dim=cfg.action_dim,
                inverse_input=cfg.inverse_input,
                num_cells=cfg.units,
                device=device,
            )
            if cfg.inverse_dynamics
            else None
        )
        self.reward_head = make_reward_head(
            in_features=self.reward_feature_dim, num_cells=cfg.units, device=device
        )
        self.discount_head = (
            make_discount_head(in_features=self.reward_feature_dim, num_cells=cfg.units, device=device)
            if cfg.discount_head
            else None
        )
        if cfg.channels_last:
            for module in (self.encoder, self.control_decoder, self.free_decoder, self.static_decoder):
                if module is not None:
                    module.to(memory_format=torch.channels_last)

        self.in_keys = [_next("pixels"), "action", "is_init"]
        out = ["state", "belief", "prior_state", "prior_mean", "prior_std", "posterior_mean", "posterior_std"]
        if cfg.free_branch:
            out += [f"free_{k}" for k in out]
        out += ["reco_pixels", "reco_control", "mask_control", "reward_pred"]
        if cfg.free_branch:
            out += ["reco_free", "mask_free"]
        if cfg.static_branch:
            out += ["mask_static"]
        if cfg.discount_head:
            out += ["discount_logit"]
        if cfg.inverse_dynamics:
            out += ["action_pred", "action_pred_valid"]
        self.out_keys = [_next(k) for k in out] + (["background"] if cfg.static_branch else [])

    # ------------------------------------------------------------------ helpers used by other modules
    @property
    def reward_feature_dim(self) -> int:
        cfg = self.config
        return (2 if cfg.reward_uses_free else 1) * (cfg.state_dim + cfg.belief_dim)

    def autocast(self, device_type: str):
        """The autocast context of ``config.precision`` (bf16 for convolutions and MLPs), or a no-op."""
        if self.config.precision == "bf16":
            return torch.autocast(device_type=device_type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def shift_static_mask_bias(self, delta: float) -> None:
        """Add ``delta`` to the bias of the background's mask logit (softmax mode), in place.

        The constructor applies ``config.static_mask_bias`` this way. The bias stays a learned parameter.

        Raises:
            ValueError: without the static branch or outside softmax mode (the background has no logit).
        """
        if self.static_decoder is None or self.config.mask_mode != "softmax":
            raise ValueError("the background's mask logit exists only with the static branch in softmax mode")
        with torch.no_grad():
            self.static_decoder.deconv[-1].bias[3] += delta

    def encode(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``[*N, 3, 64, 64]`` -> ``(e^s, e^z)`` each ``[*N, E]`` (``e^z`` is ``None`` without the free branch)."""
        embeddings = self.encoder(pixels, channels_last=self.config.channels_last)
        return embeddings[0], (embeddings[1] if self.free_rssm is not None else None)

    def reward_features(
        self,
        state: torch.Tensor,
        belief: torch.Tensor,
        free_state: torch.Tensor | None = None,
        free_belief: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``[s, h]`` or ``[s, h, z, h']`` (``reward_uses_free``), the input of the reward/discount heads."""
        parts = [state, belief]
        if self.config.reward_uses_free:
            parts += [free_state, free_belief]
        return torch.cat(parts, dim=-1)

    def initial_state(self, batch_shape, *, device=None) -> dict[str, torch.Tensor]:
        """Zero ``state``, ``belief`` (and ``free_state``, ``free_belief``) of batch shape ``batch_shape``."""
        state, belief = self.control_rssm.initial(batch_shape, device=device)
        out = {"state": state, "belief": belief}
        if self.free_rssm is not None:
            out["free_state"], out["free_belief"] = self.free_rssm.initial(batch_shape, device=device)
        return out

    # ------------------------------------------------------------------ forward over a replay window
    def _get(self, tensordict: TensorDictBase, key):
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"IsoDreamV2WorldModel needs the key {key!r} in its input tensordict; "
                f"found {sorted(map(str, tensordict.keys(True, True)))}"
            )
        return value

    def _check_inputs(self, tensordict: TensorDictBase):
        if tensordict.batch_dims != 2:
            raise ValueError(
                f"IsoDreamV2WorldModel expects a [B, T] tensordict (replay windows), got batch_size "
                f"{tuple(tensordict.batch_size)}; reshape flat samples with td.reshape(-1, T)"
            )
        pixels = self._get(tensordict, _next("pixels"))
        check_pixels(pixels, name="('next', 'pixels')")
        action = self._get(tensordict, "action")
        if action.shape[-1] != self.config.action_dim or action.dim() != 3:
            raise ValueError(
                f"'action' must have shape [B, T, {self.config.action_dim}] for this world model, "
                f"got {tuple(action.shape)}"
            )
        is_init = tensordict.get("is_init", None)
        if is_init is not None and is_init.shape[-1:] != (1,):
            raise ValueError(f"'is_init' must have shape [B, T, 1], got {tuple(is_init.shape)}")
        if self.check_inputs:
            if tensordict.batch_size[1] < 2:
                raise ValueError(
                    f"IsoDreamV2WorldModel needs windows of at least 2 steps (the inverse-dynamics cell reads step "
                    f"pairs; one step teaches no dynamics), got T={tensordict.batch_size[1]}: sample longer windows"
                )
            if is_init is None:
                raise ValueError(
                    "IsoDreamV2WorldModel needs 'is_init' [B, T, 1] bool (True where an episode starts; TorchRL's "
                    "InitTracker writes it): without it windows never reset. Pass torch.zeros(B, T, 1, "
                    "dtype=torch.bool) for windows inside one episode"
                )
            check_pixel_values(pixels, name="('next', 'pixels')")
            if not bool(torch.isfinite(action).all()):
                raise ValueError("'action' holds NaN or inf values: check the policy or the replay data")
        return pixels, action.float(), is_init

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        cfg = self.config
        pixels, action, is_init = self._check_inputs(tensordict)
        batch, time = action.shape[:2]
        device_type = pixels.device.type
        with self.autocast(device_type):
            frames = pixels.reshape(-1, *IMAGE_SHAPE)
            features = self.encoder.trunk_features(frames, channels_last=cfg.channels_last)
            control_embed = self.encoder.head("control", features).reshape(batch, time, -1)
            control_proj = self.control_rssm.project_embedding(control_embed)
            free_proj = None
            if self.free_rssm is not None:
                free_embed = self.encoder.head("free", features).reshape(batch, time, -1)
                free_proj = self.free_rssm.project_embedding(free_embed)
            static_out = None
            if self.static_decoder is not None:
                static_out = self.static_background(features.reshape(batch, time, *features.shape[1:]))
        latents = self.filter_window(
            self.control_rssm,
            self.free_rssm,
            control_proj.float(),
            None if free_proj is None else free_proj.float(),
            action,
            is_init,
        )

        control_input = latents["prior_state" if cfg.decoder_input == "paper" else "state"]
        control_feat = torch.cat([control_input, latents["belief"]], dim=-1).reshape(batch * time, -1)
        with self.autocast(device_type):
            control_out = self.control_decoder(control_feat)
            free_out = None
            if self.free_decoder is not None:
                free_input = latents[
                    "free_prior_state" if cfg.free_decoder_input == "prior" else "free_state"
                ]
                free_feat = torch.cat([free_input, latents["free_belief"]], dim=-1).reshape(batch * time, -1)
                free_out = self.free_decoder(free_feat)

        # in the decoders' dtype: the composition reads bf16 outputs as they are and composes in float32
        decoded = {"control": control_out.reshape(batch, time, *control_out.shape[1:])}
        if free_out is not None:
            decoded["free"] = free_out.reshape(batch, time, *free_out.shape[1:])
        if static_out is not None:
            decoded["static"] = static_out[:, None]
        composite, masks, colors = self.composition.compose_decoded(decoded)

        out = dict(latents)
        out["reco_pixels"] = composite
        out["reco_control"] = colors["control"]
        if "free" in colors:
            out["reco_free"] = colors["free"]
        for name, mask in masks.items():
            out[f"mask_{name}"] = mask
        features_r = self.reward_features(
            latents["state"], latents["belief"], latents.get("free_state"), latents.get("free_belief")
        )
        with self.autocast(device_type):
            out["reward_pred"] = self.reward_head(features_r).float()
            if self.discount_head is not None:
                out["discount_logit"] = self.discount_head(features_r).float()
            if self.inverse_cell is not None:
                if cfg.inverse_input == "state":
                    sequence = latents["state"]
                else:
                    sequence = control_embed.float()
                predicted = self.inverse_cell(sequence[:, :-1], sequence[:, 1:]).float()
        if self.inverse_cell is not None:
            out["action_pred"] = torch.cat([torch.zeros_like(predicted[:, :1]), predicted], dim=1)
            valid = torch.ones(batch, time, 1, dtype=torch.bool, device=action.device)
            valid[:, 0] = False
            if is_init is not None:
                valid &= ~is_init.bool()
            out["action_pred_valid"] = valid
        tensordict.update({_next(k): v for k, v in out.items()})
        if static_out is not None:
            tensordict.set("background", colors["static"].expand(batch, time, -1, -1, -1))
        return tensordict

    def static_background(self, features: torch.Tensor) -> torch.Tensor:
        """``Dec_phi3(Enc_{theta,phi3}(o_{1:K}))`` (eq. 4): one background ``[B, C, 64, 64]`` per window.

        ``features``: trunk features ``[B, T, C', 14, 14]``. Windows shorter than K repeat their last frame.
        """
        batch, time = features.shape[:2]
        k = self.config.static_frames
        frames = features[:, : min(k, time)]
        if time < k:
            frames = torch.cat([frames, frames[:, -1:].expand(batch, k - time, *frames.shape[2:])], dim=1)
        embed = self.encoder.head("static", frames.reshape(batch * k, *frames.shape[2:]))
        return self.static_decoder(embed.reshape(batch, -1))
