"""The evaluation protocol's defaults, in a module that imports nothing: the console
scripts' ``--help`` shows them before torch is imported."""

from __future__ import annotations

__all__ = ["CLAIM_RUNS", "DEFAULT_EPISODES", "DEFAULT_SEED_OFFSET"]

DEFAULT_EPISODES = 100
"""Test episodes per run (the paper: 100 per seed, 300 per algorithm)."""
DEFAULT_SEED_OFFSET = 2_000_003
"""Test episode k of a run is seeded ``k + seed + DEFAULT_SEED_OFFSET``: apart from the
training seeds (:mod:`~wcsac_rl.evaluation.evaluator`)."""
CLAIM_RUNS = 10
"""Held-out runs per row an ordering claim needs (docs/evaluation_protocol.md)."""
