"""The action model ``pi(a_t | e_t)`` of eq. 7: a tanh-squashed Gaussian (TorchRL ``TanhNormal``) or a bounded
Normal.

The authors use a "truncated normal" whose samples are in fact unclipped Normal draws clipped at the
environment; a tanh-squashed Gaussian keeps actions in ``(-1, 1)`` with an exact
log-density, which the entropy bonus and the REINFORCE option need. The mean is ``5 tanh(mu / 5)``
(TorchRL's ``tanh_loc``, as in DreamerV1/V2) and the std ``2 sigmoid(x / 2) + min_std`` (the authors'
actor std).

``distribution="bounded_normal"`` is DreamerV3's continuous actor instead: a Normal with mean ``tanh(mu)`` and
std ``(max_std - min_std) sigmoid(x + 2) + min_std`` whose samples are clipped to ``[-1, 1]`` (the gradient
passes the clip unchanged). Its entropy is bounded below by the std's floor, so a policy whose mean reaches the
border of the action box still samples around it instead of saturating.
"""

from __future__ import annotations

import torch
from torch import distributions as D
from torch import nn
from torchrl.modules import MLP, TanhNormal

from isodream_rl.modules.rssm import sigmoid2_std


ACTOR_DISTRIBUTIONS = ("tanh_normal", "bounded_normal")


class BoundedNormal(D.Independent):
    """A diagonal Normal over actions whose samples are clipped to ``[-1, 1]``.

    ``rsample_and_log_prob()`` returns the clipped sample (straight-through: the gradient is that of the
    unclipped one) and the log-density of the unclipped sample, as ``TanhNormal`` does for its own sample.

    Args:
        loc: ``[*N, action_dim]`` in ``(-1, 1)``.
        scale: ``[*N, action_dim]``, positive.
    """

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor):
        super().__init__(D.Normal(loc, scale), 1)

    @staticmethod
    def _clip(sample: torch.Tensor) -> torch.Tensor:
        return sample + (sample.clamp(-1.0, 1.0) - sample).detach()

    def rsample_and_log_prob(self) -> tuple[torch.Tensor, torch.Tensor]:
        sample = self.rsample()
        return self._clip(sample), self.log_prob(sample)

    def sample(self, sample_shape: torch.Size = torch.Size()) -> torch.Tensor:
        return super().sample(sample_shape).clamp(-1.0, 1.0)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.base_dist.loc


class IsoDreamActor(nn.Module):
    """MLP from ``e_t`` to a ``TanhNormal`` (or a :class:`BoundedNormal`) over actions in ``[-1, 1]``.

    Args:
        in_features: width of ``e_t`` (``PolicyInput.out_features``).
        action_dim: width of the action.
        num_cells: hidden width (400).
        depth: number of hidden layers (4).
        min_std: lower bound of the pre-tanh std (0.1).
        upscale: bound of the pre-tanh mean, ``upscale * tanh(mu / upscale)`` (5; ``tanh_normal`` only).
        distribution: ``"tanh_normal"`` (the paper's) or ``"bounded_normal"`` (DreamerV3's).
        max_std: upper bound of the std (1; ``bounded_normal`` only).
        device: where to create the parameters.

    Shapes:
        ``forward(e)``: ``[*N, in_features]`` -> ``(loc, scale)`` each ``[*N, action_dim]``;
        ``distribution(e)``: a ``TanhNormal`` (``BoundedNormal``) with batch shape ``[*N]`` and event shape
        ``[action_dim]``;
        ``mode(e)``: ``[*N, action_dim]``, the evaluation action (the distribution's mean, in ``(-1, 1)``).

    Examples:
        >>> import torch
        >>> actor = IsoDreamActor(in_features=6, action_dim=2, num_cells=8, depth=2)
        >>> action, log_prob = actor.distribution(torch.randn(3, 6)).rsample_and_log_prob()
        >>> action.shape, log_prob.shape
        (torch.Size([3, 2]), torch.Size([3]))
    """

    def __init__(
        self,
        *,
        in_features: int,
        action_dim: int,
        num_cells: int = 400,
        depth: int = 4,
        min_std: float = 0.1,
        upscale: float = 5.0,
        distribution: str = "tanh_normal",
        max_std: float = 1.0,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        if action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {action_dim}")
        if distribution not in ACTOR_DISTRIBUTIONS:
            raise ValueError(f"distribution must be one of {ACTOR_DISTRIBUTIONS}, got {distribution!r}")
        if distribution == "bounded_normal" and not 0 < min_std < max_std:
            raise ValueError(f"bounded_normal needs 0 < min_std < max_std, got {min_std} and {max_std}")
        self.in_features, self.action_dim = in_features, action_dim
        self.min_std, self.upscale = min_std, upscale
        self.kind, self.max_std = distribution, max_std
        self.net = MLP(
            in_features=in_features,
            out_features=2 * action_dim,
            depth=depth,
            num_cells=num_cells,
            activation_class=nn.ELU,
            device=device,
        )

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if features.shape[-1] != self.in_features:
            raise ValueError(
                f"the actor expects [*N, {self.in_features}] features, got {tuple(features.shape)}"
            )
        raw = self.net(features).float()
        loc, scale = raw.chunk(2, dim=-1)
        if self.kind == "bounded_normal":
            return torch.tanh(loc), (self.max_std - self.min_std) * torch.sigmoid(scale + 2.0) + self.min_std
        return loc, sigmoid2_std(scale, self.min_std)

    def distribution(self, features: torch.Tensor) -> TanhNormal | BoundedNormal:
        loc, scale = self(features)
        if self.kind == "bounded_normal":
            return BoundedNormal(loc, scale)
        return TanhNormal(loc, scale, upscale=self.upscale, tanh_loc=True)

    def mode(self, features: torch.Tensor) -> torch.Tensor:
        """The deterministic action used for evaluation: ``tanh(upscale * tanh(loc / upscale))`` for the
        ``TanhNormal``, the mean ``tanh(mu)`` for the ``BoundedNormal``."""
        loc, _ = self(features)
        if self.kind == "bounded_normal":
            return loc
        return torch.tanh(self.upscale * torch.tanh(loc / self.upscale))
