"""Future-state attention (paper eq. 6) and the input ``e_t`` of the actor and value models (eq. 7).

``e_t = Attention(s~_t, z~_{t:t+tau})``: the controllable features ``[s, h]`` query a window of ``tau``
noncontrollable features ``[z, h']`` (the current one and ``tau - 1`` predicted ones). As in the authors'
code the attention has learned query/key/value projections of width 500, a scaled dot product, a softmax
over the window, an output projection and the residual ``e = o + q``; ``projections=False`` is the
paper's literal ``e = softmax(s z^T) z + s``.

The projected form is evaluated without projecting the window: ``(W_q q) . (W_k z_i)`` equals
``((W_q q) W_k) . z_i``, and ``sum_i a_i (W_v z_i + b_v) = W_v (sum_i a_i z_i) + b_v`` because the weights
sum to one, so a window (often shared between imagination steps) is never copied or projected ``tau``
times. For many queries at once the projections are also multiplied out, ``M_qk = W_q^T W_k`` and
``M_vo = W_o W_v`` (``F x F``), which replaces four ``F x width`` products per query by two ``F x F`` ones
(4x fewer at width 500, F 250); gradients still reach the four factors. The result is the standard
attention (tested against it).
"""

from __future__ import annotations

import math

import torch
from torch import nn

POLICY_INPUTS = ("controllable", "attention", "concat")


class FutureStateAttention(nn.Module):
    """Single-head attention of one query over a window of ``tau`` keys, with a residual (eq. 6).

    Args:
        query_dim: width of the query features ``[s, h]``.
        key_dim: width of the window features ``[z, h']``.
        width: width of the learned query/key/value projections (500 in the authors' code).
        projections: ``True``: ``e = W_o(softmax(Q K^T / sqrt(width)) V) + q`` with ``Q = W_q q``,
            ``K = W_k z``, ``V = W_v z``. ``False``: the paper's literal ``e = softmax(q z^T) z + q`` (no
            parameters, no scaling; needs ``query_dim == key_dim``).
        device: where to create the parameters.

    Shapes:
        ``query``: ``[*N, query_dim]``; ``window``: ``[*N, tau, key_dim]`` -> ``e``: ``[*N, query_dim]``.

    Examples:
        >>> import torch
        >>> attention = FutureStateAttention(query_dim=6, key_dim=6, width=8)
        >>> attention(torch.randn(4, 6), torch.randn(4, 5, 6)).shape
        torch.Size([4, 6])
    """

    def __init__(
        self,
        *,
        query_dim: int,
        key_dim: int,
        width: int = 500,
        projections: bool = True,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        if not projections and query_dim != key_dim:
            raise ValueError(
                "FutureStateAttention(projections=False) is e = softmax(s z^T) z + s, which needs equal query "
                f"and key widths; got query_dim={query_dim}, key_dim={key_dim}. Use projections=True."
            )
        self.query_dim, self.key_dim, self.width = query_dim, key_dim, width
        self.projections = projections
        if projections:
            self.query = nn.Linear(query_dim, width, device=device)
            # A key bias adds the same score to every window entry, which the softmax cancels: omitted.
            self.key = nn.Linear(key_dim, width, bias=False, device=device)
            self.value = nn.Linear(key_dim, width, device=device)
            self.output = nn.Linear(width, query_dim, device=device)

    def _check(self, query: torch.Tensor, window: torch.Tensor) -> None:
        if query.shape[-1] != self.query_dim or window.shape[-1] != self.key_dim:
            raise ValueError(
                f"FutureStateAttention expects query [*N, {self.query_dim}] and window [*N, tau, {self.key_dim}], "
                f"got {tuple(query.shape)} and {tuple(window.shape)}"
            )
        if window.dim() != query.dim() + 1 or window.shape[:-2] != query.shape[:-1]:
            raise ValueError(
                f"the window must be [*N, tau, F] with the query's leading shape; got query "
                f"{tuple(query.shape)}, window {tuple(window.shape)}"
            )

    def fold(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The projections multiplied out (see the module docstring), differentiable in the parameters.

        Returns ``(M_qk [Dq, Dk], c_qk [Dk], M_vo [Dk, Dq], c_vo [Dq])`` with scores ``(q M_qk + c_qk) . z_i`` and
        output ``(sum_i a_i z_i) M_vo + c_vo``. Reuse them for several calls with the same parameters.
        """
        if not self.projections:
            raise ValueError("FutureStateAttention(projections=False) has no projections to fold")
        scale = 1.0 / math.sqrt(self.width)
        key = self.key.weight
        output = self.output.weight.t()
        return (
            (self.query.weight.t() @ key) * scale,
            (self.query.bias @ key) * scale,
            self.value.weight.t() @ output,
            self.value.bias @ output + self.output.bias,
        )

    def _fold_pays(self, rows: int) -> bool:
        """Whether folding (``2 W Dq Dk`` once, then ``2 Dq Dk`` per query) beats the projections per query
        (``W Dq`` for the query, ``W Dk`` for the scores' key weight, ``W Dk`` for the value and ``W Dq`` for the
        output: ``2 W (Dq + Dk)``). It never pays where ``Dq Dk >= W (Dq + Dk)``, e.g. an 800-wide query over
        80-wide keys at width 64 (Iso-Dream's DreamerV3 learner at ``size=bench``)."""
        per_query = 2 * self.width * (self.query_dim + self.key_dim) - 2 * self.query_dim * self.key_dim
        return rows * per_query > 2 * self.width * self.query_dim * self.key_dim

    def weights(
        self, query: torch.Tensor, window: torch.Tensor, *, folded: tuple | None = None
    ) -> torch.Tensor:
        """Attention weights over the window, ``[*N, tau]`` (sum to one)."""
        self._check(query, window)
        if not self.projections:
            scores_query = query
        elif folded is not None:
            scores_query = query @ folded[0] + folded[1]
        else:
            scores_query = (self.query(query) @ self.key.weight) / math.sqrt(self.width)
        return torch.einsum("...kf,...f->...k", window.to(scores_query.dtype), scores_query).softmax(-1)

    def forward(
        self, query: torch.Tensor, window: torch.Tensor, *, folded: tuple | None = None
    ) -> torch.Tensor:
        """``e = o + q``; ``folded`` (from :meth:`fold`) skips re-multiplying the projections; without it they are
        folded when that is cheaper for this many queries."""
        if folded is None and self.projections and self._fold_pays(query[..., 0].numel()):
            folded = self.fold()
        weights = self.weights(query, window, folded=folded)
        pooled = torch.einsum("...k,...kf->...f", weights, window.to(weights.dtype))
        if not self.projections:
            return pooled + query
        if folded is not None:
            return pooled @ folded[2] + folded[3] + query
        return self.output(self.value(pooled)) + query


class PolicyInput(nn.Module):
    """``e_t``, the input of the actor and the value model (eq. 7), for each ``policy_input`` mode.

    * ``"controllable"`` (DMC-style): ``e = [s, h]``; the noncontrollable branch is ignored.
    * ``"attention"`` (CARLA-style, eq. 6): ``e = FutureStateAttention([s, h], [z, h']_{t:t+tau})``.
    * ``"concat"`` (ablation): ``e = [s, h, z_t, h'_t]``, no look-ahead.

    Args:
        mode: one of ``"controllable"``, ``"attention"``, ``"concat"``.
        feature_dim: width of ``[s, h]`` (and of ``[z, h']``), ``state_dim + belief_dim``.
        window: ``tau``, the number of noncontrollable states the attention reads (current plus ``tau - 1``
            predicted). Used by ``"attention"`` only.
        width: the attention's projection width (500).
        projections: see :class:`FutureStateAttention`.
        device: where to create the parameters.

    Shapes:
        ``control``: ``[*N, F]``; ``free``: ``[*N, F]`` (``"concat"``); ``window``: ``[*N, tau, F]``
        (``"attention"``) -> ``[*N, out_features]``.
    """

    def __init__(
        self,
        *,
        mode: str,
        feature_dim: int,
        window: int = 5,
        width: int = 500,
        projections: bool = True,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        if mode not in POLICY_INPUTS:
            raise ValueError(f"unknown policy_input {mode!r}; valid: {POLICY_INPUTS}")
        if window < 1:
            raise ValueError(f"the attention window tau must be >= 1, got {window}")
        self.mode = mode
        self.feature_dim = feature_dim
        self.window = window if mode == "attention" else 0
        self.attention = (
            FutureStateAttention(
                query_dim=feature_dim,
                key_dim=feature_dim,
                width=width,
                projections=projections,
                device=device,
            )
            if mode == "attention"
            else None
        )

    @classmethod
    def for_world_model(cls, world_model, *, mode: str, **kwargs) -> PolicyInput:
        """A policy input sized for ``world_model`` (an ``IsoDreamV2WorldModel``); checks it has a free branch."""
        cfg = world_model.config
        if mode != "controllable" and not cfg.free_branch:
            raise ValueError(
                f"policy_input={mode!r} reads the noncontrollable branch, but the world model has "
                "free_branch=False; use policy_input='controllable'"
            )
        device = next(iter(world_model.parameters()), torch.empty(0)).device
        return cls(mode=mode, feature_dim=cfg.state_dim + cfg.belief_dim, device=device, **kwargs)

    @property
    def out_features(self) -> int:
        return 2 * self.feature_dim if self.mode == "concat" else self.feature_dim

    @property
    def uses_free_branch(self) -> bool:
        return self.mode != "controllable"

    def fold(self) -> tuple | None:
        """The attention's folded projections (:meth:`FutureStateAttention.fold`) for repeated calls, or ``None``."""
        if self.attention is None or not self.attention.projections:
            return None
        return self.attention.fold()

    def forward(
        self,
        control: torch.Tensor,
        free: torch.Tensor | None = None,
        window: torch.Tensor | None = None,
        *,
        folded: tuple | None = None,
    ) -> torch.Tensor:
        if self.mode == "controllable":
            return control
        if self.mode == "concat":
            if free is None:
                raise ValueError("policy_input='concat' needs the noncontrollable features [z, h']")
            return torch.cat([control, free.to(control.dtype)], dim=-1)
        if window is None or window.shape[-2] != self.window:
            got = None if window is None else tuple(window.shape)
            raise ValueError(f"policy_input='attention' needs a window [*N, {self.window}, F], got {got}")
        return self.attention(control, window, folded=folded)
