"""Baselines trained by ``isodream-train`` with the same collector, replay, evaluation and budget as Iso-Dream.

``algo=torchrl_dreamer``: TorchRL's own Dreamer pieces at our sizes (:mod:`isodream_rl.baselines.torchrl_dreamer`).
``algo=torchrl_dreamer_v3``: TorchRL's DreamerV3 at Iso-Dream's parameter count
(:mod:`isodream_rl.baselines.torchrl_dreamer_v3`).

What both share around TorchRL's pieces (the acting policy's carried state, the stepper's replay preparation, the
run parts' replay side and checkpoint check, imagination's specs) is in :mod:`isodream_rl.baselines.common`.

Importing this package registers both with the trainers' algorithm registry (:mod:`isodream_rl.trainers.registry`);
``isodream-train`` imports it.
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
from isodream_rl.baselines.torchrl_dreamer_v3 import (
    DreamerV3ContinuousActor,
    DreamerV3Settings,
    DreamerV3Widths,
    TorchRLDreamerV3Components,
    TorchRLDreamerV3Learner,
    TorchRLDreamerV3OptimizationStepper,
    TorchRLDreamerV3Policy,
    WindowInputCheck,
    make_torchrl_dreamer_v3,
)

__all__ = [
    "DreamerV3ContinuousActor",
    "DreamerV3Settings",
    "DreamerV3Widths",
    "ResettingRSSMRollout",
    "TorchRLDreamerBehavior",
    "TorchRLDreamerComponents",
    "TorchRLDreamerOptimizationStepper",
    "TorchRLDreamerPolicy",
    "TorchRLDreamerV3Components",
    "TorchRLDreamerV3Learner",
    "TorchRLDreamerV3OptimizationStepper",
    "TorchRLDreamerV3Policy",
    "WindowInputCheck",
    "dreamer_sizes",
    "make_torchrl_dreamer",
    "make_torchrl_dreamer_v3",
]
