"""Stop a run cleanly when the scheduler says so: a checkpoint first, then exit.

A cluster ends a job with a signal: SLURM sends the job's ``--signal`` (submitit asks
for ``USR2`` by default, ``SUBMITIT_PREEMPT_SIGNAL=USR1`` for ``USR1``) some time
before the time limit or on preemption, and ``SIGTERM`` before it kills the job;
``scancel``, ``kill`` and Ray's worker shutdown send ``SIGTERM``. While a run trains,
:class:`StopSignals` catches these signals and only *records* them: the trainer looks
at :attr:`StopSignals.received` between two collected batches, where the networks,
optimizers, buffers and counters are consistent, writes its checkpoint (with the epoch
in progress, as on Ctrl-C) and then calls :meth:`StopSignals.forward`, which hands the
signal to the handler that was installed before (submitit's, which requeues the job
and exits); without one the trainer raises :class:`Preempted`.

The run is then continued by ``python train.py resume=RUN_DIR``, and, when it has
``resume=auto`` (a sweep of an ``experiment=...`` does: each job continues from its own
run directory's checkpoint), by running the same command again: the message of
:class:`Preempted` (and of Ctrl-C) names them (:func:`how_to_continue`).

While a checkpoint (or any of a run's records) is being written, :class:`DeferredSignals`
holds back these signals and ``SIGINT``/``SIGHUP`` too: the write finishes (the file is
renamed into place and no temporary file is left), then the signal is delivered as it
would have been. ``kill -9`` cannot be held back: it leaves the previous file in place
and possibly the temporary one, which the next write replaces.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from types import FrameType
from typing import Any

__all__ = [
    "DEFERRED_SIGNALS",
    "STOP_SIGNALS",
    "DeferredSignals",
    "Preempted",
    "StopSignals",
    "how_to_continue",
]

STOP_SIGNALS: tuple[str, ...] = ("SIGTERM", "SIGUSR1", "SIGUSR2")
"""The signals after which a training run checkpoints and stops (``SIGINT``, Ctrl-C, is
a ``KeyboardInterrupt``, which the trainer handles the same way)."""


DEFERRED_SIGNALS: tuple[str, ...] = (*STOP_SIGNALS, "SIGINT", "SIGHUP")
"""The signals :class:`DeferredSignals` holds back while a file is written."""


def train_command() -> str:
    """How the user started this run: ``wcsac-train``, ``python -m wcsac_rl.train`` or
    (in a checkout, and from Python) ``python train.py``."""
    import sys

    started = Path(sys.argv[0]) if sys.argv and sys.argv[0] else Path()
    if started.name == "wcsac-train":
        return "wcsac-train"
    if started.name == "train.py" and started.parent.name == "wcsac_rl":
        return "python -m wcsac_rl.train"
    return "python train.py"


def how_to_continue(run_dir: Path, *, resume_auto: bool = False) -> str:
    """The command that continues the run in ``run_dir`` (``resume=RUN_DIR``, which always
    does), and with ``resume=auto`` that the same command does too (resume=auto is only
    accepted where the command names its directory)."""
    how = f"continue it with: {train_command()} resume={run_dir}"
    return f"{how} (or run the same command again: it has resume=auto)" if resume_auto else how


class Preempted(Exception):
    """The run stopped on a signal after writing its checkpoint.

    Attributes:
        signum: the signal.
        checkpoint: the checkpoint it wrote.
        frames: the frames trained so far.
    """

    def __init__(
        self, signum: int, checkpoint: Path, frames: int, *, resume_auto: bool = False
    ) -> None:
        self.signum = int(signum)
        self.checkpoint = Path(checkpoint)
        self.frames = int(frames)
        self.signal_name = signal.Signals(self.signum).name
        how = how_to_continue(self.checkpoint.parent.parent, resume_auto=resume_auto)
        super().__init__(
            f"stopped by {self.signal_name} at {self.frames} frames; checkpoint written to "
            f"{self.checkpoint}: {how}"
        )

    @property
    def exit_code(self) -> int:
        """The shell's code for a process ended by this signal (128 + signal number)."""
        return 128 + self.signum


class StopSignals:
    """Record :data:`STOP_SIGNALS` while the ``with`` block runs; restore the previous
    handlers on exit.

    Handlers can only be installed from the main thread: elsewhere (a thread-based
    launcher) this does nothing and the signals keep their previous handlers. A signal
    whose handler is ``SIG_IGN`` stays ignored.
    """

    def __init__(self, names: tuple[str, ...] = STOP_SIGNALS) -> None:
        self.signums = [getattr(signal, n) for n in names if hasattr(signal, n)]
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is not threading.main_thread():
            return self
        for signum in self.signums:
            previous = signal.getsignal(signum)
            if previous is signal.SIG_IGN:
                continue
            signal.signal(signum, self._record)
            self._previous[signum] = previous
        return self

    def __exit__(self, *exc: object) -> None:
        self.restore()

    def _record(self, signum: int, frame: FrameType | None) -> None:
        if self.received is None:  # the first one decides; later ones add nothing
            self.received = signum

    def restore(self) -> None:
        """Put the previous handlers back (idempotent)."""
        for signum, previous in self._previous.items():
            signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
        self._previous.clear()

    def forward(self) -> None:
        """Restore the previous handlers and call the previous handler of the received
        signal if it is a Python function (a scheduler's: submitit requeues the job and
        exits there). Returns if there is none, or if it returned."""
        signum = self.received
        previous = self._previous.get(signum) if signum is not None else None
        self.restore()
        if callable(previous):
            previous(signum, None)


class DeferredSignals:
    """Hold back :data:`DEFERRED_SIGNALS` while the ``with`` block runs (a file being
    written), then deliver the first one that came, to the handler that was there
    before (the default one ends the process, 128 + the signal's number; a
    :class:`StopSignals` records it; ``SIGINT`` raises ``KeyboardInterrupt``).

    The signals are caught by a Python handler, which holds for every thread of the
    process (a blocked signal mask would not: a signal may be delivered to another
    thread). Outside the main thread, where handlers cannot be installed, this does
    nothing. Nested blocks defer to the outermost one.
    """

    def __init__(self, names: tuple[str, ...] = DEFERRED_SIGNALS) -> None:
        self.signums = [getattr(signal, n) for n in names if hasattr(signal, n)]
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> DeferredSignals:
        if threading.current_thread() is not threading.main_thread():
            return self
        for signum in self.signums:
            previous = signal.getsignal(signum)
            if previous is signal.SIG_IGN or isinstance(previous, _Deferring):
                continue  # ignored, or an outer block already defers it
            signal.signal(signum, _Deferring(self))
            self._previous[signum] = previous
        return self

    def _record(self, signum: int) -> None:
        if self.received is None:
            self.received = signum

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
        self._previous.clear()
        if self.received is not None:
            received, self.received = self.received, None
            signal.raise_signal(received)


class _Deferring:
    """The handler :class:`DeferredSignals` installs (a class: nested blocks see it)."""

    def __init__(self, owner: DeferredSignals) -> None:
        self.owner = owner

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.owner._record(signum)
