"""What a reader follows through one update: the library files one ``loss(batch)`` runs.

One forward of a trainer's loss, on a batch the trainer sampled, traced with
``sys.setprofile``: the loss's own files (``wcsac_rl/objectives/``) are at most 7, and
with the kit's networks' own code (the actor's log-std clamp, the IQN critic's cosine
embedding, in ``wcsac_rl/modules/``) at most 9.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from _training_helpers import compose_config

import wcsac_rl
from wcsac_rl.training import make_trainer

PACKAGE = Path(wcsac_rl.__file__).parent
MAX_LOSS_FILES = 7
MAX_LIBRARY_FILES = 9


def forward_files(loss, batch) -> list[str]:
    """The package's files whose functions run during ``loss(batch)``, relative to it."""
    seen: set[str] = set()

    def profile(frame, event, arg):
        if event == "call":
            path = Path(frame.f_code.co_filename)
            if PACKAGE in path.parents:
                seen.add(path.relative_to(PACKAGE).as_posix())

    sys.setprofile(profile)
    try:
        loss(batch)
    finally:
        sys.setprofile(None)
    return sorted(seen)


def test_the_tracer_sees_a_library_call():
    """A loss that calls one library function is seen in that function's file only."""
    from wcsac_rl.objectives.risk import gaussian_cvar_multiplier

    assert forward_files(lambda _: gaussian_cvar_multiplier(0.1), None) == ["objectives/risk.py"]


@pytest.mark.parametrize("algo", ["wcsac", "wcsac_paper", "sac_lag"])
def test_one_forward_runs_few_library_files(tmp_path, algo):
    trainer = make_trainer(compose_config("env=tiny", f"algo={algo}"), tmp_path / "run")
    try:
        batches = iter(trainer.collector)
        for _ in range(2):
            trainer.learn(next(batches))
        files = forward_files(trainer.loss, trainer.sample())
    finally:
        trainer.close()
    loss_files = [f for f in files if f.startswith("objectives/")]
    assert "objectives/wcsac.py" in loss_files
    assert len(loss_files) <= MAX_LOSS_FILES, files
    assert len(files) <= MAX_LIBRARY_FILES, files
