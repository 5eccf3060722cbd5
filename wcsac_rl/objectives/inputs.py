"""Checks of what a loss is given: its constructor's numbers and its batch.

One NaN or infinite cost, reward or observation in a batch makes every loss term NaN,
and one optimizer step on them makes every parameter NaN for good. Checking a batch's
values needs the host to read them (a synchronisation), which a compiled update
(``torch.compile(fullgraph=True)``) must not do on every step: so the loss checks only
what its shapes say (an empty batch) on its own, and :func:`check_finite_entries` is
what :meth:`WCSACLoss.check_inputs <wcsac_rl.objectives.WCSACLoss.check_inputs>` (and
``WCSACLoss(..., check_finite=True)``) runs. The trainers check every collected batch
once instead, before it reaches the replay buffer.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from numbers import Real

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

__all__ = [
    "check_finite_entries",
    "check_nonempty_batch",
    "finite_number",
    "nonfinite_entry",
    "required_entry",
]


def finite_number(value: object, name: str, *, minimum: float | None = None) -> float:
    """``value`` as a float, or a ``ValueError`` naming ``name`` when it is not a finite
    number (NaN, ±inf, a bool, a string) at least ``minimum``."""
    ok = isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (minimum is None or value >= minimum)
    if not ok:
        what = "a finite number" if minimum is None else f">= {minimum:g} (a finite number)"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return float(value)


def required_entry(tensordict: TensorDictBase, key: NestedKey, what: str, how: str):
    """``tensordict[key]``, or a ``KeyError`` saying what it is and how to provide it."""
    value = tensordict.get(key, None)
    if value is None:
        raise KeyError(f"{what} at {key!r} of the batch; the batch has none. {how}")
    return value


def check_nonempty_batch(tensordict: TensorDictBase, what: str) -> None:
    """A ``ValueError`` naming the batch size when ``tensordict`` holds no sample (its
    shape is known without reading any value: no host synchronisation)."""
    if tensordict.batch_size.numel() == 0 and tensordict.batch_dims:
        raise ValueError(
            f"{what} got an empty batch (batch_size={list(tensordict.batch_size)}); it needs "
            "at least one transition (e.g. sample the replay buffer once it holds some)"
        )


def nonfinite_entry(
    tensordict: TensorDictBase, keys: Iterable[NestedKey]
) -> tuple[NestedKey, int, int, float] | None:
    """The first of ``keys`` whose floating-point entry in ``tensordict`` holds a NaN or
    ±inf: ``(key, how many, of how many, the first such value)``; ``None`` if all are
    finite (absent and non-float entries are skipped). Reads the values: a host
    synchronisation per entry."""
    for key in keys:
        value = tensordict.get(key, None)
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            continue
        bad = ~torch.isfinite(value)
        if bool(bad.any()):
            first = float(value[bad].reshape(-1)[0])
            return key, int(bad.sum()), value.numel(), first
    return None


def check_finite_entries(tensordict: TensorDictBase, keys: Iterable[NestedKey], what: str) -> None:
    """A ``ValueError`` naming the first entry of ``keys`` that is not finite, how many of
    its values are not, and one of them (see :func:`nonfinite_entry`)."""
    found = nonfinite_entry(tensordict, keys)
    if found is not None:
        key, count, total, first = found
        raise ValueError(
            f"{what}: batch entry {key!r} holds {count} non-finite value(s) of {total} "
            f"(e.g. {first}); a NaN or infinite cost, reward or observation makes every "
            "loss term NaN and, after one optimizer step, every parameter. Drop or fix "
            "those transitions before they reach the replay buffer"
        )
