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

The run is then continued by running the same command again (a sweep of an
``experiment=...`` runs with ``resume=auto``: each job continues from its own run
directory's checkpoint), or by ``resume=RUN_DIR``.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from types import FrameType
from typing import Any

__all__ = ["STOP_SIGNALS", "Preempted", "StopSignals"]

STOP_SIGNALS: tuple[str, ...] = ("SIGTERM", "SIGUSR1", "SIGUSR2")
"""The signals after which a training run checkpoints and stops (``SIGINT``, Ctrl-C, is
a ``KeyboardInterrupt``, which the trainer handles the same way)."""


class Preempted(Exception):
    """The run stopped on a signal after writing its checkpoint.

    Attributes:
        signum: the signal.
        checkpoint: the checkpoint it wrote.
        frames: the frames trained so far.
    """

    def __init__(self, signum: int, checkpoint: Path, frames: int) -> None:
        self.signum = int(signum)
        self.checkpoint = Path(checkpoint)
        self.frames = int(frames)
        self.signal_name = signal.Signals(self.signum).name
        super().__init__(
            f"stopped by {self.signal_name} at {self.frames} frames; checkpoint written to "
            f"{self.checkpoint}: run the same command again to continue (resume=auto), or "
            f"resume={self.checkpoint.parent.parent}"
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
