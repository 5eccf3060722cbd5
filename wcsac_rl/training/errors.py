"""The two errors a training command reports as one line (``train.py``: ``error: ...``)."""

from __future__ import annotations

__all__ = ["ConfigError", "TrainingError"]


class ConfigError(ValueError):
    """A configuration a run cannot start from; the message says what to change."""


class TrainingError(RuntimeError):
    """A run that cannot go on (or cannot be saved); the message says why and what to do.

    Raised after the last good checkpoint is safe: ``train.py`` prints it as one line.
    """
