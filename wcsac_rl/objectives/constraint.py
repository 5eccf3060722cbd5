"""The constraint: the Lagrange multiplier κ and the rule that updates it.

WCSAC's actor minimises ``β log π − Q^r + κ Γ`` while κ keeps a cost signal (the
critic's Γ, or the recent episodes' cost: ``kappa_signal``) under a threshold. How κ
moves is this module's business, and the loss never asks which rule it holds:

* :class:`GradientLagrangian` — the paper's rule: κ is a parameter (``softplus`` or
  ``exp`` of ``kappa_raw``) trained by gradient descent on ``κ · (threshold − signal)``
  (the loss's ``loss_kappa``), optionally with MDMM damping of the actor's penalty.
  This is integral control: κ moves in proportion to the accumulated violation, so it
  overshoots and oscillates, and while the signal sits under the threshold κ decays.
* :class:`PIDLagrangian` — Stooke, Achiam & Abbeel (ICML 2020), "Responsive Safety
  in RL by PID Lagrangian Methods": κ is set, not learned, from the error
  ``e = signal − threshold`` as ``κ = [Kp·EMA(e) + I + Kd·max(0, Ĉ_t − Ĉ_{t−delay})]``
  clipped to ``[0, max_kappa]``, with the integral ``I ← clip(I + Ki·e, 0, max_kappa)``
  (anti-windup) and ``Ĉ`` an exponential moving average of the signal. The
  proportional term answers a violation at once; the derivative term answers a rising
  cost before it crosses the threshold. It has no loss term: :meth:`step` is called
  once per update with the signal (``WCSACLoss.forward`` does it in training mode, as
  batch norm updates its running statistics).

Both are ``nn.Module`` with the same small interface: :attr:`kappa` (the multiplier,
detached), :meth:`penalty_weight` (κ's weight on Γ in the actor loss), :meth:`loss`
(the multiplier's loss term, or ``None``), :meth:`step` (the controller's update,
or nothing) and :meth:`diagnostics` (the rule's own state worth logging, by name).
Their state (``kappa_raw``; the PID's integral, averages and history) is in the state
dict, so a resumed run continues where it stopped.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from wcsac_rl.objectives.param_groups import watch_multiplier
from wcsac_rl.options import (
    CONSTRAINT_RULES,
    KAPPA_PARAMETRIZATIONS,
    PIDGains,
    SafetyOptions,
    check_kappa_bound,
    check_value,
    option_spec,
)

__all__ = [
    "CONSTRAINT_RULES",
    "KAPPA_PARAMETRIZATIONS",
    "GradientLagrangian",
    "PIDGains",
    "PIDLagrangian",
    "make_constraint",
]


def _check_options(**values: float) -> None:
    """Each value as the recipe's option of that name allows it (one ``ValueError`` line
    naming it): a constraint built directly gets the config's checks."""
    for key, value in values.items():
        check_value(key, value, option_spec(SafetyOptions, key))


def _inverse_softplus(x: float) -> float:
    return x + math.log(-math.expm1(-x))


class GradientLagrangian(nn.Module):
    """κ as a parameter learned by gradient descent (the paper's rule).

    Args:
        kappa_init (float): the initial κ > 0. Default: the authors' ``softplus(0) ≈ 0.693``.
        parametrization (str): ``"softplus"`` (κ = softplus(raw), the authors' code) or
            ``"log"`` (κ = exp(raw)).
        damp_scale (float): MDMM damping: the actor's penalty weight is
            ``κ − damp_scale · mean(threshold − signal)`` (the authors' ``damp``).
            ``0``: none.
        damp_clamp (bool): the damping term at most κ, so the weight is
            ``κ − min(damp_scale · mean(threshold − signal), κ) ≥ 0``: CAL's
            rectification (Wu et al. 2024, ``clamp(c·mean(d̂ − Q̂), max=λ)``). ``False``:
            unclamped, the authors' (a large slack then makes the weight negative).
        kappa_max (float, optional): an upper bound of κ (``None``: none, the paper).
            κ never exceeds it, and ``kappa_raw`` is projected back under it at every
            :meth:`step` (OmniSafe's ``lagrangian_upper_bound``), so a long violation
            cannot wind it up: κ starts to fall as soon as the signal is under the
            threshold. While ``kappa_raw`` is above the bound (at most one optimizer
            step), κ reads the bound and the gradient passes through unchanged.
        kappa_min (float): a floor under κ (``0``: none, the paper), held the same way:
            however long the signal stays under the threshold, κ decays no lower, so a
            violation after a long safe stretch meets a multiplier at least this large
            and ``kappa_raw`` climbs from the floor's raw value at once, not from
            wherever an unbounded decay left it.

    Example:
        >>> import torch
        >>> constraint = GradientLagrangian(0.5, "log")
        >>> signal = torch.tensor([20.0, 20.0])  # over a threshold of 15
        >>> constraint.loss(signal, torch.tensor(15.0)).mean().backward()
        >>> bool(constraint.kappa_raw.grad < 0)  # descending the loss raises κ
        True
    """

    rule = "gradient"

    def __init__(
        self,
        kappa_init: float = SafetyOptions.kappa_init,
        parametrization: str = SafetyOptions.kappa_parametrization,
        damp_scale: float = 0.0,
        kappa_max: float | None = None,
        kappa_min: float = 0.0,
        damp_clamp: bool = False,
    ) -> None:
        super().__init__()
        _check_options(kappa_init=kappa_init, damp_scale=damp_scale, kappa_min=kappa_min)
        if parametrization not in KAPPA_PARAMETRIZATIONS:
            raise ValueError(
                f"kappa_parametrization must be one of {KAPPA_PARAMETRIZATIONS}, "
                f"got {parametrization!r}"
            )
        if not damp_scale >= 0:
            raise ValueError(f"damp_scale must be >= 0, got {damp_scale}")
        check_kappa_bound(kappa_init, kappa_max, self.rule, kappa_min=kappa_min)
        self.parametrization = parametrization
        self.damp_scale, self.damp_clamp = float(damp_scale), bool(damp_clamp)
        self.kappa_max = None if kappa_max is None else float(kappa_max)
        self.kappa_min = float(kappa_min)
        self.kappa_raw = nn.Parameter(torch.tensor(self._raw(kappa_init)))
        # the range of kappa_raw (±inf: no bound); buffers so that they move with the module
        self.register_buffer(
            "raw_max",
            torch.tensor(math.inf if kappa_max is None else self._raw(kappa_max)),
            persistent=False,
        )
        self.register_buffer(
            "raw_min",
            torch.tensor(-math.inf if kappa_min == 0.0 else self._raw(kappa_min)),
            persistent=False,
        )
        watch_multiplier(self.kappa_raw)  # an optimizer training it at one rate with others warns

    def __setstate__(self, state) -> None:  # (deepcopy, pickle: the copy is watched too)
        super().__setstate__(state)
        watch_multiplier(self.kappa_raw)

    def _raw(self, kappa: float) -> float:
        return _inverse_softplus(kappa) if self.parametrization == "softplus" else math.log(kappa)

    @property
    def bounded(self) -> bool:
        """Whether ``kappa_max`` or ``kappa_min`` bounds κ (unbounded: the paper's rule,
        with no clamp on its path)."""
        return self.kappa_max is not None or self.kappa_min > 0.0

    def multiplier(self) -> Tensor:
        """κ as a differentiable function of ``kappa_raw`` (within ``[kappa_min,
        kappa_max]``)."""
        raw = self.kappa_raw
        if self.bounded:  # the bound's value, the identity's gradient
            raw = raw - (raw - raw.clamp(min=self.raw_min, max=self.raw_max)).detach()
        if self.parametrization == "softplus":
            return nn.functional.softplus(raw)
        return raw.exp()

    @property
    def kappa(self) -> Tensor:
        """The current κ (detached)."""
        with torch.no_grad():
            return self.multiplier()

    def penalty_weight(self, signal: Tensor, threshold: Tensor) -> Tensor:
        """κ's weight on Γ in the actor loss (detached): κ, minus the damping term
        (with ``damp_clamp``, at most κ)."""
        kappa = self.kappa
        if self.damp_scale == 0.0:
            return kappa
        damp = self.damp_scale * (threshold - signal).mean()
        return kappa - (torch.minimum(damp, kappa) if self.damp_clamp else damp)

    def loss(self, signal: Tensor, threshold: Tensor) -> Tensor:
        """``κ · (threshold − signal)`` per row (signal detached): descending it raises κ
        while the signal exceeds the threshold and lowers it otherwise."""
        return self.multiplier() * (threshold - signal.detach())

    @torch.no_grad()
    def step(self, signal: Tensor, threshold: Tensor) -> None:
        """κ moves with its optimizer; ``kappa_raw`` is projected back into the bounds
        (``kappa_max``: anti-windup; ``kappa_min``: the floor)."""
        if self.bounded:
            self.kappa_raw.clamp_(min=self.raw_min, max=self.raw_max)

    diagnostic_names: tuple[str, ...] = ()
    """The names :meth:`diagnostics` returns: none (κ is all there is)."""

    def diagnostics(self) -> dict[str, Tensor]:
        """Nothing beyond κ."""
        return {}

    def extra_repr(self) -> str:
        bound = "" if self.kappa_max is None else f", kappa_max={self.kappa_max}"
        floor = "" if not self.kappa_min else f", kappa_min={self.kappa_min}"
        return (
            f"parametrization={self.parametrization!r}, damp_scale={self.damp_scale}"
            f"{', damp_clamp=True' if self.damp_clamp else ''}{bound}{floor}"
        )


class PIDLagrangian(nn.Module):
    """κ set by a PID controller on the constraint's error (Stooke et al. 2020).

    Each :meth:`step` with the signal ``x`` and threshold ``d`` (error ``e = x − d``)::

        P ← p_ema · P + (1 − p_ema) · e
        I ← clip(I + ki · min(e, i_error_max), 0, max_kappa)  (anti-windup)
        C ← d_ema · C + (1 − d_ema) · x                       (C starts at the first x)
        D ← max(0, C − C_{t − d_delay})                       (0 until d_delay steps exist)
        κ ← clip(kp · P + I + kd · D, kappa_min, max_kappa)

    The integral starts at ``kappa_init``, so κ starts where the gradient rule's does.
    ``kappa_min`` (default 0) is a floor under the output only: the integral still
    unwinds to 0 while the signal is under the threshold.
    A NaN signal (no episode has finished yet, with ``kappa_signal="episodes"``) leaves
    everything unchanged. All of it runs on tensors (no host synchronisation).

    Example:
        >>> import torch
        >>> pid = PIDLagrangian(0.5, PIDGains(kp=0.1, ki=0.01, p_ema=0.0))
        >>> pid.step(torch.tensor(25.0), torch.tensor(15.0))  # 10 over the limit
        >>> round(float(pid.kappa), 4)  # 0.1 * 10 + (0.5 + 0.01 * 10)
        1.6
    """

    rule = "pid"

    def __init__(
        self,
        kappa_init: float = SafetyOptions.kappa_init,
        gains: PIDGains | None = None,
        kappa_min: float = 0.0,
    ) -> None:
        super().__init__()
        gains = PIDGains() if gains is None else gains
        if not isinstance(gains, PIDGains):
            raise TypeError(
                f"gains must be a PIDGains (e.g. PIDGains(kp=1.0)), got {type(gains).__name__}"
            )
        _check_options(kappa_init=kappa_init, kappa_min=kappa_min)
        if not kappa_init >= 0:
            raise ValueError(f"kappa_init must be >= 0 with the PID rule, got {kappa_init}")
        if kappa_init > gains.max_kappa:
            raise ValueError(f"kappa_init={kappa_init} is above pid.max_kappa={gains.max_kappa}")
        check_kappa_bound(kappa_init, None, self.rule, kappa_min=kappa_min)
        self.gains = gains
        self.kappa_min = float(kappa_min)
        self.register_buffer("kappa_value", torch.tensor(float(kappa_init)))
        self.register_buffer("integral", torch.tensor(float(kappa_init)))
        self.register_buffer("error_ema", torch.zeros(()))
        self.register_buffer("signal_ema", torch.zeros(()))
        # the signal's EMA over the last d_delay steps, oldest first (a shift register:
        # static shapes, so the step compiles without data-dependent indexing)
        self.register_buffer("history", torch.zeros(int(gains.d_delay)))
        self.register_buffer("steps", torch.zeros((), dtype=torch.long))

    @property
    def kappa(self) -> Tensor:
        """The current κ."""
        return self.kappa_value.clone()

    def penalty_weight(self, signal: Tensor, threshold: Tensor) -> Tensor:
        """κ's weight on Γ in the actor loss: κ itself (the P term does MDMM's job)."""
        return self.kappa

    def loss(self, signal: Tensor, threshold: Tensor) -> None:
        """None: the controller is not trained."""
        return None

    @torch.no_grad()
    def step(self, signal: Tensor, threshold: Tensor) -> None:
        """One controller update from the batch-mean ``signal`` (see the class doc)."""
        g = self.gains
        x = torch.as_tensor(signal, dtype=torch.float32, device=self.kappa_value.device).mean()
        valid = x.isfinite()
        x = torch.where(valid, x, torch.zeros_like(x))
        error = x - torch.as_tensor(threshold, dtype=x.dtype, device=x.device)
        first = self.steps == 0
        error_ema = g.p_ema * self.error_ema + (1.0 - g.p_ema) * error
        added = error if g.i_error_max is None else error.clamp(max=g.i_error_max)
        integral = (self.integral + g.ki * added).clamp(0.0, g.max_kappa)
        signal_ema = torch.where(first, x, g.d_ema * self.signal_ema + (1.0 - g.d_ema) * x)
        past = self.history[0]  # the EMA d_delay steps back (once that many exist)
        rise = torch.where(self.steps >= g.d_delay, (signal_ema - past).clamp(min=0.0), 0.0)
        kappa = (g.kp * error_ema + integral + g.kd * rise).clamp(self.kappa_min, g.max_kappa)
        # a NaN signal changes nothing
        self.error_ema.copy_(torch.where(valid, error_ema, self.error_ema))
        self.integral.copy_(torch.where(valid, integral, self.integral))
        self.signal_ema.copy_(torch.where(valid, signal_ema, self.signal_ema))
        history = torch.cat([self.history[1:], signal_ema.reshape(1)])
        self.history.copy_(torch.where(valid, history, self.history))
        self.kappa_value.copy_(torch.where(valid, kappa, self.kappa_value))
        self.steps.add_(valid.long())

    diagnostic_names: tuple[str, ...] = ("kappa_integral", "kappa_error")
    """The names :meth:`diagnostics` returns."""

    def diagnostics(self) -> dict[str, Tensor]:
        """The controller's state (copies): ``kappa_integral``, the integral term I, and
        ``kappa_error``, the EMA of the error that the proportional term multiplies. κ
        is ``Kp·kappa_error + kappa_integral`` (+ the derivative term), clipped."""
        return {"kappa_integral": self.integral.clone(), "kappa_error": self.error_ema.clone()}

    def extra_repr(self) -> str:
        floor = [f"kappa_min={self.kappa_min}"] if self.kappa_min else []
        return ", ".join([f"{k}={v}" for k, v in vars(self.gains).items()] + floor)


def make_constraint(
    rule: str,
    *,
    kappa_init: float,
    parametrization: str = "softplus",
    damp_scale: float = 0.0,
    kappa_max: float | None = None,
    kappa_min: float = 0.0,
    pid: PIDGains | dict | None = None,
    damp_clamp: bool = False,
) -> GradientLagrangian | PIDLagrangian:
    """The constraint for ``rule`` (``"gradient"`` or ``"pid"``) with its options.

    ``damp_scale``, ``parametrization`` and ``kappa_max`` are the gradient rule's,
    ``pid`` the PID rule's gains (its bound is ``pid.max_kappa``); an option of the
    other rule is refused by name. ``kappa_min`` floors κ under either rule.
    """
    if rule not in CONSTRAINT_RULES:
        raise ValueError(f"kappa_rule must be one of {CONSTRAINT_RULES}, got {rule!r}")
    if rule == "gradient":
        if pid is not None:
            raise ValueError("pid gains apply to kappa_rule='pid' only (kappa_rule='gradient')")
        return GradientLagrangian(
            kappa_init, parametrization, damp_scale, kappa_max, kappa_min, damp_clamp
        )
    check_kappa_bound(kappa_init, kappa_max, rule)  # (the floor: PIDLagrangian checks it)
    if damp_scale:
        raise ValueError(
            f"damp_scale={damp_scale} is the gradient rule's MDMM damping; with "
            "kappa_rule='pid' the proportional gain pid.kp plays its part (set damp_scale=0)"
        )
    gains = pid if isinstance(pid, PIDGains) else PIDGains(**(pid or {}))
    return PIDLagrangian(kappa_init, gains, kappa_min)


def rename_kappa_raw(module, state_dict, prefix, *args) -> None:
    """Load a state dict saved before κ moved into :attr:`WCSACLoss.constraint`."""
    old, new = f"{prefix}kappa_raw", f"{prefix}constraint.kappa_raw"
    if old in state_dict and new not in state_dict:
        state_dict[new] = state_dict.pop(old)
