"""Training: config validation, builders of every piece, the trainers, checkpoints."""

from wcsac_rl.training.config import ALGOS, ConfigError, TrainingError, validate_config
from wcsac_rl.training.trainer import RandomPolicyTrainer, Trainer, make_trainer, seed_everything

__all__ = [
    "ALGOS",
    "ConfigError",
    "RandomPolicyTrainer",
    "Trainer",
    "TrainingError",
    "make_trainer",
    "seed_everything",
    "validate_config",
]
