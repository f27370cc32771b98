"""Baselines trained by ``isodream-train`` with the same collector, replay, evaluation and budget as Iso-Dream.

``algo=torchrl_dreamer``: TorchRL's own Dreamer pieces at our sizes (:mod:`isodream_rl.baselines.torchrl_dreamer`).
"""

from isodream_rl.baselines.torchrl_dreamer import (
    ResettingRSSMRollout,
    TorchRLDreamerBehavior,
    TorchRLDreamerComponents,
    TorchRLDreamerOptimizationStepper,
    TorchRLDreamerPolicy,
    dreamer_sizes,
    make_torchrl_dreamer,
)

__all__ = [
    "ResettingRSSMRollout",
    "TorchRLDreamerBehavior",
    "TorchRLDreamerComponents",
    "TorchRLDreamerOptimizationStepper",
    "TorchRLDreamerPolicy",
    "dreamer_sizes",
    "make_torchrl_dreamer",
]
