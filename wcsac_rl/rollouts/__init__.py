"""Whole episodes of a policy, below both training and evaluation.

* :mod:`~wcsac_rl.rollouts.episodes` — run test episodes (return, cost, length) and,
  optionally, record chosen entries of every step.
* :mod:`~wcsac_rl.rollouts.critic_calibration` — the safety critic's predictions at the
  states of recorded episodes against the realised cost-to-go.

The trainer logs both every epoch; :mod:`wcsac_rl.evaluation` uses them on finished runs
(and re-exports ``run_episodes``, ``summarize_episodes``, ``EpisodeResult``).
"""
