"""Evaluation: test episodes, the paper's metrics and figures."""

from wcsac_rl.evaluation.episodes import EpisodeResult, run_episodes, summarize_episodes

__all__ = ["EpisodeResult", "run_episodes", "summarize_episodes"]
