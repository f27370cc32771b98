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
time loop, whereas we project the embeddings of the whole window at once, outside the loop (the
embedding half of that first linear layer is the expensive part). The joint two-branch rollout with
``is_init`` resets lives in :class:`~isodream_rl.modules.world_model.IsoDreamWorldModel`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator

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


@contextlib.contextmanager
def _num_threads(count: int) -> Iterator[None]:
    previous = torch.get_num_threads()
    if previous == count:
        yield
        return
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class _SingleThreaded(torch.autograd.Function):
    """Runs ``fn`` forward and its graph backward with one intra-op thread (see :func:`single_threaded`)."""

    @staticmethod
    def forward(ctx, fn, keys: list, num_args: int, *tensors: torch.Tensor):
        args = [t.detach().requires_grad_() if t.requires_grad else t for t in tensors[:num_args]]
        with torch.enable_grad(), _num_threads(1):
            outputs = fn(*args)
        keys.extend(outputs)
        ctx.set_materialize_grads(False)
        ctx.inner = (args + list(tensors[num_args:]), [outputs[k] for k in keys])
        return tuple(outputs[k].detach() for k in keys)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor | None):
        inputs, outputs = ctx.inner
        del ctx.inner
        pairs = [(o, g) for o, g in zip(outputs, grads) if g is not None and o.requires_grad]
        wanted = [i for i, t in enumerate(inputs) if t.requires_grad]
        result: list[torch.Tensor | None] = [None] * len(inputs)
        if pairs and wanted:
            with _num_threads(1):
                got = torch.autograd.grad(
                    [o for o, _ in pairs],
                    [inputs[i] for i in wanted],
                    [g for _, g in pairs],
                    allow_unused=True,
                )
            for i, g in zip(wanted, got):
                result[i] = g
        return (None, None, None, *result)


def single_threaded(
    fn: Callable[..., dict[str, torch.Tensor]],
    args: Iterable[torch.Tensor],
    parameters: Iterable[torch.Tensor],
) -> dict[str, torch.Tensor]:
    """``fn(*args)`` (a recurrent rollout returning a dict of tensors), forward and backward on one thread.

    A time loop over a ``[B, .]`` state runs thousands of tiny operations (``16 x 200`` matrices at paper
    size) that gain nothing from several threads; each one that does go parallel (MKL products,
    layer norm, reductions) waits for every thread of the pool, and on a machine whose cores are shared
    with other processes that wait is a scheduler time slice (milliseconds) per operation. This runs the
    loop's forward and, through a custom autograd function, its backward with ``torch.set_num_threads(1)``,
    restoring the previous count afterwards; the convolutions outside keep all threads. The result is the
    same function with the same gradients. Limitation: the inner graph is freed by the first backward, so
    a second backward through it (``retain_graph=True``) is not supported.

    Args:
        fn: the rollout; it reads ``parameters`` through its closure.
        args: its tensor arguments (gradients flow back to those that require them).
        parameters: the parameters ``fn`` uses, so that their gradients are produced.
    """
    args, parameters = list(args), [p for p in parameters if p.requires_grad]
    needs_graph = torch.is_grad_enabled() and any(t.requires_grad for t in args + parameters)
    if torch.get_num_threads() == 1 or not needs_graph:
        with _num_threads(1):
            return fn(*args)
    keys: list[str] = []
    outputs = _SingleThreaded.apply(fn, keys, len(args), *args, *parameters)
    return dict(zip(keys, outputs))
