"""docs/testing.md states the suite's size as it is: the count it gives is within 5 % of
the tests pytest collects (a page that said 1 963 while 3 187 ran misled its readers)."""

from __future__ import annotations

import re
import subprocess
import sys

from _training_helpers import ROOT


def test_the_testing_page_states_how_many_tests_run():
    page = (ROOT / "docs" / "testing.md").read_text()
    stated = re.search(r"slow learning tests included \((\d[\d ]*) tests;", page)
    assert stated, "docs/testing.md no longer states the suite's size"
    count = int(stated.group(1).replace(" ", ""))
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    collected = int(re.search(r"(\d+) tests? collected", done.stdout).group(1))
    assert abs(collected - count) <= 0.05 * collected, (count, collected)
