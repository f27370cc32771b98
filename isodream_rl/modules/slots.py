"""Object slots for the noncontrollable decoder ``Dec_phi2`` (an option outside the paper).

The paper decodes the noncontrollable features into one RGB component and one mask logit (eq. 4). With
``WorldModelConfig(free_slots=K)``, ``K > 1``, the features are first projected to ``K`` slot latents, one
decoder with shared weights turns each into an RGB component and a mask logit, and the slots are combined
into the branch's component and logit:

``l^z = logsumexp_k l_k``, ``o^z = sum_k softmax_k(l)_k * o_k``.

In softmax mode this is exactly a softmax over ``2 + K`` logits (controllable, ``K`` slots, background):
``M^z o^z = sum_k M_k o_k`` with ``M_k = exp(l_k) / (exp(l^s) + sum_j exp(l_j) + exp(l^b))``, and
``M^z = sum_k M_k``. So everything downstream (composition, losses, pictures, open-loop predictions) sees one
noncontrollable component and mask, as in the paper; the per-slot masks are extra outputs.

Why it was tried: on the sprites scene the single decoder draws one moving object at a position read from
``z`` and at most reuses that pathway for a second (two discs drawn as one blob). A decoder shared by the
slots learns "a slot latent -> an object at its position" once, for every slot, so a second object would
need only a second slot latent. Measured there (docs/results/world_model_demo.md, session 12): it does not
add a disc; two slots split the one disc the branch draws and the third stays empty. The limit is upstream:
the noncontrollable encoder head passes on only that disc.
"""

from __future__ import annotations

import torch
from torch import nn

from isodream_rl.modules.composition import _InwardClamp
from isodream_rl.modules.decoder import ConvDecoder


class SlotDecoder(nn.Module):
    """``K`` object slots decoded by one shared :class:`ConvDecoder` and combined into one RGB + logit map.

    Args:
        in_features: width of the branch's features ``[z_t, h'_t]``.
        num_slots: ``K`` (>= 2).
        slot_features: width of each slot latent (default: ``in_features``).
        depth: the decoder's channel depth (as :class:`ConvDecoder`).
        clamp: ``(low, high)``: each slot's colour is clamped to this range before the slots are mixed, as
            :class:`~isodream_rl.modules.composition.MaskComposition` clamps branch components (``None``: no
            clamp).
        inward: the clamp's backward passes the gradients that move an out-of-range colour back (see
            ``WorldModelConfig.clamp_gradient``).
        device: where to create the parameters.

    Shapes:
        ``forward``: ``[N, in_features]`` -> ``[N, 4, 64, 64]`` (RGB, then the combined logit), the form of a
        :class:`ConvDecoder` with 4 output channels. ``decompose`` also returns the slots' weights within the
        branch, ``softmax_k(l)``, ``[N, K, 1, 64, 64]``.
    """

    def __init__(
        self,
        *,
        in_features: int,
        num_slots: int,
        slot_features: int | None = None,
        depth: int = 32,
        clamp: tuple[float, float] | None = None,
        inward: bool = False,
        device=None,
    ):
        super().__init__()
        if num_slots < 2:
            raise ValueError(f"SlotDecoder needs num_slots >= 2, got {num_slots} (1 slot: use ConvDecoder)")
        self.in_features = in_features
        self.num_slots = num_slots
        self.slot_features = slot_features or in_features
        self.clamp = clamp
        self.inward = inward
        self.project = nn.Linear(in_features, num_slots * self.slot_features, device=device)
        self.decoder = ConvDecoder(in_features=self.slot_features, out_channels=4, depth=depth, device=device)

    def decompose(self, latent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(combined [N, 4, H, W], weights [N, K, 1, H, W])`` for features ``[N, in_features]``."""
        if latent.dim() != 2 or latent.shape[-1] != self.in_features:
            raise ValueError(
                f"SlotDecoder expects features [N, {self.in_features}], got {tuple(latent.shape)}"
            )
        n, k = latent.shape[0], self.num_slots
        slots = self.project(latent).reshape(n * k, self.slot_features)
        decoded = self.decoder(slots)
        channels_last = decoded.is_contiguous(memory_format=torch.channels_last)
        decoded = decoded.reshape(n, k, *decoded.shape[1:])
        colors, logits = decoded[:, :, :3], decoded[:, :, 3:]
        if self.clamp is not None:
            colors = _InwardClamp.apply(colors, *self.clamp) if self.inward else colors.clamp(*self.clamp)
        weights = torch.softmax(logits, dim=1)
        combined_color = (weights * colors).sum(1)
        combined_logit = torch.logsumexp(logits, dim=1)
        out = torch.cat([combined_color, combined_logit], dim=1)
        if channels_last:  # the composition reads the decoders' layout
            out = out.contiguous(memory_format=torch.channels_last)
        return out, weights

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return self.decompose(latent)[0]
