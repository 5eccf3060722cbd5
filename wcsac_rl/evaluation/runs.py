"""Finding runs and evaluations on disk, and naming Table 1's rows.

A **run directory** is what ``train.py`` writes: ``config.yaml``, ``progress.csv``
and ``checkpoints/last.pt`` (single runs under ``outputs/<date>/<time>_<row>_<env>_seed<N>``,
sweeps under ``multirun/<date>/<time>/<job>_<row>_<env>_seed<N>``). An **evaluated
directory** also holds ``evaluation.csv`` + ``evaluation.json`` (written by
``python -m wcsac_rl.evaluate``); the random policy evaluated without a training
run gives an evaluated directory with no checkpoint.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from pathlib import Path

from wcsac_rl.envs.presets import env_title, has_goals
from wcsac_rl.training.checkpoint import CHECKPOINT_DIR, LAST_CHECKPOINT
from wcsac_rl.training.registry import ALGORITHMS, row_algorithm

__all__ = [
    "ACRONYMS",
    "EVALUATION_CSV",
    "EVALUATION_JSON",
    "ROW_ORDER",
    "STAGING_SUFFIX",
    "display_text",
    "env_has_layout",
    "env_title",
    "find_evaluated_dirs",
    "find_progress_dirs",
    "find_run_dirs",
    "has_checkpoint",
    "looks_like_run_dir",
    "make_row_label",
    "row_name",
    "row_sort_key",
    "split_row_label",
]

EVALUATION_CSV = "evaluation.csv"
EVALUATION_JSON = "evaluation.json"
STAGING_SUFFIX = ".partial"
"""A report is written into ``.<name>.<pid>.<token>.partial`` first and moved into place
when whole (:mod:`~wcsac_rl.evaluation.reporting`); one a killed report left behind is
not searched for runs (its archived copies would be counted twice)."""

ROW_ORDER: tuple[str, ...] = tuple(row for entry in ALGORITHMS.values() for row in entry.paper_rows)
"""Table 1's rows (``algo.label`` values) in the paper's order (the registry's
``paper_rows``)."""


def env_has_layout(env: str | None) -> bool:
    """Whether runs of ``env`` have a layout (hazards, goal) and goals to count
    (:func:`~wcsac_rl.envs.presets.has_goals`): a user's ``env=gymnasium`` env does not,
    so its report leaves out Figure 5's trajectories and the goals columns. ``None`` (no
    env known): as a preset."""
    return has_goals(env)


_TRAILING_NUMBER = re.compile(r"[0-9]+(?:\.[0-9]+)?$")
"""The number a row label ends with (α, or a variant's own cost limit)."""
_AT_LIMIT = re.compile(r"d([0-9.]+)")
"""A variant with its own cost limit d (conf/row/sac_lag_d<d>.yaml: the matched-mean control)."""
ACRONYMS = {"iqn": "IQN"}
"""Words of a row label written in capitals in its name (``wcsac_iqn_0.1``: WCSAC-IQN-0.1)."""


def row_name(label: str) -> str:
    """The paper's name of a row: its algorithm's title (the registry's), then the words
    of its variant: ``"sac_lag"`` → ``"SAC-Lag"``, ``"wcsac_0.5"`` → ``"WCSAC-0.5"``, the
    IQN safety critic's ``"wcsac_iqn_0.5"`` → ``"WCSAC-IQN-0.5"``, the paper's safety
    critic and κ ``"wcsac_paper_0.5"`` → ``"WCSAC-paper-0.5"``, a variant with its own
    cost limit ``"sac_lag_d1.5"`` → ``"SAC-Lag (d=1.5)"``.

    >>> row_name("wcsac_0.1"), row_name("wcsac_iqn_0.1"), row_name("random"), row_name("my_algo")
    ('WCSAC-0.1', 'WCSAC-IQN-0.1', 'Random Policy', 'my_algo')
    >>> row_name("wcsac_paper_0.1"), row_name("sac_lag_paper"), row_name("sac_lag_d1.5")
    ('WCSAC-paper-0.1', 'SAC-Lag-paper', 'SAC-Lag (d=1.5)')
    """
    base, settings = split_row_label(label)
    if settings:  # a row of a label split by a differing setting (make_row_label)
        return f"{row_name(base)} ({settings})"
    entry = row_algorithm(label)
    if entry is None:
        return label
    name = entry.title
    for word in label[len(entry.name) + 1 :].split("_") if label != entry.name else ():
        at = _AT_LIMIT.fullmatch(word)
        name += f" (d={at.group(1)})" if at else f"-{ACRONYMS.get(word, word)}"
    return name


def make_row_label(label: str, settings: dict[str, str]) -> str:
    """The row label of runs of ``label`` made with ``settings`` that other runs of the
    same label do not share: ``"sac_lag[cost_limit=1.5]"`` (no settings: ``label``).

    >>> make_row_label("sac_lag", {"cost_limit": "1.5"}), make_row_label("sac", {})
    ('sac_lag[cost_limit=1.5]', 'sac')
    >>> row_name("sac_lag[cost_limit=1.5]"), split_row_label("sac_lag[cost_limit=1.5]")
    ('SAC-Lag (cost_limit=1.5)', ('sac_lag', 'cost_limit=1.5'))
    """
    if not settings:
        return label
    return f"{label}[{', '.join(f'{key}={value}' for key, value in settings.items())}]"


def split_row_label(label: str) -> tuple[str, str]:
    """``(algo.label, settings)`` of a row label of :func:`make_row_label`."""
    if label.endswith("]") and "[" in label:
        base, settings = label[:-1].split("[", 1)
        return base, settings
    return label, ""


def row_sort_key(label: str) -> tuple[int, float, str]:
    """Sort key putting rows in the paper's order: by algorithm in the registry's order
    (SAC, SAC-Lag, CAL, WCSAC, CPO, Random Policy), within one the algorithm's own row
    first, then its variants without a number (``sac_lag_paper``), then those with one by
    decreasing number (WCSAC by decreasing α, the IQN critic's row after the Gaussian
    one of the same α; SAC-Lag with its own limit, the largest first); then unknown
    labels alphabetically.

    >>> sorted(["random", "wcsac_iqn_0.1", "wcsac_0.1", "sac", "wcsac_0.9"], key=row_sort_key)
    ['sac', 'wcsac_0.9', 'wcsac_0.1', 'wcsac_iqn_0.1', 'random']
    >>> sorted(["wcsac_0.5", "sac_lag_paper", "sac_lag", "cal"], key=row_sort_key)
    ['sac_lag', 'sac_lag_paper', 'cal', 'wcsac_0.5']
    >>> sorted(["wcsac_0.9", "sac_lag_d1.5", "sac_lag_d13.5", "sac_lag"], key=row_sort_key)
    ['sac_lag', 'sac_lag_d13.5', 'sac_lag_d1.5', 'wcsac_0.9']
    """
    base, settings = split_row_label(label)
    if settings:  # right after the row of its label's other settings
        order, value, _ = row_sort_key(base)
        return (order, value, label)
    entry = row_algorithm(label)
    if entry is None:
        return (len(ALGORITHMS), 0.0, label)
    order = list(ALGORITHMS).index(entry.name)
    number = _TRAILING_NUMBER.search(label[len(entry.name) :])
    return (order, 0.0 if number is None else 1.0 + 1.0 / (1.0 + float(number.group())), label)


def display_text(text: str) -> str:
    """``text`` as valid UTF-8: the bytes of a file name that is not UTF-8 (which Python
    carries as lone surrogates) are shown as U+FFFD, so that it can be printed and
    written into a report."""
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "replace").decode("utf-8")


def has_checkpoint(run_dir: str | os.PathLike) -> bool:
    """Whether ``run_dir/checkpoints/last.pt`` exists."""
    return (Path(run_dir) / CHECKPOINT_DIR / LAST_CHECKPOINT).is_file()


def looks_like_run_dir(path: str | os.PathLike) -> bool:
    """A directory written by ``train.py`` (it has ``config.yaml`` and ``progress.csv``
    or a checkpoint), whether or not its checkpoint survived."""
    path = Path(path)
    return (path / "config.yaml").is_file() and (
        (path / "progress.csv").is_file() or has_checkpoint(path)
    )


def _walk(root: Path) -> Iterable[Path]:
    """``root`` and every directory below it (sorted, symlinks not followed; a report's
    staging directory left behind, ``.*.partial``, not entered)."""
    yield root
    for dirpath, dirnames, _ in os.walk(root):
        dirnames[:] = sorted(
            d for d in dirnames if not (d.startswith(".") and d.endswith(STAGING_SUFFIX))
        )
        for name in dirnames:
            yield Path(dirpath) / name


def _no_checkpoint(path: Path) -> str:
    return (
        f"{path}: run directory without a checkpoint "
        f"(expected {path / CHECKPOINT_DIR / LAST_CHECKPOINT})"
    )


def find_run_dirs(
    paths: Iterable[str | os.PathLike], *, accounted: Iterable[str | os.PathLike] = ()
) -> tuple[list[Path], list[str]]:
    """Run directories to evaluate under ``paths`` (run dirs and/or sweep dirs).

    A path that is itself a run directory is taken as one (with or without its
    checkpoint); any other directory is searched recursively for run directories
    (directories below a run directory are not searched further).

    Args:
        accounted: directories whose lack of a checkpoint is reported elsewhere (a
            sweep's jobs, :mod:`~wcsac_rl.evaluation.sweeps`): no error line for them.

    Returns:
        ``(run_dirs, errors)``: the run directories with a checkpoint, in the order
        given (each once), and one error line per run directory without a
        checkpoint (given or found) and per path that does not exist or holds no run.
    """
    found: list[Path] = []
    errors: list[str] = []
    known = {Path(d).expanduser().resolve() for d in accounted}

    def no_checkpoint(path: Path) -> None:
        if path.resolve() not in known:
            errors.append(_no_checkpoint(path))

    for raw in paths:
        path = Path(raw).expanduser()
        if not path.exists():
            errors.append(f"{path}: no such file or directory")
            continue
        if path.is_file():
            if path.name == LAST_CHECKPOINT and path.parent.name == CHECKPOINT_DIR:
                path = path.parent.parent
            else:
                errors.append(f"{path}: not a run directory (expected a directory)")
                continue
        if has_checkpoint(path):
            found.append(path)
            continue
        if looks_like_run_dir(path) or path.resolve() in known:
            no_checkpoint(path)
            continue
        below = []
        run_roots: list[Path] = []
        for candidate in _walk(path):
            if any(root in candidate.parents for root in run_roots):
                continue
            if has_checkpoint(candidate):
                below.append(candidate)
                run_roots.append(candidate)
            elif looks_like_run_dir(candidate) or candidate.resolve() in known:
                no_checkpoint(candidate)
                run_roots.append(candidate)
        if not run_roots:
            errors.append(f"{path}: no run directories with {CHECKPOINT_DIR}/{LAST_CHECKPOINT}")
        found.extend(below)
    unique = list(dict.fromkeys(p.resolve() for p in found))
    return unique, errors


def _find_holding(paths: Iterable[str | os.PathLike], *names: str) -> list[Path]:
    """Every directory at or below ``paths`` holding each of ``names`` (sorted, unique)."""
    found = [
        d
        for raw in paths
        if Path(raw).expanduser().is_dir()
        for d in _walk(Path(raw).expanduser())
        if all((d / name).is_file() for name in names)
    ]
    return sorted(dict.fromkeys(p.resolve() for p in found))


def find_evaluated_dirs(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Every directory at or below ``paths`` that holds ``evaluation.json`` (sorted, unique)."""
    return _find_holding(paths, EVALUATION_JSON)


def find_progress_dirs(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Every run directory at or below ``paths`` with ``config.yaml`` and ``progress.csv``."""
    return _find_holding(paths, "config.yaml", "progress.csv")
