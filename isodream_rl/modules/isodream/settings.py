"""The default learner's settings (``algo=isodream`` and its ablations): one table, :data:`ISODREAM_SETTINGS`.

DreamerV3's settings at the values TorchRL's DreamerV3 reproduction sets, written out here rather than taken from
``algo=torchrl_dreamer_v3``'s table (:data:`~isodream_rl.modules.dreamer_v3.TORCHRL_DREAMER_V3_SETTINGS`), so that a
change to the baseline's does not move the default's; and Iso-Dream's own: the inverse-dynamics term's weight and the
rule that derives both branches' widths from the size preset.
"""

from __future__ import annotations

from dataclasses import dataclass

from isodream_rl.modules.dreamer_v3 import DreamerV3Settings


@dataclass(frozen=True)
class IsoDreamSettings(DreamerV3Settings):
    """DreamerV3's settings and Iso-Dream's own on DreamerV3's learner."""

    lambda_inverse: float
    """alpha of eq. 5, the inverse-dynamics term's weight, on the same per-frame squared-error scale as the image
    term (``algo.lambda_inverse`` replaces it)."""
    hidden_per_hidden_dim: float
    """DreamerV3's ``hidden`` of the controllable branch per unit of the size preset's ``hidden_dim``."""
    free_hidden_fraction: float
    """``hidden`` of the action-free branch per unit of the controllable branch's."""


#: ``algo=isodream``'s settings, every value named.
ISODREAM_SETTINGS = IsoDreamSettings(
    num_categoricals=32,
    unimix=0.01,
    num_blocks=8,
    prior_layers=2,
    num_bins=255,
    free_bits=1.0,
    lambda_dynamic=1.0,
    lambda_representation=0.1,
    continuation_horizon=333.0,
    lmbda=0.95,
    entropy_bonus=3e-4,
    return_normalization_rate=0.01,
    return_normalization_min_scale=1.0,
    slow_critic_regularization=1.0,
    slow_critic_tau=0.02,
    replay_value_loss_weight=0.3,
    policy_min_std=0.1,
    policy_max_std=1.0,
    agc=0.3,
    optimizer_eps=1e-20,
    lr_warmup=1000,
    lambda_inverse=30.0,
    hidden_per_hidden_dim=1.25,
    free_hidden_fraction=0.5,
)
