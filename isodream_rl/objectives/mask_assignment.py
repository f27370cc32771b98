"""Mask assignment: the branches' masks pulled towards each branch's responsibility for each pixel.

Not in the paper: an optional auxiliary term of :class:`~isodream_rl.objectives.IsoDreamModelLoss`
(``lambda_mask_assignment``, off by default). It treats eq. 4 as a spatial mixture, as MONet/IODINE-style
scene models do, and asks each pixel's masks to match the posterior responsibilities

``r_k = m_k N(o; o^k, sigma^2 I) / sum_j m_j N(o; o^j, sigma^2 I)``

(``m_k`` the masks, ``o^k`` the clamped branch components, both detached), through the cross-entropy
``-sum_k r_k log m_k`` (reported as ``KL(r || m)``, which has the same gradient). In softmax mode its
gradient on branch ``k``'s logit is ``m_k - r_k``.

Why: under eq. 4 alone, the gradient of the image loss on a mask logit is ``m_k <o^k - o^, dL/do^>``,
proportional to the mask itself. A branch whose softmax mask went to ~0 on a region cannot take the
region back, even where its own component draws the frame better than the branch that owns it
(docs/results/world_model_demo.md: the noncontrollable branch kept one sprites disc out of three, the
other two left to the background). Here a branch that explains a pixel far better than the others gets
responsibility ~1 there whatever its current mask, and its logit a push of order one. Where the branches
explain a pixel equally well, ``r = m`` and the term does nothing. The composite, and so the image loss,
are eq. 4 unchanged; only the masks' training signal gains this term.
"""

from __future__ import annotations

import torch


def mask_assignment(
    masks: dict[str, torch.Tensor],
    colors: dict[str, torch.Tensor],
    target: torch.Tensor,
    *,
    std: float,
    branches: tuple[str, ...] | None = None,
    eps: float = 1e-8,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The mask-assignment cross-entropy and the responsibilities.

    With ``branches`` a subset ``S`` of the branches, the assignment happens inside ``S`` only: each pixel's
    masks of ``S`` conditioned on ``S`` (``m_k / M``, ``M = sum_S m_j``) are pulled towards the conditional
    responsibilities ``r_k = m_k N_k / sum_S m_j N_j``, weighted by ``M`` (detached). The logits of the
    branches outside ``S`` get no gradient, and the share ``M`` of ``S`` at a pixel is left to the image
    loss. With ``S`` all branches, ``M = 1`` and this is the plain term.

    Args:
        masks: branch name -> mask ``[*N, 1, H, W]`` (non-negative, summing to one over branches; gradients
            flow into them).
        colors: branch name -> the component as composed ``[*N, 3, H, W]`` (broadcastable; detached here).
        target: the observed frame in the components' pixel range ``[*N, 3, H, W]``.
        std: ``sigma``, the pixel standard deviation of each branch's Gaussian in the responsibilities:
            the smaller, the harder the assignment (0.1 on the ``[-0.5, 0.5]`` range: a squared-error
            advantage of 0.1, summed over RGB, outweighs a 150-fold smaller mask).
        branches: the subset ``S`` (default: every branch of ``masks``).
        eps: floor of the masks inside the logarithm.

    Returns:
        ``(loss, responsibilities)``: ``loss`` is ``sum_pixels M KL(r || m / M)`` averaged over the frames
        ``N`` (its gradient is that of ``-M sum_S r_k log(m_k / M)``); ``responsibilities[name]``, for the
        branches of ``S``, is ``[*N, 1, H, W]``, detached, summing to one over ``S``.
    """
    if std <= 0:
        raise ValueError(f"std must be > 0, got {std}")
    if set(masks) != set(colors):
        raise KeyError(
            f"masks and colors must name the same branches, got {sorted(masks)} and {sorted(colors)}"
        )
    names = list(masks) if branches is None else list(branches)
    unknown = set(names) - set(masks)
    if len(names) < 2 or unknown:
        raise ValueError(f"branches must name two or more of {sorted(masks)}, got {branches}")
    log_masks = torch.cat([_wide(masks[n]).clamp(min=eps).log() for n in names], dim=-3)
    # log(m_k / M): the masks conditioned on the subset
    log_share = torch.logsumexp(log_masks, dim=-3, keepdim=True)
    log_conditional = log_masks - log_share
    with torch.no_grad():
        target = _wide(target)
        # log m_k + log N(o; o^k, sigma^2): the Gaussian's constant is the same for every branch
        scores = torch.cat(
            [(_wide(colors[n]) - target).pow(2).sum(-3, keepdim=True) for n in names], dim=-3
        ).mul_(-0.5 / std**2)
        log_resp = torch.log_softmax(scores + log_masks.detach(), dim=-3)
        resp = log_resp.exp()
        share = log_share.detach().exp()
    frames = log_masks.numel() // log_masks.shape[-3:].numel()
    loss = (share * resp * (log_resp - log_conditional)).sum() / frames
    return loss, dict(zip(names, resp.split(1, dim=-3)))


def _wide(x: torch.Tensor) -> torch.Tensor:
    """``x`` in float32 at least (bf16 autocast outputs are widened; float64 stays)."""
    return x if x.dtype == torch.float64 else x.float()
