"""Recurrent state-space model cells of the two dynamic branches (paper eq. 3).

Both branches share one cell design (DreamerV2, Gaussian latent):

* transition  ``h_t = GRU(h_{t-1}, [x_{t-1}, a_{t-1}])`` with ``x`` the stochastic state,
* prior       ``p(x~_t | h_t)``,
* posterior   ``q(x_t | h_t, e_t)`` with ``e_t`` the branch's encoder embedding,

with ``std = 2 * sigmoid(raw / 2) + min_std`` ("sigmoid2", as in the authors' code).
:class:`ActionConditionedRSSM` is the controllable branch ``GRU_s(h, s, a)``; :class:`ActionFreeRSSM`
is the noncontrollable branch ``GRU_z(h', z)`` with no action input and its own parameters.

Why not TorchRL's ``RSSMPrior`` / ``RSSMPosterior``: they fix a softplus std and a plain ``nn.GRUCell``
(the authors use sigmoid2 and a layer-norm GRU), and their posterior projects ``[h, e]`` inside the
time loop, whereas we project the embeddings of the whole window at once, outside the loop (one product
for the window instead of one per step).

The joint two-branch filter with ``is_init`` resets is here too: :func:`filter_step`, one step of both
branches, and :func:`filter_window`, a window of them. These are the reference forms; the world model runs
:func:`~isodream_rl.modules.isodream_v2.fast_paths.fast_filter_window` instead when ``IsoDreamV2Config.fast_paths`` is
set (the same function: both branches' step as one batched computation, on one thread).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


def sigmoid2_std(raw: torch.Tensor, min_std: float) -> torch.Tensor:
    """``2 * sigmoid(raw / 2) + min_std``: a std in ``(min_std, 2 + min_std)``."""
    return 2.0 * torch.sigmoid(raw / 2.0) + min_std


class LayerNormGRUCell(nn.Module):
    """GRU cell with layer normalisation of the gate pre-activations (DreamerV2 / the authors' default).

    ``[r, c, u] = LN(W [x, h])``; ``c' = tanh(r * c)``; ``u' = sigmoid(u - 1)``; ``h' = u' c' + (1 - u') h``.
    The ``-1`` update bias makes the cell keep its state early in training.

    Args:
        input_size: width of ``x``.
        hidden_size: width of ``h``.
        device: where to create the parameters.

    Shapes:
        ``x: [N, input_size]``, ``h: [N, hidden_size]`` -> ``[N, hidden_size]``.
    """

    def __init__(self, input_size: int, hidden_size: int, *, device: torch.device | str | None = None):
        super().__init__()
        self.hidden_size = hidden_size
        self.linear = nn.Linear(input_size + hidden_size, 3 * hidden_size, bias=False, device=device)
        self.norm = nn.LayerNorm(3 * hidden_size, device=device)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        return gru_gates(self.norm(self.linear(torch.cat([x, h], dim=-1))), h)


def gru_gates(parts: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """The gates of :class:`LayerNormGRUCell` from its normalised pre-activations ``[r, c, u]`` ``[..., 3D]``."""
    reset, cand, update = parts.chunk(3, dim=-1)
    cand = torch.tanh(torch.sigmoid(reset) * cand)
    update = torch.sigmoid(update - 1.0)
    return update * cand + (1.0 - update) * h


class RSSMCell(nn.Module):
    """One branch of the decoupled RSSM: transition, prior and posterior (eq. 3).

    Args:
        action_dim: width of the action input; ``0`` gives an action-free cell.
        state_dim: width of the stochastic state (``stoch``, 50 in the paper's setting).
        belief_dim: width of the GRU state (``deter``, 200).
        hidden_dim: width of the hidden layers of the MLPs (200).
        embed_dim: width of this branch's encoder embedding.
        min_std: lower bound of the std (0.1).
        layer_norm_gru: use :class:`LayerNormGRUCell` (the authors' default) instead of ``nn.GRUCell``.
        device: where to create the parameters.

    The methods work on tensors with any leading batch shape ``[*N]``.
    """

    def __init__(
        self,
        *,
        action_dim: int,
        state_dim: int,
        belief_dim: int,
        hidden_dim: int,
        embed_dim: int,
        min_std: float = 0.1,
        layer_norm_gru: bool = True,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        if action_dim < 0:
            raise ValueError(f"action_dim must be >= 0, got {action_dim}")
        self.action_dim = action_dim
        self.state_dim = state_dim
        self.belief_dim = belief_dim
        self.embed_dim = embed_dim
        self.min_std = min_std
        self.transition_in = nn.Linear(state_dim + action_dim, hidden_dim, device=device)
        if layer_norm_gru:
            self.gru = LayerNormGRUCell(hidden_dim, belief_dim, device=device)
        else:
            self.gru = nn.GRUCell(hidden_dim, belief_dim, device=device)
        self.prior_net = nn.Sequential(
            nn.Linear(belief_dim, hidden_dim, device=device),
            nn.ELU(),
            nn.Linear(hidden_dim, 2 * state_dim, device=device),
        )
        # The posterior's first layer acts on [h, e]; it is split so that the embedding half can be
        # applied to a whole window at once (``project_embedding``), outside the time loop.
        self.posterior_belief_in = nn.Linear(belief_dim, hidden_dim, device=device)
        self.posterior_embed_in = nn.Linear(embed_dim, hidden_dim, bias=False, device=device)
        self.posterior_out = nn.Linear(hidden_dim, 2 * state_dim, device=device)

    def _stats(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, std = raw.chunk(2, dim=-1)
        return mean, sigmoid2_std(std, self.min_std)

    def transition(
        self, state: torch.Tensor, belief: torch.Tensor, action: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``h_t = GRU(h_{t-1}, [x_{t-1}, a_{t-1}])``. ``state: [*N, S]``, ``belief: [*N, D]``, ``action: [*N, A]``."""
        if self.action_dim:
            if action is None:
                raise ValueError("this RSSM branch is action-conditioned: an action is required")
            if action.shape[-1] != self.action_dim:
                raise ValueError(
                    f"action has {action.shape[-1]} dims, the action-conditioned RSSM expects {self.action_dim}"
                )
            x = torch.cat([state, action.to(state.dtype)], dim=-1)
        else:
            x = state
        x = F.elu(self.transition_in(x))
        lead = x.shape[:-1]
        # The recurrent cell runs in fp32 even under autocast (bf16 GRUs drift over long windows).
        with torch.autocast(device_type=x.device.type, enabled=False):
            new = self.gru(x.float().reshape(-1, x.shape[-1]), belief.float().reshape(-1, self.belief_dim))
        return new.reshape(*lead, self.belief_dim)

    def prior(self, belief: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``p(x~_t | h_t)``: returns ``(mean, std)``, each ``[*N, S]``."""
        return self._stats(self.prior_net(belief))

    def project_embedding(self, embedding: torch.Tensor) -> torch.Tensor:
        """Embedding half of the posterior's first layer, for a whole window: ``[*N, E] -> [*N, hidden]``."""
        if embedding.shape[-1] != self.embed_dim:
            raise ValueError(f"embedding has {embedding.shape[-1]} features, expected {self.embed_dim}")
        return self.posterior_embed_in(embedding)

    def posterior(
        self, belief: torch.Tensor, projected_embedding: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``q(x_t | h_t, e_t)`` from ``project_embedding(e_t)``: returns ``(mean, std)``, each ``[*N, S]``."""
        hidden = F.elu(self.posterior_belief_in(belief) + projected_embedding)
        return self._stats(self.posterior_out(hidden))

    @staticmethod
    def sample(mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
        """Reparameterised sample ``mean + std * eps``."""
        return mean + std * torch.randn_like(std)

    def imagine_step(
        self, state: torch.Tensor, belief: torch.Tensor, action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One prior step: returns ``(prior_mean, prior_std, prior_state, belief)`` at ``t`` from ``t - 1``."""
        belief = self.transition(state, belief, action)
        mean, std = self.prior(belief)
        return mean, std, self.sample(mean, std), belief

    def observe_step(
        self,
        state: torch.Tensor,
        belief: torch.Tensor,
        action: torch.Tensor | None,
        projected_embedding: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """One filtering step: prior and posterior at ``t`` from the posterior at ``t - 1``.

        Returns a dict with ``belief``, ``prior_mean``, ``prior_std``, ``prior_state`` (a sample of the
        prior), ``posterior_mean``, ``posterior_std`` and ``state`` (a sample of the posterior).
        """
        prior_mean, prior_std, prior_state, belief = self.imagine_step(state, belief, action)
        post_mean, post_std = self.posterior(belief, projected_embedding)
        return {
            "belief": belief,
            "prior_mean": prior_mean,
            "prior_std": prior_std,
            "prior_state": prior_state,
            "posterior_mean": post_mean,
            "posterior_std": post_std,
            "state": self.sample(post_mean, post_std),
        }

    def initial(self, batch_shape: torch.Size | tuple[int, ...], *, device=None, dtype=None):
        """Zero ``(state, belief)`` of shapes ``[*batch, S]`` and ``[*batch, D]``."""
        state = torch.zeros(*batch_shape, self.state_dim, device=device, dtype=dtype)
        return state, torch.zeros(*batch_shape, self.belief_dim, device=device, dtype=dtype)


class ActionConditionedRSSM(RSSMCell):
    """Controllable branch: ``h_t = GRU_s(h_{t-1}, s_{t-1}, a_{t-1})``, ``p(s~_t | h_t)``, ``q(s_t | h_t, e^s_t)`` (eq. 3)."""

    def __init__(self, *, action_dim: int, **kwargs):
        if action_dim < 1:
            raise ValueError(f"the action-conditioned RSSM needs action_dim >= 1, got {action_dim}")
        super().__init__(action_dim=action_dim, **kwargs)


class ActionFreeRSSM(RSSMCell):
    """Noncontrollable branch: ``h'_t = GRU_z(h'_{t-1}, z_{t-1})``, ``p(z~_t | h'_t)``, ``q(z_t | h'_t, e^z_t)`` (eq. 3)."""

    def __init__(self, **kwargs):
        super().__init__(action_dim=0, **kwargs)


def filter_step(
    control: RSSMCell,
    free: RSSMCell | None,
    previous: dict[str, torch.Tensor],
    action: torch.Tensor,
    control_embedding: torch.Tensor,
    free_embedding: torch.Tensor | None,
    reset: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """One filtering step of both branches (eq. 3), with embeddings already projected: the reference.

    Args:
        control: the :class:`ActionConditionedRSSM`.
        free: the :class:`ActionFreeRSSM`, or ``None``.
        previous: ``state``, ``belief`` (and ``free_state``, ``free_belief``) at ``t``, ``[*N, .]``.
        action: ``a_t`` ``[*N, A]``.
        control_embedding: ``control.project_embedding(e^s_{t+1})``.
        free_embedding: ``free.project_embedding(e^z_{t+1})`` or ``None``.
        reset: ``[*N, 1]`` bool; where true, states, beliefs and the action are zeroed first.

    Returns:
        the controllable outputs of :meth:`RSSMCell.observe_step` and the ``free_``-prefixed ones.
    """
    keep = None if reset is None else (~reset).to(action.dtype)
    state, belief = previous["state"], previous["belief"]
    if keep is not None:
        state, belief, action = state * keep, belief * keep, action * keep
    out = control.observe_step(state, belief, action, control_embedding)
    if free is not None:
        free_state, free_belief = previous["free_state"], previous["free_belief"]
        if keep is not None:
            free_state, free_belief = free_state * keep, free_belief * keep
        free_out = free.observe_step(free_state, free_belief, None, free_embedding)
        out.update({f"free_{k}": v for k, v in free_out.items()})
    return out


def filter_window(
    control: RSSMCell,
    free: RSSMCell | None,
    control_proj: torch.Tensor,
    free_proj: torch.Tensor | None,
    action: torch.Tensor,
    is_init: torch.Tensor | None,
) -> dict[str, torch.Tensor]:
    """Both branches filtered over a ``[B, T]`` window from zero states (eq. 3): :func:`filter_step` per step.

    Args:
        control, free: the two cells (``free`` may be ``None``).
        control_proj, free_proj: projected embeddings ``[B, T, hidden]`` (``free_proj`` ``None`` without ``free``).
        action: ``a_t`` ``[B, T, A]``.
        is_init: ``[B, T, 1]`` bool resets, or ``None``.

    Returns:
        the keys of :func:`filter_step`, each ``[B, T, .]``.
    """
    batch, time = action.shape[:2]
    # unbind, not [:, t]: its backward is one stack, where indexing writes a zero-filled window per step
    actions = action.unbind(1)
    resets = [None] * time if is_init is None else is_init.bool().unbind(1)
    state, belief = control.initial((batch,), device=action.device)
    previous = {"state": state, "belief": belief}
    if free is not None:
        previous["free_state"], previous["free_belief"] = free.initial((batch,), device=action.device)
    control_steps = control_proj.unbind(1)
    free_steps = [None] * time if free_proj is None else free_proj.unbind(1)
    steps = []
    for t in range(time):
        previous = filter_step(
            control, free, previous, actions[t], control_steps[t], free_steps[t], resets[t]
        )
        steps.append(previous)
    return {k: torch.stack([s[k] for s in steps], dim=1) for k in steps[0]}
