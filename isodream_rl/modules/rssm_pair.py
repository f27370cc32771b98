"""Both RSSM branches filtered as one batched computation (paper eq. 3, two cells in one step).

The controllable cell ``GRU_s(h, s, a)`` and the action-free cell ``GRU_z(h', z)`` have the same layer
shapes except for the action input, so one filtering step of both is the same sequence of matrix
products on a leading branch dimension of size 2: ``bmm`` over stacked weights instead of two calls per
layer. The action-free cell's transition input is padded with zero columns where the action would be,
so the stacked product gives exactly its own result. At paper size this halves the ~30 small operations
per time step of the window's filtering loop, which runs on one thread (see
:func:`~isodream_rl.modules.rssm.single_threaded`).

The weights are stacked from the two cells' own parameters at each call (``torch.stack`` is
differentiable), so the modules, their parameter names and checkpoints are unchanged; the result equals
running :meth:`RSSMCell.observe_step` on each branch, with the same random draws in the same order.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from isodream_rl.modules.rssm import LayerNormGRUCell, RSSMCell, gru_gates, sigmoid2_std

OUT_KEYS = (
    "belief",
    "prior_mean",
    "prior_std",
    "prior_state",
    "posterior_mean",
    "posterior_std",
    "state",
)


def can_pair(control: RSSMCell, free: RSSMCell | None) -> bool:
    """Whether :class:`RSSMPair` applies: two layer-norm-GRU cells of equal sizes, the second action-free."""
    return (
        free is not None
        and isinstance(control.gru, LayerNormGRUCell)
        and isinstance(free.gru, LayerNormGRUCell)
        and free.action_dim == 0
        and (control.state_dim, control.belief_dim, control.min_std)
        == (free.state_dim, free.belief_dim, free.min_std)
        and control.transition_in.out_features == free.transition_in.out_features
        and control.gru.norm.eps == free.gru.norm.eps
    )


class RSSMPair:
    """One filtering step of the controllable and the action-free branch, batched over the two.

    Args:
        control: the :class:`~isodream_rl.modules.rssm.ActionConditionedRSSM`.
        free: the :class:`~isodream_rl.modules.rssm.ActionFreeRSSM` (:func:`can_pair` must hold).

    Build one per rollout (it stacks the current weights); tensors carry a leading branch dimension
    ``[2, B, .]``, index 0 the controllable branch and 1 the noncontrollable one.
    """

    def __init__(self, control: RSSMCell, free: RSSMCell):
        if not can_pair(control, free):
            raise ValueError("RSSMPair needs two layer-norm-GRU cells of equal sizes, the second action-free")
        self.action_dim = control.action_dim
        self.state_dim = control.state_dim
        self.min_std = control.min_std
        self.eps = control.gru.norm.eps
        cells = (control, free)
        free_in = F.pad(free.transition_in.weight, (0, self.action_dim))
        self.transition_weight = torch.stack([control.transition_in.weight, free_in]).transpose(1, 2)
        self.transition_bias = torch.stack([c.transition_in.bias for c in cells])[:, None]
        self.gru_weight = torch.stack([c.gru.linear.weight for c in cells]).transpose(1, 2)
        self.norm_weight = torch.stack([c.gru.norm.weight for c in cells])[:, None]
        self.norm_bias = torch.stack([c.gru.norm.bias for c in cells])[:, None]
        # prior_net[0] and posterior_belief_in both read h_t: one product for the two
        self.belief_weight = torch.stack(
            [torch.cat([c.prior_net[0].weight, c.posterior_belief_in.weight]) for c in cells]
        ).transpose(1, 2)
        self.belief_bias = torch.stack(
            [torch.cat([c.prior_net[0].bias, c.posterior_belief_in.bias]) for c in cells]
        )[:, None]
        self.hidden = control.prior_net[0].out_features
        # prior_net[2] (control, free) and posterior_out (control, free): one product over four
        self.out_weight = torch.stack(
            [control.prior_net[2].weight, free.prior_net[2].weight]
            + [control.posterior_out.weight, free.posterior_out.weight]
        ).transpose(1, 2)
        self.out_bias = torch.stack(
            [control.prior_net[2].bias, free.prior_net[2].bias]
            + [control.posterior_out.bias, free.posterior_out.bias]
        )[:, None]

    def observe_step(
        self,
        state: torch.Tensor,
        belief: torch.Tensor,
        action: torch.Tensor,
        projected_embedding: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """``[2, B, S]`` states, ``[2, B, D]`` beliefs, ``[B, A]`` action, ``[2, B, hidden]`` projected embeddings.

        Returns the keys of :meth:`RSSMCell.observe_step`, each ``[2, B, .]``.
        """
        batch = state.shape[1]
        padded = torch.cat([action[None], torch.zeros_like(action)[None]]).to(state.dtype)
        x = F.elu(torch.baddbmm(self.transition_bias, torch.cat([state, padded], -1), self.transition_weight))
        # layer-norm GRU (LayerNormGRUCell) with per-branch affine parameters
        parts = torch.bmm(torch.cat([x, belief], -1), self.gru_weight)
        parts = F.layer_norm(parts, parts.shape[-1:], eps=self.eps)
        belief = gru_gates(torch.addcmul(self.norm_bias, parts, self.norm_weight), belief)
        hidden = torch.baddbmm(self.belief_bias, belief, self.belief_weight)
        prior_hidden = F.elu(hidden[..., : self.hidden])
        post_hidden = F.elu(hidden[..., self.hidden :] + projected_embedding)
        raw = torch.baddbmm(self.out_bias, torch.cat([prior_hidden, post_hidden]), self.out_weight)
        mean, std = raw.chunk(2, dim=-1)
        std = sigmoid2_std(std, self.min_std)
        # the draws of RSSMCell.observe_step, branch after branch: control prior, control posterior, ...
        noise = [torch.randn(batch, self.state_dim, dtype=std.dtype, device=std.device) for _ in range(4)]
        eps = torch.stack([noise[0], noise[2], noise[1], noise[3]])
        sample = torch.addcmul(mean, std, eps)
        return {
            "belief": belief,
            "prior_mean": mean[:2],
            "prior_std": std[:2],
            "prior_state": sample[:2],
            "posterior_mean": mean[2:],
            "posterior_std": std[2:],
            "state": sample[2:],
        }
