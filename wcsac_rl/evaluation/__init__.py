"""Evaluation: test episodes, the paper's metrics and figures.

* test episodes themselves are :mod:`wcsac_rl.rollouts` (shared with training);
  ``run_episodes``, ``summarize_episodes`` and ``EpisodeResult`` are re-exported here.
* :mod:`~wcsac_rl.evaluation.metrics` — Table 1's metrics (EC, C_α, ER, over budget)
  and their aggregation over seeds; pure functions.
* :mod:`~wcsac_rl.evaluation.runs` — finding run / sweep / evaluated directories; row names.
* :mod:`~wcsac_rl.evaluation.evaluator` — a run's final evaluation →
  ``evaluation.csv`` + ``evaluation.json`` (``python -m wcsac_rl.evaluate``).
* :mod:`~wcsac_rl.evaluation.run_calibration` — a finished run's safety critic against the
  realised cost-to-go of its test episodes (``python -m wcsac_rl.calibration``; the
  measurement is :mod:`wcsac_rl.rollouts.critic_calibration`, logged each epoch as ``calib/*``).
* :mod:`~wcsac_rl.evaluation.trajectories` — robot paths and MuJoCo videos of test episodes.
* :mod:`~wcsac_rl.evaluation.plots` — per-run curves and the paper's Figures 4, 5, 6.
* :mod:`~wcsac_rl.evaluation.reporting` — Table 1 + figures for a set of runs
  (``python -m wcsac_rl.report``).
* :mod:`~wcsac_rl.evaluation.run_statistics` — statistics over runs (IQM, probability of
  improvement, their bootstrap intervals); :mod:`~wcsac_rl.evaluation.run_report` and
  :mod:`~wcsac_rl.evaluation.run_plots` — the report's runs one by one and their figures.
"""

from wcsac_rl.evaluation.metrics import (
    RISK_LEVELS,
    aggregate_seeds,
    curve_mean_std,
    exceedance_proportion,
    table1_metrics,
)
from wcsac_rl.rollouts.episodes import EpisodeResult, run_episodes, summarize_episodes

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
