"""The constraint: what the Lagrange multiplier κ reads, and the rule that moves it.

WCSAC's actor minimises ``β log π − Q^r + κ Γ`` while κ keeps a cost signal (the
critic's Γ, or the recent episodes' cost) under a threshold.

What κ reads (:class:`ConstraintSignal`). Four options, each with the paper's choice
first:

* ``kappa_states`` — where the critic is read: ``"replay"`` (the sampled batch, the
  paper and the authors' code; Γ then estimates a discounted per-step cost, held under
  the per-step threshold ``d·(1−γ_c^T)/((1−γ_c)T)``) or ``"initial"`` (episode start
  states, one per batch row under the ``initial_states`` key, with ``a ~ π``:
  Γ(s₀, a₀) estimates the CVaR of the episode's cost, held under the episodic limit
  ``d`` itself; :class:`~wcsac_rl.objectives.StartStateBuffer` provides them).
* ``kappa_actions`` — at replay states, the actions: ``"replay"`` (the stored ones, the
  authors' code) or ``"policy"`` (``a ~ π``, as the paper writes; Γ at the actor's own
  actions, computed with the actor loss).
* ``kappa_statistic`` — ``"mean"`` (the paper): the mean of the per-state Γ(s, a, α);
  ``"tail"``: the CVaR_α of the critic's cost distribution *mixed over the states*
  (the head's :meth:`~wcsac_rl.objectives.safety_head.SafetyHead.mixture_cvar`), which
  at start states is the CVaR of an episode's cost when the start state is random too;
  the mean of per-state CVaRs is never larger and misses a tail made of a few risky
  start states. Equal at α = 1.
* ``kappa_signal`` — ``"critic"`` (the paper): that statistic. ``"episodes"``: the
  recent finished episodes' empirical CVaR_α (or mean cost), read from the batch at the
  ``episode_cvar`` key (:class:`~wcsac_rl.objectives.EpisodeCostWindow`); ``"max"``:
  the larger of the two, so κ rises as soon as collected episodes exceed the limit
  while the critic still lags. Where no episode has finished (NaN) both fall back to
  the critic. Needs ``kappa_states="initial"`` (the threshold is then the episodic
  ``d`` the costs are measured against).

The actor's cost term is always the critic's Γ at its own actions; the signal only sets
κ (and the MDMM damping).

``kappa_signal_every`` (k): at the start states with the tail statistic, the critic's
reading is one number per batch that nothing else uses, so it may be read every k
training updates and held in between (:class:`HeldStatistic`): the actor draws at the
start states and the critic's evaluation there happen once in k updates. The episodes'
half of the signal is still read at every update. k = 1 (the default) reads it every
update.

How κ moves (the loss never asks which rule it holds):

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
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

from wcsac_rl.objectives.budget import per_step_cost_threshold
from wcsac_rl.objectives.inputs import required_entry
from wcsac_rl.objectives.param_groups import watch_multiplier
from wcsac_rl.options import (
    CONSTRAINT_RULES,
    KAPPA_ACTIONS,
    KAPPA_PARAMETRIZATIONS,
    KAPPA_SIGNALS,
    KAPPA_STATES,
    KAPPA_STATISTICS,
    PIDGains,
    SafetyOptions,
    check_options,
    check_value,
)

__all__ = [
    "CONSTRAINT_RULES",
    "KAPPA_ACTIONS",
    "KAPPA_PARAMETRIZATIONS",
    "KAPPA_SIGNALS",
    "KAPPA_STATES",
    "KAPPA_STATISTICS",
    "ConstraintSignal",
    "GradientLagrangian",
    "HeldStatistic",
    "PIDGains",
    "PIDLagrangian",
    "make_constraint",
]


class ConstraintSignal:
    """The signal κ holds under its threshold, per batch row (see the module doc).

    Args:
        head: the loss's safety head (:mod:`wcsac_rl.objectives.safety_head`): its
            :meth:`cvar` and :meth:`mixture_cvar` give the statistics.
        keys: the loss's ``tensor_keys`` (``initial_states``, ``episode_cvar``).
        states, actions, statistic, signal: ``kappa_states``, ``kappa_actions``,
            ``kappa_statistic``, ``kappa_signal``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from wcsac_rl.modules import make_safety_critic
        >>> from wcsac_rl.objectives import WCSACLoss
        >>> from wcsac_rl.objectives.safety_head import GaussianHead
        >>> keys = WCSACLoss.default_keys()
        >>> head = GaussianHead(make_safety_critic(3, 1), keys, risk_level=1.0,
        ...                     nonnegative_cost=False)
        >>> signal = ConstraintSignal(head, keys, states="initial", signal="max")
        >>> batch = TensorDict({"episode_cvar": torch.tensor([[20.0], [float("nan")]])}, [2])
        >>> signal.signal(batch, torch.tensor([12.0, 12.0]))  # NaN: the critic's
        tensor([20., 12.])
    """

    def __init__(
        self,
        head,
        keys,
        *,
        states: str = "initial",
        actions: str = "policy",
        statistic: str = "tail",
        signal: str = "critic",
    ) -> None:
        check_options(
            {
                "kappa_actions": actions,
                "kappa_states": states,
                "kappa_signal": signal,
                "kappa_statistic": statistic,
            }
        )
        self.head = head
        self.keys = keys
        self.states, self.actions = states, actions
        self.statistic_kind, self.signal_kind = statistic, signal

    @property
    def needs_replay_values(self) -> bool:
        """Whether the signal is read at the batch's own state-actions."""
        return self.states == "replay" and self.actions == "replay"

    def threshold(self, cost_limit: float, cost_gamma: float, max_episode_steps: int) -> float:
        """The threshold for the episodic limit ``d``: ``d`` at start states, the
        per-step ``d·(1−γ_c^T)/((1−γ_c)T)`` at replay states."""
        if self.states == "initial":
            return cost_limit
        return per_step_cost_threshold(cost_limit, cost_gamma, max_episode_steps)

    def initial_states(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The start states the batch carries (one per row), shaped like the batch."""
        key = self.keys.initial_states
        states = required_entry(
            tensordict,
            key,
            "kappa_states='initial' needs episode start states (a sub-tensordict shaped like "
            "the batch with the actor's observation entries)",
            f"The wcsac_rl trainer attaches them; in your own loop sample start states and "
            f"set batch[{key!r}] = them.",
        )
        if states.batch_dims > tensordict.batch_dims:
            # (rebuilt from flat entries, e.g. TorchRL's keyword call, a sub-tensordict
            # takes every leading dimension its entries share: the observation's too)
            states = states.copy()
            states.batch_size = tensordict.batch_size
        return states

    def critic_values(self, tensordict: TensorDictBase, replay_values, at_policy: Callable):
        """The critics' values where the statistic is taken: ``at_policy(states)`` (the
        critics at ``a ~ π(states)``, no gradient) at the start states, ``replay_values``
        at the replay state-actions, or ``None`` for the actor's own actions on the
        batch (they come with the actor loss)."""
        if self.states == "initial":
            return at_policy(self.initial_states(tensordict))
        if self.actions == "replay":
            return replay_values
        return None

    def statistic(self, values, mask: Tensor | None = None) -> Tensor:
        """Per row: Γ (``"mean"``: the κ loss averages it), or for ``"tail"`` the CVaR_α
        of the critic's distribution mixed over the rows, repeated per row (detached).
        ``mask`` (per row, ``False``: a padded or invalid row, TorchRL's loss masks)
        keeps those rows out of the mixture; the κ loss's reduction drops them from the
        mean."""
        if self.statistic_kind == "mean":
            return self.head.cvar(values)
        return self.head.mixture_cvar(values, mask).detach().expand(self.head.row_shape(values))

    def episode_cvar(self, tensordict: TensorDictBase) -> Tensor:
        """The recent episodes' empirical CVaR_α from the batch (NaN: none finished)."""
        key = self.keys.episode_cvar
        return required_entry(
            tensordict,
            key,
            f"kappa_signal={self.signal_kind!r} needs the empirical CVaR_α of recent "
            "episode costs ([*B, 1], NaN while no episode has ended)",
            f"The wcsac_rl trainer attaches it; in your own loop keep an "
            f"EpisodeCostWindow.for_loss(loss) and set batch[{key!r}] with its attach().",
        )

    def signal(self, tensordict: TensorDictBase, statistic: Tensor | None) -> Tensor | None:
        """What κ holds under the threshold: the critic's ``statistic``, or the
        episodes' empirical CVaR, or the larger of them; the critic's where the episodes
        give NaN (none finished yet)."""
        if self.signal_kind == "critic" or statistic is None:
            return statistic
        episodes = self.episode_cvar(tensordict).to(statistic.dtype).reshape(statistic.shape)
        if self.signal_kind == "max":
            return torch.fmax(statistic, episodes)  # fmax: NaN loses
        return torch.where(episodes.isnan(), statistic, episodes)


class HeldStatistic(nn.Module):
    """The critic's statistic read every ``every`` training updates and held in between.

    Two buffers, so that a checkpoint carries them and a resumed run reads the critic
    when the uninterrupted one would: ``value`` (the last reading, 0-dim) and ``age``
    (updates since it was read, counting the one that read it; 0: none yet).

    Example:
        >>> hold = HeldStatistic(3)
        >>> hold.take() is None          # nothing held yet: read the critic
        True
        >>> hold.store(torch.tensor(4.0))
        >>> hold.take(), hold.take()     # the next two updates hold it
        (tensor(4.), tensor(4.))
        >>> hold.take() is None          # the third reads it again
        True
    """

    def __init__(self, every: int) -> None:
        super().__init__()
        check_value("kappa_signal_every", every, "kappa_signal_every")
        self.every = int(every)
        self.register_buffer("value", torch.full((), float("nan")))
        self.register_buffer("age", torch.zeros((), dtype=torch.long))
        self._age: int | None = 0  # the buffer's value in Python (None: not read yet)

    def take(self) -> Tensor | None:
        """The held value for this update (and count it), or ``None`` when the critic is
        to be read: nothing held yet, or held for ``every`` updates already. The age is
        kept in Python beside its buffer: read from the buffer once (after a load), not
        at every update."""
        if self._age is None:
            self._age = int(self.age)  # (a host read: once, not per update)
        if self._age == 0 or self._age >= self.every:
            return None
        self._age += 1
        self.age += 1
        return self.value.clone()

    def store(self, value: Tensor) -> None:
        """Hold ``value`` (0-dim, detached) from this update on."""
        self.value.copy_(value.detach().reshape(()))
        self.age.fill_(1)
        self._age = 1

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        super()._load_from_state_dict(*args, **kwargs)
        self._age = None  # (the loaded buffer is read again at the next update)

    def extra_repr(self) -> str:
        return f"every={self.every}"


# ------------------------------------------------------------ how κ moves
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
        check_options(  # (as the config's options: a constraint built directly too)
            {
                "kappa_rule": self.rule,
                "kappa_init": kappa_init,
                "kappa_parametrization": parametrization,
                "damp_scale": damp_scale,
                "kappa_max": kappa_max,
                "kappa_min": kappa_min,
            }
        )
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
        check_options(
            {
                "kappa_rule": self.rule,
                "kappa_init": kappa_init,
                "kappa_min": kappa_min,
                "pid": gains,
            }
        )
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
    check_options({"kappa_rule": rule, "kappa_init": kappa_init, "kappa_max": kappa_max})
    if rule == "gradient":
        if pid is not None:
            raise ValueError("pid gains apply to kappa_rule='pid' only (kappa_rule='gradient')")
        return GradientLagrangian(
            kappa_init, parametrization, damp_scale, kappa_max, kappa_min, damp_clamp
        )
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
