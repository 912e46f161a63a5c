"""SIGTERM as an exception that is not lost (vio_graph/interrupts.py)."""

from __future__ import annotations

import signal

import pytest

from vio_graph import interrupts
from vio_graph.viz.progress import progress_bar


def test_a_swallowed_sigterm_stops_the_next_progress_update() -> None:
    old = signal.getsignal(signal.SIGTERM)
    try:
        try:  # the handler's exception, swallowed as a weakref callback's would be
            interrupts.on_sigterm(signal.SIGTERM, None)
        except interrupts.Terminated:
            pass
        with progress_bar(10, "test", enabled=False) as bar:
            with pytest.raises(interrupts.Terminated) as info:
                bar.update_to(1)
            assert info.value.signum == signal.SIGTERM
            bar.update_to(2)  # raised once: the cleanup that follows is not cut short
    finally:
        signal.signal(signal.SIGTERM, old)
        interrupts._pending = None
