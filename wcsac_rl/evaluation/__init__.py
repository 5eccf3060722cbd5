"""Evaluation: test episodes, the paper's metrics and figures.

* :mod:`~wcsac_rl.evaluation.episodes` — run whole test episodes (return, cost, length).
* :mod:`~wcsac_rl.evaluation.metrics` — Table 1's metrics (EC, C_α, ER, over budget)
  and their aggregation over seeds; pure functions.
* :mod:`~wcsac_rl.evaluation.runs` — finding run / sweep / evaluated directories; row names.
* :mod:`~wcsac_rl.evaluation.evaluator` — a run's final evaluation →
  ``evaluation.csv`` + ``evaluation.json`` (``python -m wcsac_rl.evaluate``).
* :mod:`~wcsac_rl.evaluation.calibration` — the safety critic's predictions against the
  realised cost-to-go of test episodes (``calib/*`` columns, ``python -m wcsac_rl.calibration``).
* :mod:`~wcsac_rl.evaluation.trajectories` — robot paths and MuJoCo videos of test episodes.
* :mod:`~wcsac_rl.evaluation.plots` — per-run curves and the paper's Figures 4, 5, 6.
* :mod:`~wcsac_rl.evaluation.reporting` — Table 1 + figures for a set of runs
  (``python -m wcsac_rl.report``).
"""

from wcsac_rl.evaluation.episodes import EpisodeResult, run_episodes, summarize_episodes
from wcsac_rl.evaluation.metrics import (
    RISK_LEVELS,
    aggregate_seeds,
    curve_mean_std,
    exceedance_proportion,
    table1_metrics,
)

__all__ = [
    "RISK_LEVELS",
    "EpisodeResult",
    "aggregate_seeds",
    "curve_mean_std",
    "exceedance_proportion",
    "run_episodes",
    "summarize_episodes",
    "table1_metrics",
]
