"""What every test shares: each starts from an empty ``torch.compile`` cache."""

from __future__ import annotations

import sys

import pytest


@pytest.fixture(autouse=True)
def _fresh_compile_cache():
    """Dynamo keys compiled graphs on the code object — for every TorchRL loss the one
    ``LossModule`` forward wrapper — and refuses a ninth recompilation of it under
    ``fullgraph=True``. In one test process (``TEST_WORKERS=0``, or a worker given many
    files) the losses compiled by earlier tests would make a later compile test fail
    because of the order it ran in, not its code; so each test's compilations end with it."""
    yield
    dynamo = sys.modules.get("torch._dynamo")
    if dynamo is not None:
        dynamo.reset()
