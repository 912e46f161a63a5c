"""The garbage collector's start-up pause of ``vio-graph run`` (vio_graph/memory.py): off
while the run starts, on again with the start-up's objects frozen once the replay starts,
and as it was after the run (nothing frozen, collector on), also when the run fails."""

from __future__ import annotations

import gc
import signal
import sys
from pathlib import Path

import pytest

from vio_graph import memory
from vio_graph.memory import collection_paused_for_start_up, start_up_done


@pytest.fixture(autouse=True)
def _collector_restored():
    enabled = gc.isenabled()
    yield
    assert memory._start_up is None
    assert gc.get_freeze_count() == 0
    if enabled:
        gc.enable()
    else:
        gc.disable()


def test_pause_then_freeze_then_restore() -> None:
    assert gc.isenabled() and gc.get_freeze_count() == 0
    with collection_paused_for_start_up():
        assert not gc.isenabled()
        start_up_done()
        assert gc.isenabled() and gc.get_freeze_count() > 0
        start_up_done()  # once only
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_without_start_up_done_the_block_turns_it_back_on() -> None:
    with collection_paused_for_start_up():
        assert not gc.isenabled()
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_restored_when_the_block_raises() -> None:
    with pytest.raises(RuntimeError), collection_paused_for_start_up():
        start_up_done()
        raise RuntimeError("a failed run")
    assert gc.isenabled() and gc.get_freeze_count() == 0
    with pytest.raises(RuntimeError), collection_paused_for_start_up():
        raise RuntimeError("a run failed before its replay")
    assert gc.isenabled()


def test_left_alone_when_off_frozen_or_nested() -> None:
    start_up_done()  # outside a block: nothing
    assert gc.isenabled() and gc.get_freeze_count() == 0
    gc.disable()
    with collection_paused_for_start_up():
        start_up_done()
        assert not gc.isenabled() and gc.get_freeze_count() == 0
    assert not gc.isenabled()
    gc.enable()
    gc.freeze()  # the caller's own freeze is not undone
    try:
        n = gc.get_freeze_count()
        with collection_paused_for_start_up():
            assert gc.isenabled()
            fresh = [[] for _ in range(1000)]  # a second freeze would take these
            start_up_done()
        # neither unfrozen (frozen objects freed meanwhile lower the count by a few) nor
        # frozen again (the fresh lists would raise it by 1000)
        assert gc.isenabled() and n - 100 <= gc.get_freeze_count() <= n
        del fresh
    finally:
        gc.unfreeze()
    with collection_paused_for_start_up():
        with collection_paused_for_start_up():  # inner block: no second pause
            pass
        assert not gc.isenabled()
    assert gc.isenabled()


def test_run_command_pauses_until_the_replay_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``vio-graph run`` in this process: the collector is off up to the replay, on during
    it with objects frozen, and as before afterwards."""
    from tests.test_cli import _two_second_recording
    from vio_graph import replay
    from vio_graph.cli import main

    rec = _two_second_recording(tmp_path / "rec")
    seen = []
    real_run = replay.Replay.run

    def run(self, *args, **kwargs):
        seen.append((gc.isenabled(), gc.get_freeze_count() > 0))
        return real_run(self, *args, **kwargs)

    monkeypatch.setattr(replay.Replay, "run", run)
    monkeypatch.setattr(
        sys, "argv", ["vio-graph", "run", str(rec), "--out", str(tmp_path / "o"), "--no-rerun"]
    )
    previous = signal.getsignal(signal.SIGTERM)
    try:
        main()
    except SystemExit as exc:
        assert not exc.code
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert seen == [(True, True)]
    assert gc.isenabled() and gc.get_freeze_count() == 0
    assert (tmp_path / "o" / "metrics.json").is_file()


def test_everything_is_frozen_at_the_interpreter_exit(tmp_path: Path) -> None:
    """A process that ran ``vio-graph run`` freezes its objects at exit (atexit), after the
    run's files are complete: the shutdown's collections then skip them."""
    import json
    import os
    import subprocess

    from tests.test_cli import _two_second_recording

    rec = _two_second_recording(tmp_path / "rec")
    out = tmp_path / "out"
    code = """
import atexit, gc, json, sys
# registered first, so it runs last (atexit runs its handlers in reverse order)
atexit.register(lambda: print(json.dumps({"frozen": gc.get_freeze_count()})))
from vio_graph.cli import main
sys.argv = ["vio-graph", "run", sys.argv[1], "--out", sys.argv[2], "--no-rerun"]
main()
"""
    repo = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(repo) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(
        [sys.executable, "-c", code, str(rec), str(out)],
        capture_output=True,
        text=True,
        env=env,
        cwd=repo,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1])["frozen"] > 10_000
    assert json.loads((out / "metrics.json").read_text())["frames"] == 60
