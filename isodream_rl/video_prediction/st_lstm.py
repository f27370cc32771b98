"""Spatiotemporal LSTM cells (PredRNN-v2) and their action-conditioned variant.

Reference: Wang et al., "PredRNN: A Recurrent Neural Network for Spatiotemporal Predictive Learning",
TPAMI 2022 (https://arxiv.org/abs/2103.09504); Iso-Dream, NeurIPS 2022, Sec. 4.4 and Appendix D.

TorchRL has no convolutional recurrent cell, hence these.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["SpatioTemporalLSTMCell", "ActionConditionedSTLSTMCell", "STLSTMState"]

STLSTMState = tuple[torch.Tensor, torch.Tensor]  # (h, c), each [B, hidden, H, W]


class SpatioTemporalLSTMCell(nn.Module):
    """One ST-LSTM layer: a temporal memory ``c`` and a spatiotemporal memory ``m`` that zig-zags
    through the layers of a stack.

    With ``x`` the input, ``h`` the hidden state, ``c`` the temporal memory and ``m`` the spatiotemporal
    memory (all ``[B, C, H, W]``)::

        i, f, g  = sigma(Wx x + Wh h),  c' = f * c + i * g              (delta_c = i * g)
        i', f', g' = sigma(W'x x + Wm m),  m' = f' * m + i' * g'        (delta_m = i' * g')
        o = sigma(Wox x + Woh h + Wo [c', m']),  h' = o * tanh(W1x1 [c', m'])

    ``delta_c`` and ``delta_m`` are returned for PredRNN-v2's decoupling loss, which keeps the two
    memories from learning the same thing.

    Args:
        in_channels: channels of ``x``.
        hidden_channels: channels of ``h``, ``c`` and ``m``.
        kernel_size: side of the square convolution kernels (odd).
        forget_bias: added to both forget gates' pre-activations, as in PredRNN.

    Examples:
        >>> cell = SpatioTemporalLSTMCell(in_channels=8, hidden_channels=16, kernel_size=3)
        >>> x = torch.zeros(2, 8, 16, 16)
        >>> h, c, m, dc, dm = cell(x, cell.initial_state(x), torch.zeros(2, 16, 16, 16))
        >>> h.shape
        torch.Size([2, 16, 16, 16])
    """

    def __init__(
        self, *, in_channels: int, hidden_channels: int, kernel_size: int = 5, forget_bias: float = 1.0
    ) -> None:
        super().__init__()
        if kernel_size % 2 != 1:
            raise ValueError(f"kernel_size must be odd to keep the spatial size, got {kernel_size}")
        pad = kernel_size // 2
        self.hidden_channels = hidden_channels
        self.forget_bias = forget_bias
        self.conv_x = nn.Conv2d(in_channels, 7 * hidden_channels, kernel_size, padding=pad)
        self.conv_h = nn.Conv2d(hidden_channels, 4 * hidden_channels, kernel_size, padding=pad)
        self.conv_m = nn.Conv2d(hidden_channels, 3 * hidden_channels, kernel_size, padding=pad)
        self.conv_o = nn.Conv2d(2 * hidden_channels, hidden_channels, kernel_size, padding=pad)
        self.conv_last = nn.Conv2d(2 * hidden_channels, hidden_channels, 1)

    def initial_state(self, x: torch.Tensor) -> STLSTMState:
        """Zero ``(h, c)`` matching ``x``'s batch, spatial size, dtype and device."""
        zeros = x.new_zeros(x.shape[0], self.hidden_channels, *x.shape[-2:])
        return zeros, zeros.clone()

    def _hidden_term(self, h: torch.Tensor, action: torch.Tensor | None) -> torch.Tensor:
        if action is not None:
            raise ValueError("SpatioTemporalLSTMCell takes no action; use ActionConditionedSTLSTMCell")
        return self.conv_h(h)

    def forward(
        self, x: torch.Tensor, state: STLSTMState, m: torch.Tensor, action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step.

        Args:
            x: input ``[B, C_in, H, W]``.
            state: ``(h, c)``, each ``[B, C, H, W]``.
            m: spatiotemporal memory ``[B, C, H, W]`` (from the layer below, or the top layer at the
                previous step).
            action: only for :class:`ActionConditionedSTLSTMCell`.

        Returns:
            ``(h', c', m', delta_c, delta_m)``, each ``[B, C, H, W]``.
        """
        h, c = state
        i_x, f_x, g_x, i_xm, f_xm, g_xm, o_x = self.conv_x(x).chunk(7, dim=1)
        i_h, f_h, g_h, o_h = self._hidden_term(h, action).chunk(4, dim=1)
        i_m, f_m, g_m = self.conv_m(m).chunk(3, dim=1)

        delta_c = torch.sigmoid(i_x + i_h) * torch.tanh(g_x + g_h)
        c = torch.sigmoid(f_x + f_h + self.forget_bias) * c + delta_c
        delta_m = torch.sigmoid(i_xm + i_m) * torch.tanh(g_xm + g_m)
        m = torch.sigmoid(f_xm + f_m + self.forget_bias) * m + delta_m

        memory = torch.cat([c, m], dim=1)
        o = torch.sigmoid(o_x + o_h + self.conv_o(memory))
        h = o * torch.tanh(self.conv_last(memory))
        return h, c, m, delta_c, delta_m


class ActionConditionedSTLSTMCell(SpatioTemporalLSTMCell):
    """ST-LSTM whose hidden-state gate term is modulated by the action: ``(Wh * h) ⊙ (Wa a)``.

    In Iso-Dream the action is tiled over the image and convolved to a feature map; away from the
    zero-padded borders that map is constant in space, so here the action embedding is a per-channel
    gain broadcast over space, computed by a linear layer (same function, without the convolutions).

    Args:
        in_channels, hidden_channels, kernel_size, forget_bias: as :class:`SpatioTemporalLSTMCell`.
        action_channels: width of the action embedding passed to :meth:`forward`.
    """

    def __init__(
        self,
        *,
        in_channels: int,
        hidden_channels: int,
        action_channels: int,
        kernel_size: int = 5,
        forget_bias: float = 1.0,
    ) -> None:
        super().__init__(
            in_channels=in_channels,
            hidden_channels=hidden_channels,
            kernel_size=kernel_size,
            forget_bias=forget_bias,
        )
        self.action_gain = nn.Linear(action_channels, 4 * hidden_channels)
        # Start as the plain cell (unit gain) so the action only has to learn a modulation.
        nn.init.ones_(self.action_gain.bias)

    def _hidden_term(self, h: torch.Tensor, action: torch.Tensor | None) -> torch.Tensor:
        if action is None:
            raise ValueError("ActionConditionedSTLSTMCell needs an action embedding [B, action_channels]")
        return self.conv_h(h) * self.action_gain(action)[:, :, None, None]
