"""Tolerances for floating-point equalities, derived from float32 rounding (not collected).

Two float32 computations of the same quantity that round differently differ by
their accumulated rounding errors. On another CPU they do: torch dispatches its
elementwise and reduction kernels on the SIMD width (``ATEN_CPU_CAPABILITY``:
scalar, AVX2, AVX-512 sum in different orders and use FMA or not), and BLAS blocks
its matrix products by the CPU's cache and vector sizes. Each rounding moves a
value by at most half a float32 ulp, ``2⁻²⁴·|x|``, so a result that went through
``ops`` roundings of values of size ``magnitude`` (a sum of ``ops`` terms, a chain
of ``ops`` operations) is off by at most ``ops · 2⁻²⁴ · magnitude``, and two such
computations differ by at most twice that:

    tolerance = ops × 2⁻²³ × magnitude

``magnitude`` is the size of the values being rounded, not of the result: where
terms cancel (a gradient that sums over a batch, a difference of two losses) the
result can be far smaller than its terms, so the tensor's largest entry, or the
terms' own size, is the scale. An error of the kind a bug makes (a missing term, a
wrong sign, a swapped key) is a fraction of ``magnitude`` itself, 10⁴–10⁶ times
these tolerances, so the assertions stay meaningful.

Checked on this machine with ``ATEN_CPU_CAPABILITY=default|avx2|avx512`` and
``MKL_ENABLE_INSTRUCTIONS=SSE4_2|AVX2`` (the scalar kernels reproduce a failure once
seen on an AVX-512 Xeon): the largest observed error is ≤ 1/4 of every tolerance
derived here.
"""

from __future__ import annotations

import torch

__all__ = ["EPS32", "assert_close_f32", "f32_tolerance"]

EPS32 = 2.0**-23
"""float32 machine epsilon (``torch.finfo(torch.float32).eps``): twice the largest
relative rounding error of one operation."""


def f32_tolerance(ops: int, magnitude: float | torch.Tensor) -> float:
    """``ops × 2⁻²³ × magnitude``: how far two float32 computations of a value may differ
    when each rounds ``ops`` times values of size ``magnitude``."""
    return float(ops) * EPS32 * float(magnitude)


def assert_close_f32(
    actual: torch.Tensor,
    expected: torch.Tensor,
    *,
    ops: int,
    magnitude: float | torch.Tensor | None = None,
    msg: str | None = None,
) -> None:
    """``|actual − expected| ≤ ops × 2⁻²³ × magnitude`` elementwise.

    ``magnitude`` defaults to the largest ``|expected|`` entry (the scale of the
    values the computation rounded); pass the terms' size where they cancel.
    """
    expected = torch.as_tensor(expected)
    if magnitude is None:
        magnitude = expected.detach().abs().max() if expected.numel() else 0.0
    atol = f32_tolerance(ops, magnitude)
    torch.testing.assert_close(
        torch.as_tensor(actual),
        expected,
        rtol=0,
        atol=atol,
        msg=None if msg is None else lambda default: f"{msg}: {default}",
    )
