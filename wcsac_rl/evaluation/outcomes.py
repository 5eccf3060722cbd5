"""Episode outcomes: every test episode classed by what happened in it, so that a reader
sees whether a run learned its task instead of inferring it from a negative return.

With a goal (:func:`~wcsac_rl.evaluation.runs.env_has_layout`) the classes are
:data:`GOAL_OUTCOMES`, without one :data:`PLAIN_OUTCOMES`; a run **learned** its task when
at least :data:`LEARNED_GOAL_SHARE` of its test episodes reached the goal. The classes,
``outcomes.md`` / ``.csv`` and ``fig_outcomes.png``: docs/evaluation_protocol.md.

>>> from wcsac_rl.rollouts.episodes import EpisodeResult
>>> episodes = [EpisodeResult(1.0, 0.0, 300, 1, False), EpisodeResult(-9.0, 12.0, 1000, 0, False)]
>>> outcome_counts(episodes, has_goals=True)
{'goal': 1, 'goal_cost': 0, 'no_goal': 0, 'no_goal_cost': 1, 'failure': 0}
>>> goal_share(outcome_counts(episodes, has_goals=True))
0.5
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from wcsac_rl.evaluation.latex import csv_text, markdown_cell, markdown_table, markdown_text

__all__ = [
    "FIG_OUTCOMES",
    "GOAL_OUTCOMES",
    "LEARNED_GOAL_SHARE",
    "OUTCOMES_CSV",
    "OUTCOMES_MD",
    "OUTCOME_TITLES",
    "PLAIN_OUTCOMES",
    "episode_outcome",
    "goal_share",
    "learned",
    "outcome_classes",
    "outcome_counts",
    "outcome_rows",
    "outcomes_csv",
    "outcomes_markdown",
    "plot_outcomes",
]

GOAL_OUTCOMES = ("goal", "goal_cost", "no_goal", "no_goal_cost", "failure")
"""The classes of an episode on an env with a goal, in the order tables and bars show them."""
PLAIN_OUTCOMES = ("cost_free", "cost", "failure")
"""The classes of an episode on an env without goals."""
OUTCOME_TITLES = {
    "goal": "goal, cost-free",
    "goal_cost": "goal, with cost",
    "no_goal": "no goal, cost-free",
    "no_goal_cost": "no goal, with cost",
    "cost_free": "cost-free",
    "cost": "with cost",
    "failure": "numerical failure",
}
"""Each class as a table's column heading and a figure's legend entry."""
LEARNED_GOAL_SHARE = 0.95
"""The share of test episodes reaching the goal above which a run learned its task."""


def outcome_classes(has_goals: bool) -> tuple[str, ...]:
    """The classes of an env with (:data:`GOAL_OUTCOMES`) or without goals."""
    return GOAL_OUTCOMES if has_goals else PLAIN_OUTCOMES


def episode_outcome(episode: Any, has_goals: bool) -> str:
    """The class of one episode (an :class:`~wcsac_rl.rollouts.episodes.EpisodeResult`:
    its ``cost``, ``goal_reached`` and ``numerical_failure``)."""
    if episode.numerical_failure:
        return "failure"
    with_cost = episode.cost > 0
    if not has_goals:
        return "cost" if with_cost else "cost_free"
    reached = "goal" if episode.goal_reached > 0 else "no_goal"
    return f"{reached}_cost" if with_cost else reached


def outcome_counts(episodes: Iterable[Any], has_goals: bool) -> dict[str, int]:
    """Episodes per class, every class of the env in order (0 included)."""
    counts = dict.fromkeys(outcome_classes(has_goals), 0)
    for episode in episodes:
        counts[episode_outcome(episode, has_goals)] += 1
    return counts


def goal_share(counts: Mapping[str, int]) -> float:
    """The share of episodes that reached the goal (NaN: no goals, or no episodes)."""
    total = sum(counts.values())
    if "goal" not in counts or not total:
        return float("nan")
    return (counts["goal"] + counts["goal_cost"]) / total


def learned(counts: Mapping[str, int]) -> str:
    """``yes`` / ``no`` by :data:`LEARNED_GOAL_SHARE`, ``-`` on an env without goals."""
    share = goal_share(counts)
    if share != share:  # NaN
        return "-"
    return "yes" if share >= LEARNED_GOAL_SHARE else "no"


def outcome_columns(classes: Sequence[str]) -> list[str]:
    """The outcome table's columns after ``row`` and ``seed``."""
    return [*classes, "episodes", *(["learned"] if "goal" in classes else [])]


OUTCOMES_MD = "outcomes.md"
OUTCOMES_CSV = "outcomes.csv"
FIG_OUTCOMES = "fig_outcomes.png"
_COLORS = {
    "goal": "#2ca02c",
    "goal_cost": "#bcbd22",
    "no_goal": "#9e9e9e",
    "no_goal_cost": "#d62728",
    "cost_free": "#2ca02c",
    "cost": "#d62728",
    "failure": "#000000",
}


def outcome_rows(evaluations: Sequence[Any], has_goals: bool) -> list[dict[str, Any]]:
    """One row per evaluated run (an :class:`~wcsac_rl.evaluation.evaluator.Evaluation`),
    by row then seed: ``label``, ``algorithm``, ``seed``, ``run`` and the counts."""
    from wcsac_rl.evaluation.runs import row_name, row_sort_key

    rows = [
        {
            "label": ev.label,
            "algorithm": row_name(ev.label),
            "seed": int(ev.meta.get("seed", -1)),
            "run": ev.directory.name,
            "counts": outcome_counts(ev.episodes, has_goals),
        }
        for ev in evaluations
    ]
    return sorted(rows, key=lambda r: (row_sort_key(r["label"]), r["seed"], r["run"]))


def outcomes_markdown(rows: Sequence[Mapping[str, Any]], title: str, has_goals: bool) -> str:
    """``outcomes.md``: a column per class (episodes), one line per run."""
    classes = outcome_classes(has_goals)
    columns = outcome_columns(classes)
    head = ["row", "seed", *(OUTCOME_TITLES.get(c, c) for c in columns), "run"]
    lines = [
        f"# Episode outcomes — {markdown_text(title)}",
        "",
        "The test episodes of each run's final policy by what happened in them (episodes; "
        + (
            f"learned: at least {LEARNED_GOAL_SHARE:.0%} of them reached the goal)."
            if has_goals
            else "the env has no goal)."
        ),
        "",
    ]
    body = []
    for row in rows:
        counts = row["counts"]
        cells = [markdown_cell(row["algorithm"]), row["seed"], *(counts[c] for c in classes)]
        cells += [sum(counts.values()), *([learned(counts)] if has_goals else [])]
        body.append([*cells, markdown_cell(row["run"])])
    align = "lr" + "r" * len(classes) + "r" + ("l" if has_goals else "") + "l"
    return "\n".join(lines + markdown_table(head, align, body)) + "\n"


def outcomes_csv(rows: Sequence[Mapping[str, Any]], has_goals: bool) -> str:
    """``outcomes.csv``: ``label, algorithm, seed, run``, the counts, ``episodes`` and
    (with goals) ``goal_share``."""
    classes = outcome_classes(has_goals)
    columns = ["label", "algorithm", "seed", "run", *classes, "episodes"]
    columns += ["goal_share"] if has_goals else []
    return csv_text(
        (
            {**row, **row["counts"], "episodes": sum(row["counts"].values()),
             "goal_share": repr(goal_share(row["counts"]))}
            for row in rows
        ),
        columns,
    )  # fmt: skip


def plot_outcomes(
    rows: Sequence[Mapping[str, Any]],
    out: Any,
    *,
    title: str,
    has_goals: bool,
    formats: Sequence[str] = ("png",),
) -> None:
    """``fig_outcomes.png``: one horizontal bar per run, its episodes' shares stacked by
    class (the first run on top), the runs grouped by row."""
    from matplotlib.figure import Figure

    from wcsac_rl.evaluation.plots import draw_literally, save_figure

    classes = outcome_classes(has_goals)
    n = len(rows)
    fig = Figure(figsize=(7.5, 1.4 + 0.24 * n), layout="constrained")
    ax = fig.subplots()
    y = list(range(n))[::-1]
    left = [0.0] * n
    for cls in classes:
        shares = [row["counts"][cls] / max(sum(row["counts"].values()), 1) for row in rows]
        ax.barh(y, shares, left=left, height=0.75, color=_COLORS[cls], label=OUTCOME_TITLES[cls])
        left = [a + b for a, b in zip(left, shares)]
    ax.set_yticks(y, [f"{row['algorithm']}  seed {row['seed']}" for row in rows], fontsize=8)
    draw_literally(ax.get_yticklabels())  # (names from run data: a "$" is a character)
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(-0.6, n - 0.4)
    ax.set_xlabel("share of test episodes")
    if has_goals:
        ax.axvline(LEARNED_GOAL_SHARE, color="k", linestyle="--", linewidth=1)
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=3, fontsize=8,
              frameon=False)  # fmt: skip
    draw_literally(fig.suptitle(f"Episode outcomes — {title}"))
    save_figure(fig, out, formats=formats)
