"""Training: configuration, Trainer assembly, algorithm registry, optimisation stepper, hooks, checkpoints."""

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
    "IsoDreamOptimizationStepper",
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
