"""Code and docs speak of the project, not of its history: no issue numbers in the
package, its tests, docs, configs, examples or README (a study's own pages under results/
and benchmarks/ record when and why they were made, and may)."""

from __future__ import annotations

import re

import pytest
from _training_helpers import ROOT

ISSUE_NUMBER = re.compile(r"\b[Ii]ssues? *#?\d+")
SCANNED = ["wcsac_rl", "tests", "docs", "conf", "examples"]
SUFFIXES = {".py", ".md", ".yaml", ".rst", ".txt"}
FILES = [
    *sorted(
        p
        for folder in SCANNED
        for p in (ROOT / folder).rglob("*")
        if p.suffix in SUFFIXES and p.is_file()
    ),
    ROOT / "README.md",
    ROOT / "train.py",
]


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(ROOT)) for p in FILES])
def test_no_issue_numbers(path):
    hits = [
        f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if ISSUE_NUMBER.search(line)
    ]
    assert not hits, "\n".join(hits)
