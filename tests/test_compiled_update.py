"""``compile=true`` compiles the whole update (loss forward, backward, the optimizers'
steps, the targets' Polyak update) as one function; it computes what the eager update
computes: the same losses and gradients, each update started from the same state.

Inductor draws its own random numbers unless told to fall back to ATen's
(``fallback_random``); the test tells it, so both updates draw the same actor noise.
``cudagraphs=true`` (replaying the update as a CUDA graph) needs a CUDA device: here it
is refused in one line."""

from __future__ import annotations

import time

import pytest
import torch
from _tolerance import assert_close_f32
from _training_helpers import compose_config, fill_replay_alike

from wcsac_rl.training import make_trainer
from wcsac_rl.training.config import ConfigError

UPDATES = 3


def _grad_recorder(trainer) -> dict[str, list[torch.Tensor]]:
    """Each parameter's gradient at every backward (hooks; the update zeroes them)."""
    grads: dict[str, list[torch.Tensor]] = {}
    for name, param in trainer.loss.named_parameters():
        grads[name] = []
        param.register_post_accumulate_grad_hook(
            torch.compiler.disable(lambda p, seen=grads[name]: seen.append(p.grad.detach().clone()))
        )
    return grads


def _copy_state(source, dest) -> None:
    """``source``'s parameters, targets, buffers and optimizer state into ``dest``'s own
    tensors (in place: the compiled function keeps reading the same tensors)."""
    with torch.no_grad():
        theirs = source.loss.state_dict()
        for key, value in dest.loss.state_dict().items():
            value.copy_(theirs[key])
        for name, optimizer in dest.optimizers.items():
            other = source.optimizers[name]
            for group, other_group in zip(optimizer.param_groups, other.param_groups):
                for p, q in zip(group["params"], other_group["params"]):
                    for key, value in optimizer.state[p].items():
                        value.copy_(other.state[q][key])


def _assert_same_state(eager, compiled) -> None:
    """After one update from the same state: the same parameters and targets (Adam
    moves an entry by at most ``lr``, and by ``lr`` times the gradient's relative error
    more where that gradient is at rounding level: 1 % of ``lr`` bounds it, ``tau`` times
    that for a target; a step not taken is off by a good fraction of ``lr``, a target
    not averaged by ``tau`` times that), the same Adam moments (linear and quadratic in
    the gradients) and step counts."""
    lr, tau = float(eager.cfg.algo.lr), float(eager.cfg.algo.tau)
    theirs = eager.loss.state_dict()
    for key, value in compiled.loss.state_dict().items():
        expected = theirs[key]
        if not expected.is_floating_point():
            assert torch.equal(value, expected), key
            continue
        # a few roundings at the entries' size (an Adam step, a lerp), plus the step's
        # share: 1 % of lr, times tau for a target
        share = 0.01 * lr * (tau if "target_" in key else 1.0)
        tolerance = share + 4 * 2.0**-23 * float(expected.abs().max())
        assert (value - expected).abs().max() <= tolerance, key
    for name, optimizer in compiled.optimizers.items():
        other = eager.optimizers[name]
        for group, other_group in zip(optimizer.param_groups, other.param_groups):
            for p, q in zip(group["params"], other_group["params"]):
                mine, expected = optimizer.state[p], other.state[q]
                assert torch.equal(mine["step"], expected["step"]), name
                assert_close_f32(mine["exp_avg"], expected["exp_avg"], ops=64, msg=name)
                assert_close_f32(mine["exp_avg_sq"], expected["exp_avg_sq"], ops=128, msg=name)


def test_the_compiled_update_gives_the_eager_updates_losses_and_gradients(tmp_path, monkeypatch):
    monkeypatch.setattr(torch._inductor.config, "fallback_random", True)
    eager = make_trainer(compose_config("env=tiny", "algo=wcsac"), tmp_path / "eager")
    compiled = make_trainer(
        compose_config("env=tiny", "algo=wcsac", "compile=true"), tmp_path / "compiled"
    )
    try:
        fill_replay_alike(eager, compiled)
        eager_grads, compiled_grads = _grad_recorder(eager), _grad_recorder(compiled)
        first_call = None
        for update in range(UPDATES):
            if update:  # (the first: both built alike, with the same seed)
                _copy_state(eager, compiled)
            sample, rng = eager.sample(), torch.get_rng_state()
            expected = eager.update(sample.clone())
            torch.set_rng_state(rng)
            start = time.perf_counter()
            actual = compiled.update(sample.clone())
            first_call = first_call or time.perf_counter() - start
            assert expected is not None and actual is not None
            _assert_same_state(eager, compiled)
            assert sorted(actual.keys()) == sorted(expected.keys())
            for key in expected.keys():
                if key.startswith("loss_"):
                    # inductor's fused kernels sum in another order than ATen's: batch
                    # means of 64 rows (seen here: 1.3 roundings at the loss's size)
                    assert_close_f32(actual[key], expected[key], ops=64, msg=key)
        print(f"first compiled update (the compilation): {first_call:.1f} s")
        for name, expected in eager_grads.items():
            actual = compiled_grads[name]
            assert len(actual) == len(expected) == UPDATES, name
            for step, (a, e) in enumerate(zip(actual, expected)):
                # each entry sums 64 rows' terms of the tensor's largest entry's size
                # (seen here: 3.1 roundings)
                assert_close_f32(a, e, ops=64, msg=f"{name} at update {step}")
        # and a wrong gradient would be caught: the actor's moves with the batch
        first = eager_grads[next(n for n in eager_grads if "actor" in n)]
        assert not torch.equal(first[0], first[1])
    finally:
        eager.close()
        compiled.close()


def test_cudagraphs_without_a_cuda_device_is_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError) as excinfo:
        make_trainer(compose_config("env=tiny", "algo=wcsac", "cudagraphs=true"), tmp_path / "r")
    message = str(excinfo.value)
    assert "\n" not in message and "device=cuda" in message and "device=cpu" in message
