"""The README's WCSACLoss example runs as written."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_wcsac_loss_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    example = blocks[0]
    assert len(example.splitlines()) <= 40
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)  # e.g. TorchRL's InitTracker warning
        exec(compile(example, str(README), "exec"), {"__name__": "readme_example"})
    printed = capsys.readouterr().out
    assert "kappa" in printed and "cvar" in printed
    assert "NStepCost.for_loss(loss)" in example  # built as examples/pendulum_wcsac.py builds it
