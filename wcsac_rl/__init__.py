"""wcsac_rl: Worst-Case Soft Actor Critic and risk-averse safe-RL baselines for TorchRL."""

__version__ = "0.1.0"
