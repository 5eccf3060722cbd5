"""The paper's Table 1 (StaticEnv, d = 15) and a side-by-side comparison with yours.

:data:`PAPER_TABLE1` holds the published numbers (docs/paper.md, "Table 1"); the
report writes :func:`paper_comparison_markdown` as ``table1_vs_paper.md`` next to
``table1.md`` when the runs are on an env the paper tabulates, at its budget.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from itertools import pairwise
from typing import Any

from wcsac_rl.evaluation.defaults import CLAIM_RUNS
from wcsac_rl.evaluation.latex import markdown_table
from wcsac_rl.evaluation.metrics import RISK_LEVELS, cvar_key
from wcsac_rl.evaluation.runs import env_title, row_name, row_sort_key

__all__ = ["PAPER_COST_LIMIT", "PAPER_ROW_OF", "PAPER_TABLE1", "paper_comparison_markdown"]

PAPER_COST_LIMIT = 15.0
"""The budget d of the paper's Table 1."""

PAPER_TABLE1: dict[str, dict[str, dict[str, float]]] = {
    "static": {
        "sac": {"EC": 21.7, "C0.9": 24.1, "C0.5": 42.8, "C0.1": 56.5, "ER": 0.97},
        "sac_lag": {"EC": 14.3, "C0.9": 15.9, "C0.5": 28.6, "C0.1": 141.8, "ER": 0.27},
        "wcsac_0.9": {"EC": 4.2, "C0.9": 4.6, "C0.5": 8.4, "C0.1": 31.4, "ER": 0.56},
        "wcsac_0.5": {"EC": 1.8, "C0.9": 2.0, "C0.5": 3.6, "C0.1": 17.9, "ER": 0.19},
        "wcsac_0.1": {"EC": 1.4, "C0.9": 1.6, "C0.5": 2.9, "C0.1": 14.3, "ER": -0.43},
        "cpo": {"EC": 16.3, "C0.9": 18.1, "C0.5": 32.5, "C0.1": 58.3, "ER": 0.84},
        "random": {"EC": 49.1, "C0.9": 54.5, "C0.5": 98.1, "C0.1": 431.6, "ER": -20.10},
    }
}
"""Table 1 of Yang et al. (2021) per env name and row label: 3 M training frames per
seed, 300 deterministic test episodes per row (100 per seed), d = 15. The paper
tabulates StaticEnv only (DynamicEnv is in its Figure 4)."""

PAPER_ROW_OF: dict[str, str] = {
    "sac_lag_paper": "sac_lag",
    "wcsac_paper_0.9": "wcsac_0.9",
    "wcsac_paper_0.5": "wcsac_0.5",
    "wcsac_paper_0.1": "wcsac_0.1",
    "wcsac_iqn_0.9": "wcsac_0.9",
    "wcsac_iqn_0.5": "wcsac_0.5",
    "wcsac_iqn_0.1": "wcsac_0.1",
}
"""Rows of this kit compared with a paper row of another label: the paper's own
formulation of a row, and WCSAC with the IQN critic against the paper's WCSAC."""

_COLUMNS = ("EC", *(cvar_key(a) for a in RISK_LEVELS), "ER")  # table1.md's


def _ranked(values: Mapping[str, float]) -> list[str]:
    """Row labels from the lowest value up (ties in the paper's row order)."""
    return sorted(values, key=lambda label: (values[label], row_sort_key(label)))


def _ordering(values: Mapping[str, float]) -> str:
    """``"WCSAC-0.1 < WCSAC-0.5 < SAC"``: row names from the lowest value up (ties ``=``)."""
    ranked = _ranked(values)
    text = row_name(ranked[0])
    for previous, label in pairwise(ranked):
        text += (" = " if values[label] == values[previous] else " < ") + row_name(label)
    return text


def paper_comparison_markdown(
    rows: Sequence[Mapping[str, Any]], env: str, cost_limit: float
) -> str | None:
    """Your Table 1 ``rows`` (from :func:`~wcsac_rl.evaluation.reporting.table1_rows`)
    beside the paper's, column by column, then the orderings of C0.1 and EC over the
    rows both tables have. ``None`` when the paper has no table for ``env`` or used
    another budget than ``cost_limit`` (the numbers would not be comparable).
    """
    paper = PAPER_TABLE1.get(env)
    if paper is None or float(cost_limit) != PAPER_COST_LIMIT:
        return None
    ours = {row["label"]: row for row in rows}
    compared = [label for label in ours if PAPER_ROW_OF.get(label, label) in paper]
    if not compared:
        return None
    header = ["Algorithm", "paper row"]
    for key in _COLUMNS:
        header += [f"{key} here", f"{key} paper"]
    body = []
    for label in compared:
        reference = PAPER_ROW_OF.get(label, label)
        cells = [row_name(label), row_name(reference)]
        for key in _COLUMNS:
            cells += [f"{float(ours[label][key]):.2f}", f"{paper[reference][key]:.2f}"]
        body.append(cells)
    lines = [
        f"# Table 1 here and in the paper — {env_title(env)}, budget d = {cost_limit:g}",
        "",
        *markdown_table(header, "ll" + "r" * (len(header) - 2), body),
    ]
    same = [label for label in compared if label in paper]  # the paper's own labels only
    lines.append("")
    if not same:  # (rows compared only through another label: nothing to order)
        lines += ["No ordering: none of the paper's own rows here.", ""]
    for key in ("C0.1", "EC") if same else ():
        here = {label: float(ours[label][key]) for label in same}
        there = {label: paper[label][key] for label in same}
        verdict = "the same order" if _ranked(here) == _ranked(there) else "a different order"
        runs = [ours[label].get("runs") for label in same]  # (table1_rows' count per row)
        fewest = None if None in runs else min(int(n) for n in runs)
        caveat = (  # (an ordering's rule: docs/evaluation_protocol.md)
            f"; not a finding: {fewest} run(s) in a row, an ordering needs {CLAIM_RUNS}"
            if fewest is not None and fewest < CLAIM_RUNS
            else ""
        )
        lines += [
            f"{key}, lowest first — here: {_ordering(here)}",
            f"{key}, lowest first — paper: {_ordering(there)}",
            f"({verdict} over the {len(same)} rows both tables have{caveat})",
            "",
        ]
    lines += [
        "Here: the runs of this report (training frames and seeds in table1.csv). Paper: "
        "Yang et al. 2021, Table 1, 3 M frames per seed, 300 test episodes per row. "
        "Rows of this kit without a paper label are set against the paper row named in "
        "the second column; the orderings use the rows with the paper's own labels.",
        "",
    ]
    return "\n".join(lines)
