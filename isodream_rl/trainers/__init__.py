"""Training: configuration, the learners' run parts (the default's :class:`IsoDreamComponents`, the DreamerV2-style
learner's :class:`IsoDreamV2Components`) and their settings tables, Trainer assembly, algorithm registry,
optimisation stepper, hooks."""

from isodream_rl.run_utils.checkpoint import CheckpointError, CheckpointManager
from isodream_rl.trainers.components import RunComponents
from isodream_rl.trainers.config import (
    AlgoConfig,
    CheckpointConfig,
    ConfigError,
    EnvConfig,
    LoggingConfig,
    ModelConfig,
    RunConfig,
    TrainConfig,
    validate_config,
)
from isodream_rl.trainers.isodream import IsoDreamComponents
from isodream_rl.trainers.isodream_v2 import IsoDreamV2Components
from isodream_rl.trainers.registry import register_algorithm
from isodream_rl.trainers.run import evaluate_checkpoint, train
from isodream_rl.trainers.run_lifecycle import RunResult
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper, NonFiniteLossError
from isodream_rl.trainers.world_model_config import WorldModelModeConfig

__all__ = [
    "AlgoConfig",
    "CheckpointConfig",
    "CheckpointError",
    "CheckpointManager",
    "ConfigError",
    "EnvConfig",
    "IsoDreamComponents",
    "IsoDreamOptimizationStepper",
    "IsoDreamV2Components",
    "LoggingConfig",
    "ModelConfig",
    "NonFiniteLossError",
    "RunComponents",
    "RunConfig",
    "RunResult",
    "TrainConfig",
    "WorldModelModeConfig",
    "evaluate_checkpoint",
    "register_algorithm",
    "train",
    "validate_config",
]
