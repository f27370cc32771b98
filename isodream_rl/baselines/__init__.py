"""Baselines trained by ``isodream-train`` with the same collector, replay, evaluation and budget as Iso-Dream.

``algo=torchrl_dreamer``: TorchRL's own Dreamer pieces at our sizes (:mod:`isodream_rl.baselines.torchrl_dreamer`).
``algo=torchrl_dreamer_v3``: TorchRL's DreamerV3 at Iso-Dream's parameter count
(:mod:`isodream_rl.baselines.torchrl_dreamer_v3`).

What both share around TorchRL's pieces (the run parts' replay side and checkpoint check) is in
:mod:`isodream_rl.baselines.common`; what Iso-Dream's learners share with them lives in the lower layers: the acting
policy's carried state (:class:`~isodream_rl.modules.isodream_v2.policy.CarriedStatePolicy`), imagination's specs
(:mod:`isodream_rl.objectives.imagination_env`), the stepper's replay preparation
(:class:`~isodream_rl.trainers.stepper.ZeroStateStepper`), DreamerV3's settings, actor and input check
(:mod:`isodream_rl.modules.dreamer_v3`), its stepper and optimisers (:mod:`isodream_rl.trainers.dreamer_v3`).

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
    DreamerV3Widths,
    TorchRLDreamerV3Components,
    TorchRLDreamerV3Learner,
    TorchRLDreamerV3Policy,
    make_torchrl_dreamer_v3,
)

# DreamerV3's shared pieces, re-exported from their homes in the lower layers
from isodream_rl.modules.dreamer_v3 import DreamerV3ContinuousActor, DreamerV3Settings, WindowInputCheck
from isodream_rl.trainers.dreamer_v3 import DreamerV3OptimizationStepper

__all__ = [
    "DreamerV3ContinuousActor",
    "DreamerV3OptimizationStepper",
    "DreamerV3Settings",
    "DreamerV3Widths",
    "ResettingRSSMRollout",
    "TorchRLDreamerBehavior",
    "TorchRLDreamerComponents",
    "TorchRLDreamerOptimizationStepper",
    "TorchRLDreamerPolicy",
    "TorchRLDreamerV3Components",
    "TorchRLDreamerV3Learner",
    "TorchRLDreamerV3Policy",
    "WindowInputCheck",
    "dreamer_sizes",
    "make_torchrl_dreamer",
    "make_torchrl_dreamer_v3",
]
