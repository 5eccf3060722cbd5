"""An update reads nothing back to the host: the finite checks and the skip of a
non-finite update happen on the device (fused Adam's ``found_inf``, a Polyak weight of
0), and the training loop reads a batch's updates once, after the last one. The masked
step gives the same parameters, bit for bit, as an unmasked one where all is finite.

``algo=sac`` runs TorchRL's ``SACLoss``; the kit's actor builds its distribution as a
``SyncFreeTanhNormal``, TorchRL's ``TanhNormal`` without the bound checks that read 3
values per construction (6 per SAC update) in eager mode."""

from __future__ import annotations

import traceback

import pytest
import torch
from _training_helpers import compose_config, fill_replay_alike
from torch.overrides import TorchFunctionMode
from torchrl.modules import TanhNormal

from wcsac_rl.modules.actor import SyncFreeTanhNormal
from wcsac_rl.training import make_trainer

HOST_READS = {
    torch.Tensor.item,
    torch.Tensor.tolist,
    torch.Tensor.numpy,
    torch.Tensor.cpu,
    torch.Tensor.__bool__,
    torch.Tensor.__int__,
    torch.Tensor.__float__,
    torch.Tensor.__index__,
}
"""What copies a tensor's value to Python (a host synchronisation on an accelerator)."""


class HostReads(TorchFunctionMode):
    """Record every host read while active: the function and the library line."""

    def __init__(self) -> None:
        super().__init__()
        self.reads: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func in HOST_READS:
            frames = [
                f"{f.filename.rsplit('site-packages/', 1)[-1]}:{f.lineno}"
                for f in traceback.extract_stack()[:-1]
                if "wcsac_rl" in f.filename or "torchrl" in f.filename
            ]
            self.reads.append(f"{func.__name__} at {frames[-1] if frames else '?'}")
        return func(*args, **(kwargs or {}))


def _trained_until(trainer, updates: int) -> None:
    batches = iter(trainer.collector)
    while trainer.updates < updates:
        trainer.tracker.add(batch := next(batches))
        trainer.learn(batch)


HELD = ("algo.kappa_signal_every=10", "algo.kappa_statistic=tail", "algo.kappa_states=initial")


@pytest.mark.parametrize(
    "overrides",
    [("algo=wcsac",), ("algo=wcsac", *HELD), ("algo=sac_lag",), ("algo=cal",), ("algo=sac",)],
    ids=["wcsac", "wcsac-held-signal", "sac_lag", "cal", "sac"],
)
def test_an_update_in_the_training_loop_reads_nothing_back(tmp_path, overrides):
    trainer = make_trainer(compose_config("env=tiny", *overrides), tmp_path / "run")
    counter, real_update, calls = HostReads(), trainer.update, []

    def counted(batch):
        calls.append(1)
        with counter:
            return real_update(batch)

    trainer.update = counted
    try:
        _trained_until(trainer, 100)
    finally:
        trainer.close()
    assert len(calls) >= 100 and trainer.updates == len(calls)  # (none skipped)
    assert counter.reads == []


@pytest.mark.parametrize(
    "low, high", [(-1.0, 1.0), (torch.tensor([-2.0, 0.0]), torch.tensor([0.5, 3.0]))]
)
@pytest.mark.parametrize("loc_scale", [1.0, 30.0], ids=["moderate", "saturated"])
def test_the_sync_free_tanh_normal_is_torchrls_bit_for_bit_and_reads_nothing(low, high, loc_scale):
    """Draws, log-probabilities (of its own draws and of given actions), the
    deterministic action and the gradients of all of them: equal to TorchRL's
    ``TanhNormal`` bit for bit; building and using it reads nothing back."""
    torch.manual_seed(0)
    raw_loc, raw_scale = loc_scale * torch.randn(64, 2), torch.rand(64, 2) + 0.05
    given = torch.rand(64, 2) * 0.98 + 0.01  # inside both boxes' upper parts
    given = torch.as_tensor(low) + given * (torch.as_tensor(high) - torch.as_tensor(low))
    results = []
    for cls in (SyncFreeTanhNormal, TanhNormal):
        loc, scale = raw_loc.clone().requires_grad_(), raw_scale.clone().requires_grad_()
        torch.manual_seed(1)
        counter = HostReads()
        with counter:
            dist = cls(loc, scale, low=low, high=high)
            action, log_prob = dist.rsample_and_log_prob()
            scored = dist.log_prob(given)
            mean_action = dist.deterministic_sample
            (action.sum() + log_prob.sum() + scored.sum() + mean_action.sum()).backward()
        results.append((counter.reads, action, log_prob, scored, mean_action, loc.grad, scale.grad))
    (reads, *ours), (torchrl_reads, *theirs) = results
    assert reads == []
    assert torchrl_reads  # (what the class is for: TorchRL's checks read the bounds)
    for name, a, b in zip(("action", "log_prob", "scored", "mode", "dloc", "dscale"), ours, theirs):
        assert torch.isfinite(a).all(), name
        assert torch.equal(a, b), name


def _state(trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in trainer.loss.state_dict().items()}


@pytest.mark.parametrize("algo", ["wcsac", "sac_lag", "sac"])
def test_the_masked_step_equals_an_unmasked_one_bit_for_bit(tmp_path, algo):
    """Two trainers built alike: one steps through ``update`` (masked on the device),
    the other as a plain loop would (backward, ``step()``, Polyak at its scalar weight)."""
    config = compose_config("env=tiny", f"algo={algo}")
    masked = make_trainer(config, tmp_path / "a")
    plain = make_trainer(config, tmp_path / "b")
    try:
        assert all(torch.equal(v, _state(plain)[k]) for k, v in _state(masked).items())
        fill_replay_alike(masked, plain)
        for _ in range(3):
            sample, rng = masked.sample(), torch.get_rng_state()
            assert masked.update(sample.clone()) is not None
            torch.set_rng_state(rng)  # (the actor's draws: the same for both)
            out = plain.loss(sample.clone())
            sum(v for k, v in out.items() if k.startswith("loss_")).backward()
            for optimizer in plain.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            plain.target_updater.step()
        after = _state(plain)
        for key, value in _state(masked).items():
            assert torch.equal(value, after[key]), key
    finally:
        masked.close()
        plain.close()
