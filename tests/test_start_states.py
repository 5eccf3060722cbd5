"""StartStateBuffer: the episode start states a κ loss at start states reads."""

from __future__ import annotations

import pytest
import torch
from _loss_helpers import OBS_DIM, make_batch, make_loss
from tensordict import TensorDict

from wcsac_rl.objectives import StartStateBuffer


def _collected(step_count: torch.Tensor, **extra) -> TensorDict:
    """A collector-shaped batch [envs, time] whose observation encodes (env, t)."""
    envs, horizon = step_count.shape
    obs = torch.arange(envs * horizon, dtype=torch.float32).reshape(envs, horizon, 1)
    return TensorDict(
        {
            "observation": obs.expand(envs, horizon, OBS_DIM).clone(),
            "step_count": step_count.unsqueeze(-1),
            "action": torch.zeros(envs, horizon, 2),
            **extra,
        },
        [envs, horizon],
    )


def test_add_starts_keeps_only_first_steps_and_only_the_state_entries():
    steps = torch.tensor([[5, 6, 0, 1], [0, 1, 2, 0]])
    buffer = StartStateBuffer(["observation"], capacity=100)
    assert buffer.add_starts(_collected(steps)) == 3
    stored = buffer[:].exclude("index")  # the replay buffer's own bookkeeping
    assert set(stored.keys()) == {"observation"}
    # rows (0, 2), (1, 0), (1, 3) of the flattened 2 x 4 batch: indices 2, 4, 7
    assert sorted(stored["observation"][:, 0].tolist()) == [2.0, 4.0, 7.0]
    assert buffer.add_starts(_collected(torch.tensor([[3, 4]]))) == 0
    assert len(buffer) == 3


def test_init_tracker_flags_take_precedence_over_step_counts():
    steps = torch.tensor([[0, 1, 2]])
    is_init = torch.tensor([[[False], [True], [False]]])
    buffer = StartStateBuffer()
    assert buffer.add_starts(_collected(steps, is_init=is_init)) == 1
    assert buffer[:]["observation"][0, 0].item() == 1.0


def test_capacity_keeps_the_most_recent_start_states():
    buffer = StartStateBuffer(capacity=2)
    for first in (0.0, 10.0, 20.0):
        batch = _collected(torch.tensor([[0]]))
        batch["observation"] += first
        buffer.add_starts(batch)
    assert len(buffer) == 2
    assert sorted(buffer[:]["observation"][:, 0].tolist()) == [10.0, 20.0]


def test_attach_gives_every_row_a_stored_start_state():
    buffer = StartStateBuffer(out_key="starts")
    buffer.add_starts(_collected(torch.tensor([[0, 1, 0, 1, 0]])))  # observations 0, 2, 4
    batch = buffer.attach(make_batch(64))
    assert batch["starts"].batch_size == torch.Size([64])
    assert set(batch["starts"].keys()) == {"observation"}
    drawn = set(batch["starts", "observation"][:, 0].tolist())
    assert drawn <= {0.0, 2.0, 4.0} and len(drawn) > 1  # uniform draws, not one row


def test_errors_name_the_missing_piece_and_change_nothing():
    buffer = StartStateBuffer()
    with pytest.raises(RuntimeError, match="no start states yet"):
        buffer.attach(make_batch(4))
    no_counter = _collected(torch.tensor([[0, 1]])).exclude("step_count")
    with pytest.raises(KeyError, match="StepCounter"):
        buffer.add_starts(no_counter)
    other = StartStateBuffer(["pixels"])
    with pytest.raises(KeyError, match="pixels"):
        other.add_starts(_collected(torch.tensor([[0]])))
    assert len(buffer) == 0 and len(other) == 0
    buffer.add_starts(_collected(torch.tensor([[0]])))
    with pytest.raises(ValueError, match="flat batch"):
        buffer.attach(make_batch(4).reshape(2, 2))
    for capacity in (0, 2.5):
        with pytest.raises(ValueError, match="capacity"):
            StartStateBuffer(capacity=capacity)
    with pytest.raises(ValueError, match="state_keys"):
        StartStateBuffer([])


def test_for_loss_feeds_a_kappa_at_start_states_loss():
    loss = make_loss(risk_level=0.1, kappa_states="initial", cost_limit=15.0)
    buffer = StartStateBuffer.for_loss(loss)
    assert buffer.state_keys == loss.initial_state_keys
    assert buffer.out_key == loss.tensor_keys.initial_states
    starts = _collected(torch.tensor([[0, 1, 2, 0]]))
    starts["observation"] = torch.randn(1, 4, OBS_DIM)
    buffer.add_starts(starts)
    out = loss(buffer.attach(make_batch(16)))
    assert torch.isfinite(out["loss_kappa"]) and torch.isfinite(out["cvar"])
    out["loss_kappa"].backward()
    assert loss.kappa_raw.grad is not None and loss.kappa_raw.grad != 0


def test_for_loss_follows_the_loss_s_initial_states_key_set_after_it():
    loss = make_loss(risk_level=0.1, kappa_states="initial", cost_limit=15.0)
    buffer = StartStateBuffer.for_loss(loss)
    loss.set_keys(initial_states="starts")
    starts = _collected(torch.tensor([[0, 1, 2, 0]]))
    starts["observation"] = torch.randn(1, 4, OBS_DIM)
    buffer.add_starts(starts)
    batch = buffer.attach(make_batch(16))
    assert buffer.out_key == "starts" and "starts" in batch.keys() and "initial" not in batch
    assert torch.isfinite(loss(batch)["loss_kappa"])
    with pytest.raises(AttributeError, match=r"loss\.set_keys\(initial_states=\.\.\.\)"):
        buffer.out_key = "other"
