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

The names below are imported on first use, so that the console scripts' ``--help`` (which
reads :mod:`~wcsac_rl.evaluation.defaults`) answers before torch is imported.
"""

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

_METRICS = ("RISK_LEVELS", "aggregate_seeds", "curve_mean_std", "exceedance_proportion",
            "table1_metrics")  # fmt: skip
_EPISODES = ("EpisodeResult", "run_episodes", "summarize_episodes")


def __getattr__(name: str):
    """The names above, imported on first use (PEP 562): importing a light submodule
    (``wcsac_rl.evaluation.defaults``, for a console script's ``--help``) loads no torch."""
    if name in _METRICS:
        from wcsac_rl.evaluation import metrics as source
    elif name in _EPISODES:
        from wcsac_rl.rollouts import episodes as source
    else:
        raise AttributeError(f"module 'wcsac_rl.evaluation' has no attribute {name!r}")
    value = getattr(source, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
