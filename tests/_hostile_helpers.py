"""Shared builders of the hostile-input suites, ``tests/test_red_team.py`` and
``tests/test_hostile_inputs.py`` (not collected: no ``test_`` prefix): a tiny trained run
shared by a module, every file of it hashed before and after each test, one-line error
checks, written once here."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from _training_helpers import ROOT, compose_config, tree_digests

from wcsac_rl.training import make_trainer

TINY = ("env=tiny", "env.max_episode_steps=50")

CLASSES = ("error", "handled", "fixed", "xfail")
"""How a case came out: ``error`` (one line naming the option or file, a non-zero exit,
no traceback), ``handled`` (it does the right thing), ``fixed`` (it was a traceback or
silently wrong, and is now one line), ``xfail`` (it is still a failure: the test asserts
the one line it should give and is marked ``xfail(strict=True)`` with the fix)."""


def train_tiny(run_dir: Path, *overrides: str) -> Path:
    """A finished tiny run at ``run_dir`` (in process: no Hydra records)."""
    trainer = make_trainer(compose_config(*TINY, *overrides), run_dir)
    try:
        trainer.run()
    finally:
        trainer.close()
    return run_dir


def files_unchanged(request, fixture: str, message: str):
    """The body of a module's autouse fixture: for a test that uses the module's shared
    ``fixture`` (a folder of runs), every file below it is byte-identical after the test."""
    if fixture not in request.fixturenames:
        yield
        return
    root = request.getfixturevalue(fixture)
    before = tree_digests(root)
    yield
    assert tree_digests(root) == before, message


def copy_run(run: Path, tmp_path: Path, name: str | None = None) -> Path:
    target = tmp_path / (name or run.name)
    shutil.copytree(run, target)
    return target


def one_line(message: str, *needles: str) -> None:
    """``message`` is one line, no traceback, and holds every needle."""
    assert "\n" not in message.strip(), message
    assert "Traceback" not in message, message
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"


def error_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error:")]


def parametrize(names: str, cases: list[tuple], fixes: dict[str, str]):
    """``pytest.mark.parametrize`` over ``cases`` (first item: the input, second: its
    class), the ``xfail`` ones marked strict with the fix from ``fixes``."""
    for case in cases:
        assert case[1] in CLASSES, case
        assert (case[1] == "xfail") == (case[0] in fixes), case[0]
    params = [
        pytest.param(
            *case,
            id=str(case[0]),
            marks=[pytest.mark.xfail(strict=True, reason=fixes[case[0]])]
            if case[1] == "xfail"
            else [],
        )
        for case in cases
    ]
    return pytest.mark.parametrize(names, params)


def train_py(cwd: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python train.py <overrides>`` in ``cwd`` (what a user types)."""
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *overrides],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


EVIDENCE_RUNS = ROOT / "results" / "evidence_static" / "runs"
"""The archived runs of a committed study (three seeds a row)."""


def evaluated_tiny_run(root: Path) -> Path:
    """``root`` holding ``wcsac``: a finished tiny WCSAC run (α = 0.5, 400 frames)
    evaluated on 2 episodes."""
    from wcsac_rl.evaluation.evaluator import evaluate_run

    train_tiny(root / "wcsac", "risk_level=0.5", "total_frames=400")
    evaluate_run(root / "wcsac", episodes=2, progress=False)
    return root


def copy_study(root: Path) -> Path:
    """``root`` holding two rows of three archived runs each (WCSAC-0.1, SAC-Lag; seeds
    0, 10, 20) copied from :data:`EVIDENCE_RUNS`."""
    for row in ("wcsac_0.1", "sac_lag"):
        for seed in (0, 10, 20):
            name = f"{row}_static_seed{seed}"
            shutil.copytree(EVIDENCE_RUNS / name, root / name)
    return root
