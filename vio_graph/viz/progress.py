"""Progress bars for the CLI and the pipeline (tqdm on stderr), with a silent stub."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from tqdm import tqdm

from vio_graph.interrupts import raise_if_pending


class _Bar(tqdm):
    def update_to(self, n: int) -> None:
        """Set the absolute count (callbacks that report 'n done so far'); a SIGTERM whose
        exception was swallowed is raised here (vio_graph/interrupts.py)."""
        raise_if_pending()
        self.update(n - self.n)


@contextlib.contextmanager
def progress_bar(
    total: int | None, desc: str, unit: str = "it", enabled: bool = True
) -> Iterator[_Bar]:
    with _Bar(
        total=total,
        desc=desc,
        unit=unit,
        disable=None if enabled else True,
        leave=False,
        mininterval=0.5,
        dynamic_ncols=True,
    ) as bar:
        yield bar
