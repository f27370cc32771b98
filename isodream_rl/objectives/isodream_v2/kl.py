"""KL divergence of diagonal Gaussians with DreamerV2 balancing and free nats (the KL terms of eq. 5)."""

from __future__ import annotations

import torch


def gaussian_kl(
    mean_q: torch.Tensor, std_q: torch.Tensor, mean_p: torch.Tensor, std_p: torch.Tensor
) -> torch.Tensor:
    """``KL(N(mean_q, std_q) || N(mean_p, std_p))`` summed over the last dimension: ``[*N, S] -> [*N]``."""
    var_ratio = (std_q / std_p).pow(2)
    return 0.5 * (var_ratio + ((mean_q - mean_p) / std_p).pow(2) - 1.0 - var_ratio.log()).sum(-1)


def balanced_kl(
    posterior_mean: torch.Tensor,
    posterior_std: torch.Tensor,
    prior_mean: torch.Tensor,
    prior_std: torch.Tensor,
    *,
    balance: float = 0.8,
    free_nats: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """DreamerV2 KL balancing with free nats applied to the batch mean.

    ``balance * max(mean KL(sg(q) || p), free) + (1 - balance) * max(mean KL(q || sg(p)), free)``: the
    prior moves towards the posterior faster than the posterior towards the prior.

    Returns:
        ``(loss, kl)``: the scalar loss term and the detached mean ``KL(q || p)`` for logging.
    """
    if not 0.0 <= balance <= 1.0:
        raise ValueError(f"kl balance must lie in [0, 1], got {balance}")
    to_prior = gaussian_kl(posterior_mean.detach(), posterior_std.detach(), prior_mean, prior_std).mean()
    to_posterior = gaussian_kl(posterior_mean, posterior_std, prior_mean.detach(), prior_std.detach()).mean()
    loss = balance * to_prior.clamp_min(free_nats) + (1.0 - balance) * to_posterior.clamp_min(free_nats)
    return loss, to_prior.detach()
