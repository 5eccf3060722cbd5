"""Training: config validation, builders of every piece, the trainer, checkpoints."""

from wcsac_rl.training.config import ALGOS, ConfigError, validate_config
from wcsac_rl.training.trainer import Trainer, seed_everything

__all__ = ["ALGOS", "ConfigError", "Trainer", "seed_everything", "validate_config"]
