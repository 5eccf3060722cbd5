"""Stop a run cleanly when the scheduler says so: a checkpoint first, then exit.

:class:`StopSignals` records a scheduler's stop signal (``SIGTERM``, ``USR1``/``USR2``)
while a run trains; the trainer checks :attr:`StopSignals.received` between two
collected batches, writes its checkpoint and calls :meth:`StopSignals.forward` (the
handler installed before, such as submitit's requeue) or raises :class:`Preempted`,
whose message says how to continue (:func:`how_to_continue`). :class:`DeferredSignals`
holds these signals and ``SIGINT``/``SIGHUP`` back while a record is written. Which
scheduler sends what: docs/reproduce.md; what survives which signal:
docs/guarantees.md ("What is atomic, and what survives SIGTERM and kill -9").
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


class _CaughtSignals:
    """Catch ``names`` with a Python handler while the ``with`` block runs, recording the
    first that came (:attr:`received`); the previous handlers come back on exit.

    Handlers can only be installed from the main thread: elsewhere (a thread-based
    launcher) this does nothing and the signals keep their previous handlers. A signal
    whose handler is ``SIG_IGN`` stays ignored.
    """

    def __init__(self, names: tuple[str, ...]) -> None:
        self.signums = [getattr(signal, n) for n in names if hasattr(signal, n)]
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self):
        if threading.current_thread() is not threading.main_thread():
            return self
        for signum in self.signums:
            previous = signal.getsignal(signum)
            if previous is signal.SIG_IGN or isinstance(previous, _Deferring):
                continue  # ignored, or a DeferredSignals block already holds it back
            signal.signal(signum, self._handler())
            self._previous[signum] = previous
        return self

    def __exit__(self, *exc: object) -> None:
        self.restore()

    def _handler(self) -> Any:
        return self._record

    def _record(self, signum: int, frame: FrameType | None = None) -> None:
        if self.received is None:  # the first one decides; later ones add nothing
            self.received = signum

    def restore(self) -> None:
        """Put the previous handlers back (idempotent)."""
        for signum, previous in self._previous.items():
            signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
        self._previous.clear()


class StopSignals(_CaughtSignals):
    """Record :data:`STOP_SIGNALS` while the ``with`` block runs (:class:`_CaughtSignals`)."""

    def __init__(self, names: tuple[str, ...] = STOP_SIGNALS) -> None:
        super().__init__(names)

    def forward(self) -> None:
        """Restore the previous handlers and call the previous handler of the received
        signal if it is a Python function (a scheduler's: submitit requeues the job and
        exits there). Returns if there is none, or if it returned."""
        signum = self.received
        previous = self._previous.get(signum) if signum is not None else None
        self.restore()
        if callable(previous):
            previous(signum, None)


class DeferredSignals(_CaughtSignals):
    """Hold back :data:`DEFERRED_SIGNALS` while the ``with`` block runs (a file being
    written), then deliver the first one that came, to the handler that was there
    before (the default one ends the process, 128 + the signal's number; a
    :class:`StopSignals` records it; ``SIGINT`` raises ``KeyboardInterrupt``).

    A Python handler holds for every thread of the process (a blocked signal mask would
    not: a signal may be delivered to another thread). Nested blocks defer to the
    outermost one.
    """

    def __init__(self, names: tuple[str, ...] = DEFERRED_SIGNALS) -> None:
        super().__init__(names)

    def _handler(self) -> Any:
        return _Deferring(self)  # (a class: nested blocks see it)

    def __exit__(self, *exc: object) -> None:
        self.restore()
        if self.received is not None:
            received, self.received = self.received, None
            signal.raise_signal(received)


class _Deferring:
    """The handler :class:`DeferredSignals` installs (a class: nested blocks see it)."""

    def __init__(self, owner: DeferredSignals) -> None:
        self.owner = owner

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.owner._record(signum)
