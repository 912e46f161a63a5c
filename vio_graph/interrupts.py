"""SIGTERM as an exception, raised like Ctrl-C, that a swallowing context cannot lose.

Python runs a signal handler between bytecodes of the main thread, wherever it is; if that
is inside a callback whose exceptions the interpreter ignores (a weakref callback of the
import system's module locks, for one), the handler's exception is printed and dropped and
the run would go on to the end. So the handler also notes the signal, and the progress
callbacks the long loops call (vio_graph/viz/progress.py) raise it again if it was noted and
never delivered.
"""

from __future__ import annotations

import signal

_pending: int | None = None  # a SIGTERM raised but perhaps not delivered


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every ``finally`` (temporary files, the recording
    writer's folder, the rerun stream) runs before the process exits."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def on_sigterm(signum: int, _frame: object) -> None:
    """The SIGTERM handler: ignore further SIGTERMs (the cleanup must not be cut short), note
    the signal and raise :class:`Terminated`."""
    global _pending
    signal.signal(signum, signal.SIG_IGN)
    _pending = signum
    raise Terminated(signum)


def raise_if_pending() -> None:
    """Raise :class:`Terminated` once if a SIGTERM was noted (and forget it): called where a
    long loop reports progress, so a signal whose exception was swallowed still stops it."""
    global _pending
    if _pending is not None:
        signum, _pending = _pending, None
        raise Terminated(signum)
