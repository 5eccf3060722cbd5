"""Named option sets of :class:`~wcsac_rl.objectives.WCSACLoss`."""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

__all__ = ["PAPER_OPTIONS"]

PAPER_OPTIONS: Mapping[str, Any] = MappingProxyType(
    {
        "variance_target": "moment",
        "cost_gamma": None,
        "cost_n_steps": 1,
        "nonnegative_cost": False,
        "kappa_states": "replay",
        "kappa_statistic": "mean",
        "kappa_signal": "critic",
        "kappa_rule": "gradient",
    }
)
"""The safety critic and κ as the paper writes them (Eq. 7–8, one-step targets with the
reward's γ, κ on the mean Γ over replay states against the per-step threshold):
``WCSACLoss(..., **PAPER_OPTIONS)``. The defaults differ, on StaticEnv evidence
(docs/defaults.md); ``algo=wcsac_paper`` is the same in the config."""
