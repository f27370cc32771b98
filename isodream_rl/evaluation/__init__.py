"""Scores of a trained model against the ground truth the envs render.

:func:`decomposition_scores`: how well a world model's branches (paper §3.1, eq. 4) split a scene into the
controllable agent, the moving noncontrollable distractors and the static background, on windows with
ground-truth masks (``make_env(..., return_masks=True)``, any env of ``isodream_rl.envs``).

:mod:`isodream_rl.evaluation.branches` (not imported here): the pictures of each branch and the scores of the
world-model mode (``score_branches``).

:class:`ExactSpritesModel`: sprites ``reach`` as an exact, differentiable world model, to train the behavior
learner without model error (:func:`isodream_rl.trainers.exact_model.train_behavior_on_exact_model`).
"""

from isodream_rl.evaluation.decomposition import (
    BRANCHES,
    CLASSES,
    ISOLATION_AIMS,
    branch_assignment,
    check_windows,
    decomposition_scores,
    isolation_verdict,
    score_decomposition,
)
from isodream_rl.evaluation.exact_sprites import ExactSpritesModel

__all__ = [
    "BRANCHES",
    "CLASSES",
    "ExactSpritesModel",
    "ISOLATION_AIMS",
    "branch_assignment",
    "check_windows",
    "decomposition_scores",
    "isolation_verdict",
    "score_decomposition",
]
