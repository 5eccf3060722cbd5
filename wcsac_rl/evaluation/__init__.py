"""Evaluation: test episodes, the paper's metrics, a run's evaluation and calibration, the
report's tables and figures (its modules: docs/layout.md; the console scripts
``python -m wcsac_rl.evaluate``, ``wcsac_rl.calibration`` and ``wcsac_rl.report``).

The test episodes themselves are :mod:`wcsac_rl.rollouts` (shared with training); the names
below are imported on first use, so that the console scripts' ``--help`` (which reads
:mod:`~wcsac_rl.evaluation.defaults`) answers before torch is imported.
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
