"""Run many independent tasks on Dask (a local cluster or a remote scheduler) or serially.

A *task* is a picklable, module-level function applied to one picklable item (a tuple or dict
of paths and JSON strings: workers read recordings and write results on a file system they
share with the client). Failures stay with their task: :func:`run_tasks` returns one
:class:`Outcome` per item, in the items' order, holding either the value or the error line.
A worker that dies while running a task does not lose it: the Dask scheduler hands the task
to another worker (up to ``distributed.scheduler.allowed-failures`` deaths, 3 by default,
after which the task's outcome is a ``KilledWorker`` error).

``scheduler``:

- ``None`` or ``"local"``: a ``distributed.LocalCluster`` on this machine, ``workers``
  single-threaded worker processes (default: the number of CPUs);
- ``"serial"``: every task in this process, one after the other (no Dask; the reference run);
- ``"tcp://HOST:PORT"`` (any Dask address): an existing scheduler, started with
  ``dask scheduler`` and ``dask worker tcp://HOST:PORT``; ``workers`` is ignored.
"""

from __future__ import annotations

import contextlib
import logging
import os
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from vio_graph.errors import VioGraphError

log = logging.getLogger(__name__)

SERIAL = "serial"
LOCAL = "local"


@dataclass(frozen=True)
class Outcome:
    """What one task gave: ``value`` if it finished, else ``error`` (``Type: message``)."""

    value: Any = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def _error_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int | None = None) -> Iterator[Any]:
    """A ``distributed.Client`` on a new LocalCluster (``None``/``"local"``) or on the
    scheduler at ``scheduler``; closed (and the local cluster shut down) on exit."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - dask[distributed] is a dependency
        raise VioGraphError(
            "the Dask engine needs dask[distributed]: pip install 'dask[distributed]'"
        ) from exc
    for name in ("distributed", "tornado"):  # their INFO chatter is not the user's business
        logging.getLogger(name).setLevel(logging.WARNING)
    if scheduler in (None, LOCAL):
        n = workers or os.cpu_count() or 1
        if n < 1:
            raise VioGraphError(f"--workers: need at least 1 worker, got {n}")
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,  # the pipeline is single-threaded numpy/GTSAM work
            processes=True,
            dashboard_address=None,
            memory_limit=0,  # a long trial must not be paused or killed by a memory guess
            silence_logs=logging.CRITICAL,  # task errors are reported in the outcomes
        )
        try:
            with Client(cluster) as client:
                yield client
        finally:
            cluster.close()
        return
    try:
        client = Client(scheduler, timeout="20s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise VioGraphError(f"--scheduler {scheduler}: cannot connect ({exc})") from exc
    try:
        yield client
    finally:
        client.close()


def run_tasks(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    scheduler: str | None = None,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    names: Sequence[str] | None = None,
) -> list[Outcome]:
    """Apply ``fn`` to every item (see the module docstring for ``scheduler``); one
    :class:`Outcome` per item in the items' order. ``progress(n)`` is called with the number
    of finished tasks; ``names`` (one per item) label the tasks on the Dask dashboard."""
    items = list(items)
    if scheduler == SERIAL:
        outcomes = []
        for k, item in enumerate(items):
            try:
                outcomes.append(Outcome(value=fn(item)))
            except Exception as exc:  # isolated: reported in the outcome, the rest goes on
                log.debug("task %d failed", k, exc_info=True)
                outcomes.append(Outcome(error=_error_line(exc)))
            if progress:
                progress(k + 1)
        return outcomes

    from distributed import as_completed

    run_id = uuid.uuid4().hex[:8]
    with dask_client(scheduler, workers) as client:
        futures = []
        for k, item in enumerate(items):
            label = names[k] if names is not None else str(k)
            key = f"{fn.__name__}-{label}-{run_id}-{k}"  # unique; Dask groups by prefix
            futures.append(client.submit(fn, item, key=key, pure=False))
        index = {f.key: k for k, f in enumerate(futures)}
        outcomes: list[Outcome | None] = [None] * len(items)
        for done, fut in enumerate(as_completed(futures), start=1):
            k = index[fut.key]
            try:
                outcomes[k] = Outcome(value=fut.result())
            except Exception as exc:  # the task's own error, or KilledWorker
                outcomes[k] = Outcome(error=_error_line(exc))
            fut.release()
            if progress:
                progress(done)
    return [o if o is not None else Outcome(error="lost") for o in outcomes]


def map_or_raise(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    scheduler: str | None,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[Any]:
    """:func:`run_tasks`, then the values; any failed task -> one VioGraphError listing them
    (the behaviour of the process-pool path, which stops on an error, after the rest ran)."""
    outcomes = run_tasks(fn, items, scheduler, workers, progress)
    failed = [(k, o.error) for k, o in enumerate(outcomes) if not o.ok]
    if failed:
        lines = "; ".join(f"task {k} ({items[k]!r:.80}): {err}" for k, err in failed)
        raise VioGraphError(f"{len(failed)} of {len(items)} tasks failed: {lines}")
    return [o.value for o in outcomes]
