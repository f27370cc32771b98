"""Iso-Dream's three-branch action-conditioned video predictor (Sec. 4.4, Appendix D).

Reference: Pan et al., "Iso-Dream: Isolating and Leveraging Noncontrollable Visual Dynamics in World
Models", NeurIPS 2022 (https://arxiv.org/abs/2205.13817).
"""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F
from torch import nn

from isodream_rl.video_prediction.config import PredictorConfig
from isodream_rl.video_prediction.inverse_dynamics import ActionInverseCell
from isodream_rl.video_prediction.st_lstm import ActionConditionedSTLSTMCell, SpatioTemporalLSTMCell

__all__ = ["ThreeBranchPredictor"]


class _Branch(nn.Module):
    """Head convolution, a stack of ST-LSTM layers, a decoupling adapter and a decoder."""

    def __init__(self, config: PredictorConfig, *, action_conditioned: bool, out_channels: int) -> None:
        super().__init__()
        c1, c2 = config.encoder_channels
        hidden, k = config.hidden_channels, config.kernel_size
        self.head = nn.Conv2d(c2, c2, k, padding=k // 2)
        modulate = action_conditioned and config.action_conditioning == "modulate"
        self.modulated = modulate
        cells = []
        for layer in range(config.num_layers):
            kwargs = dict(
                in_channels=c2 if layer == 0 else hidden,
                hidden_channels=hidden,
                kernel_size=k,
                forget_bias=config.forget_bias,
            )
            if modulate:
                cells.append(ActionConditionedSTLSTMCell(action_channels=config.action_embedding, **kwargs))
            else:
                cells.append(SpatioTemporalLSTMCell(**kwargs))
        self.cells = nn.ModuleList(cells)
        # PredRNN-v2: the decoupling loss compares the memory increments after this 1x1 adapter.
        self.adapter = nn.Conv2d(hidden, hidden, 1, bias=False)
        self.decoder = nn.Sequential(
            nn.ConvTranspose2d(hidden, c1, 4, stride=2, padding=1),
            nn.LeakyReLU(0.2),
            nn.ConvTranspose2d(c1, out_channels, 4, stride=2, padding=1),
        )
        if config.mask_composition:
            # Start close to "copy the previous frame" (static mask ~0.9): a sensible prediction from
            # the first update, which the branches then have to improve on.
            with torch.no_grad():
                self.decoder[-1].bias[-1] = -3.0

    def step(self, x, states, m, action):
        """One step of the stack; returns the top hidden state, new states, m and the decoupling term."""
        new_states, decouple = [], x.new_zeros(())
        for cell, state in zip(self.cells, states):
            h, c, m, delta_c, delta_m = cell(x, state, m, action if self.modulated else None)
            new_states.append((h, c))
            a = F.normalize(self.adapter(delta_c).flatten(2), dim=2)
            b = F.normalize(self.adapter(delta_m).flatten(2), dim=2)
            decouple = decouple + (a * b).sum(2).abs().mean()
            x = h
        return x, new_states, m, decouple / len(self.cells)


def _at_least_fp32(x: torch.Tensor) -> torch.Tensor:
    """``x`` in fp32 if it is in a narrower float type (bf16 under autocast), else unchanged."""
    return x.to(torch.promote_types(x.dtype, torch.float32))


class ThreeBranchPredictor(nn.Module):
    """Action-conditioned video predictor with controllable, noncontrollable and static branches.

    * a shared encoder (two stride-2 convolutions, ``H x W -> H/4 x W/4``) and per-branch heads;
    * the action-conditioned branch: ST-LSTM layers whose hidden-state term is gated by the action;
    * the action-free branch: plain ST-LSTM layers; during the closed-loop rollout its input is its own
      masked output, so it cannot read the controllable part of the scene;
    * the static branch: the previous frame (observed, then predicted);
    * each branch decodes RGB plus a mask logit, and the frame is composed as in eq. 4,
      ``x_{t+1} = M^s * x^s + M^z * x^z + (1 - M^s - M^z) * x_t``, with the masks a softmax over the two
      logits and a zero logit for the static branch (so they are non-negative and sum to one);
    * the inverse-dynamics cell regresses ``a_t`` from action-branch features of ``x_{t+1}`` minus those
      of the branch input at ``t`` (training signal only).

    ``config.channels_last`` and ``config.precision`` set how it runs (channels-last convolutions; bf16
    autocast with fp32 memories and outputs), not what it computes.

    Frames ``0 .. context-1`` are observed; afterwards the model feeds back its own predictions (no
    scheduled sampling, as in the authors' code), so training back-propagates through the rollout.

    Args:
        config: sizes and variant switches (see :func:`~isodream_rl.video_prediction.config.variant_config`).

    Examples:
        >>> from isodream_rl.video_prediction.config import variant_config
        >>> model = ThreeBranchPredictor(config=variant_config("isodream", hidden_channels=8,
        ...     encoder_channels=(8, 8), kernel_size=3))
        >>> out = model(torch.rand(2, 5, 3, 32, 32), torch.rand(2, 5, 4), context=2)
        >>> out["frames"].shape
        torch.Size([2, 4, 3, 32, 32])
    """

    def __init__(self, *, config: PredictorConfig) -> None:
        super().__init__()
        self.config = config
        c1, c2 = config.encoder_channels
        self.encoder = nn.Sequential(
            nn.Conv2d(config.image_channels, c1, 5, stride=2, padding=2),
            nn.LeakyReLU(0.2),
            nn.Conv2d(c1, c2, 5, stride=2, padding=2),
        )
        self.action_encoder = nn.Sequential(
            nn.Linear(config.action_dim, config.action_embedding),
            nn.LeakyReLU(0.2),
            nn.Linear(config.action_embedding, config.action_embedding),
        )
        if config.action_conditioning == "concat":
            self.action_to_input = nn.Linear(config.action_embedding, c2)
        out = config.image_channels + (1 if config.mask_composition else 0)
        self.control = _Branch(config, action_conditioned=True, out_channels=out)
        self.free = (
            _Branch(config, action_conditioned=False, out_channels=out) if config.action_free_branch else None
        )
        self.inverse = (
            ActionInverseCell(in_channels=c2, action_dim=config.action_dim)
            if config.inverse_dynamics
            else None
        )

    def autocast(self, device_type: str) -> contextlib.AbstractContextManager:
        """The autocast context of ``config.precision`` (bf16 for convolutions and linear layers), or a no-op."""
        if self.config.precision == "bf16":
            return torch.autocast(device_type=device_type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _layout(self, images: torch.Tensor) -> torch.Tensor:
        """``[N, C, H, W]`` images in the layout of ``config.channels_last``."""
        if self.config.channels_last:
            return images.contiguous(memory_format=torch.channels_last)
        return images

    def _init_states(self, branch: _Branch, feat: torch.Tensor):
        # fp32 zeros even under autocast, so that the memories c and m accumulate in fp32.
        states = [
            tuple(self._layout(_at_least_fp32(s)) for s in cell.initial_state(feat)) for cell in branch.cells
        ]
        return states, states[0][0].clone()

    def forward(
        self,
        frames: torch.Tensor,
        actions: torch.Tensor,
        *,
        context: int = 2,
        return_components: bool = False,
    ) -> dict[str, torch.Tensor]:
        """Predict frames ``1 .. T-1`` from the first ``context`` frames and all actions.

        Args:
            frames: ``[B, T, C, H, W]`` in ``[0, 1]``; only ``frames[:, :context]`` are inputs, the rest
                are targets (and inverse-dynamics inputs, which affect losses only).
            actions: ``[B, T, A]``; ``actions[:, t]`` moves frame ``t`` to ``t + 1``.
            context: observed frames (2 in the BAIR/RoboNet protocols).
            return_components: also return each branch's RGB and the masks (for showcases).

        Returns:
            A dict with ``"frames"`` ``[B, T-1, C, H, W]`` (prediction of frames ``1 .. T-1``; the first
            ``context - 1`` are one-step predictions from observed frames), ``"decouple"`` (scalar
            PredRNN-v2 decoupling term summed over branches), and if the inverse cell exists
            ``"action_pred"`` ``[B, T-1, A]``. With ``return_components``: ``"reco_control"``,
            ``"reco_free"``, ``"mask_control"``, ``"mask_free"``, ``"mask_static"`` (``[B, T-1, C|1, H, W]``;
            only those that exist).
        """
        if frames.ndim != 5 or actions.ndim != 3 or frames.shape[:2] != actions.shape[:2]:
            raise ValueError(
                f"expected frames [B, T, C, H, W] and actions [B, T, A], got {frames.shape}, {actions.shape}"
            )
        if actions.shape[-1] != self.config.action_dim:
            raise ValueError(
                f"actions have {actions.shape[-1]} dims, config.action_dim={self.config.action_dim}"
            )
        steps = frames.shape[1]
        if not 1 <= context < steps:
            raise ValueError(f"context must be in [1, T-1] = [1, {steps - 1}], got {context}")
        with self.autocast(frames.device.type):
            out = self._rollout(frames, actions, context=context, return_components=return_components)
        # Under bf16 autocast some outputs are bf16; callers (losses, metrics) get fp32.
        return {k: _at_least_fp32(v) for k, v in out.items()}

    def _rollout(
        self, frames: torch.Tensor, actions: torch.Tensor, *, context: int, return_components: bool
    ) -> dict[str, torch.Tensor]:
        batch, steps = frames.shape[:2]
        # The observed frames are encoded in one batched call; the rollout encodes one frame per step.
        observed = self.encoder(self._layout(frames[:, :context].flatten(0, 1)))
        observed = observed.unflatten(0, (batch, context))
        act = self.action_encoder(actions)

        ctrl_states, ctrl_m = self._init_states(self.control, observed[:, 0])
        if self.free is not None:
            free_states, free_m = self._init_states(self.free, observed[:, 0])
        decouple = frames.new_zeros(())
        outputs: dict[str, list[torch.Tensor]] = {"frames": [], "control_inputs": []}
        prev_frame, feat, free_feat = frames[:, 0], observed[:, 0], observed[:, 0]
        for t in range(steps - 1):
            if t < context:
                prev_frame, feat = frames[:, t], observed[:, t]
                free_feat = feat
            ctrl_in = self.control.head(feat)
            outputs["control_inputs"].append(ctrl_in)
            if self.config.action_conditioning == "concat":
                ctrl_in = ctrl_in + self.action_to_input(act[:, t])[:, :, None, None]
            top, ctrl_states, ctrl_m, d = self.control.step(ctrl_in, ctrl_states, ctrl_m, act[:, t])
            decouple = decouple + d
            ctrl_out = self.control.decoder(top)
            free_part = None
            if not self.config.mask_composition:
                prediction = self._rgb(ctrl_out)
            else:
                rgb_c, logits, rgb_f = self._rgb(ctrl_out[:, :-1]), [ctrl_out[:, -1:]], None
                if self.free is not None:
                    top_f, free_states, free_m, d = self.free.step(
                        self.free.head(free_feat), free_states, free_m, None
                    )
                    decouple = decouple + d
                    free_out = self.free.decoder(top_f)
                    rgb_f = self._rgb(free_out[:, :-1])
                    logits.append(free_out[:, -1:])
                masks = torch.softmax(torch.cat([*logits, torch.zeros_like(logits[0])], dim=1), dim=1)
                prediction = masks[:, :1] * rgb_c + masks[:, -1:] * prev_frame
                if rgb_f is not None:
                    free_part = masks[:, 1:2] * rgb_f
                    prediction = prediction + free_part
                if return_components:
                    self._record(outputs, rgb_c, masks, rgb_f)
            outputs["frames"].append(prediction)
            prev_frame = prediction
            if context <= t + 1 < steps - 1:
                # Closed loop from here: encode the prediction (and the free branch's own output, its
                # next input) in one call.
                if free_part is None:
                    feat = self.encoder(prediction)
                else:
                    feat, free_feat = self.encoder(torch.cat([prediction, free_part])).chunk(2)

        result = {k: torch.stack(v, 1) for k, v in outputs.items() if k != "control_inputs"}
        result["decouple"] = decouple / (steps - 1)
        if self.inverse is not None:
            result["action_pred"] = self._inverse(frames, torch.stack(outputs["control_inputs"], 1))
        return result

    def _rgb(self, x: torch.Tensor) -> torch.Tensor:
        """A branch's decoded RGB, bounded to ``[0, 1]`` unless ``config.rgb_activation == "linear"``."""
        return torch.sigmoid(x) if self.config.rgb_activation == "sigmoid" else x

    @staticmethod
    def _record(outputs, rgb_c, masks, rgb_f) -> None:
        outputs.setdefault("reco_control", []).append(rgb_c)
        outputs.setdefault("mask_control", []).append(masks[:, :1])
        outputs.setdefault("mask_static", []).append(masks[:, -1:])
        if rgb_f is not None:
            outputs.setdefault("reco_free", []).append(rgb_f)
            outputs.setdefault("mask_free", []).append(masks[:, 1:2])

    def _inverse(self, frames: torch.Tensor, control_inputs: torch.Tensor) -> torch.Tensor:
        batch, steps = control_inputs.shape[:2]
        targets = self.control.head(self.encoder(self._layout(frames[:, 1 : steps + 1].flatten(0, 1))))
        delta = targets - control_inputs.flatten(0, 1)
        return self.inverse(delta).unflatten(0, (batch, steps))
