"""What a resume restores, exactly (docs/training.md, "What a resume restores").

Restored bit for bit: networks, targets, β, κ, every optimizer's state, the replay and
start-state buffers (with ``save_replay_buffer``), the counters, the epoch in progress
and the global RNG states. Not restored: the envs' episodes in progress, their RNGs and
the collector's state: a resumed run starts new episodes, so it is not bit-identical
to an uninterrupted one.
"""

from __future__ import annotations

import random

import numpy as np
import torch
from _training_helpers import compose_config

from wcsac_rl.training import make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, numpy_rng_state

OPTIONS = ("env=tiny", "save_replay_buffer=true", "algo.kappa_states=initial")


def _equal_states(a, b, where=""):
    assert type(a) is type(b) or (torch.is_tensor(a) and torch.is_tensor(b)), where
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _equal_states(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _equal_states(x, y, f"{where}[{i}]")
    elif torch.is_tensor(a):
        assert a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b), where
    else:
        assert a == b, where


def test_a_resume_restores_the_learner_buffers_counters_and_rng_states_exactly(tmp_path):
    run_dir = tmp_path / "run"
    first = make_trainer(compose_config(*OPTIONS), run_dir)
    try:
        first.run()
        saved = load_checkpoint(first.checkpoint_path)
        learner = first.learner_state()
    finally:
        first.close()
    resumed = make_trainer(
        compose_config(*OPTIONS, "total_frames=1200", f"resume={run_dir}"), run_dir
    )
    try:
        _equal_states(resumed.loss.state_dict(), learner["loss"], "loss")
        for key, optimizer in resumed.optimizers.items():
            _equal_states(optimizer.state_dict(), learner["optimizers"][key], f"optimizers.{key}")
        for name in ("replay_buffer", "initial_state_buffer"):
            ours, theirs = getattr(resumed, name), getattr(first, name)
            assert len(ours) == len(theirs)
            _equal_states(ours[:].to_dict(), theirs[:].to_dict(), name)
            assert ours.write_count == theirs.write_count  # the next write goes to the same row
        assert (resumed.tracker.frames, resumed.updates, resumed.epoch) == (800, 200, 2)
        assert resumed.tracker.total_cost == first.tracker.total_cost
        _equal_states(torch.get_rng_state(), saved["rng"]["torch"], "torch rng")
        _equal_states(numpy_rng_state(), saved["rng"]["numpy"], "numpy rng")
        assert random.getstate() == saved["rng"]["python"]
        # not restored: the training envs start new episodes, seeded seed + frames
        assert resumed.update_start_frames == 200  # the buffer came back: no refill
    finally:
        resumed.close()
