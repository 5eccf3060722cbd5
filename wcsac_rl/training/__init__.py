"""Training: config validation, builders of every piece, the trainers, checkpoints."""

from wcsac_rl.training.config import ConfigError, TrainingError, validate_config
from wcsac_rl.training.registry import ALGORITHMS, Algorithm, make_trainer, trainer_class
from wcsac_rl.training.trainer import RandomPolicyTrainer, Trainer, seed_everything

__all__ = [
    "ALGORITHMS",
    "Algorithm",
    "ConfigError",
    "RandomPolicyTrainer",
    "Trainer",
    "TrainingError",
    "make_trainer",
    "seed_everything",
    "trainer_class",
    "validate_config",
]
