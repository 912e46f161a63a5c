"""The replay's compact per-frame timing table reads like the list of dicts it replaced, and
the recording reader hands back its memory-mapped depth pages (flat memory on long trials)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import vio_graph.recording.reader as reader_mod
from vio_graph.recording import Recording
from vio_graph.replay import TimingTable


def test_timing_table_reads_like_a_list_of_dicts() -> None:
    rng = np.random.default_rng(0)
    rows = []
    for k in range(300):  # grows past its first capacity several times; stages come and go
        row = {"frontend_total": float(rng.uniform(1, 5)), "fusion": float(rng.uniform(0, 1))}
        if k % 7 == 0:
            row["frontend_icp"] = float(k)
        if k >= 150:
            row["late_stage"] = 0.5
        rows.append(row)
    table = TimingTable()
    for row in rows:
        table.append(row)
    assert len(table) == len(rows)
    assert list(table) == rows
    assert table[-1] == rows[-1] and table[7] == rows[7]
    np.testing.assert_array_equal(table.column("fusion"), [r["fusion"] for r in rows])
    icp = table.column("frontend_icp")
    assert np.isnan(icp[1]) and icp[14] == 14.0
    assert np.isnan(table.column("late_stage")[:150]).all()
    assert np.isnan(table.column("never_timed")).all() and table.column("never_timed").size == 300
    with pytest.raises(IndexError):
        table[300]


def _rss_file_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssFile:"):
            return int(line.split()[1])
    pytest.skip("no /proc/self/status RssFile (not Linux)")
    return 0


def test_reading_every_frame_does_not_keep_the_depth_maps_resident(
    short_upstair: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(reader_mod, "RELEASE_EVERY_FRAMES", 16)
    rec = Recording.open(short_upstair)
    depth, _, conf = rec._depth
    before = _rss_file_kib()
    frames = [rec.frame(i) for i in range(rec.num_frames)]
    grown_kib = _rss_file_kib() - before
    mapped_kib = (depth.nbytes + conf.nbytes) // 1024
    assert mapped_kib > 5000  # the test means something: the maps are larger than the slack
    assert grown_kib < 0.3 * mapped_kib  # without the hand-back it grows by ~mapped_kib
    # and the frames read are right: the same values as reading the arrays directly
    k = len(frames) // 2
    assert np.array_equal(frames[k].depth_m > 0, np.asarray(depth[k]) > 0)


def test_run_view_computes_nothing_for_the_null_visualizer_only(tmp_path: Path) -> None:
    """--no-rerun (the NullVisualizer itself): the per-frame view is skipped; a visualizer that
    records (any subclass) still receives every frame's logs, the same as before."""
    from vio_graph.config import load_config
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    class Spy(NullVisualizer):
        def __init__(self) -> None:
            self.calls: list[str] = []

        def set_time(self, timestamp_s: float) -> None:
            self.calls.append("time")

        def log_leg(self, name, points_xz_m) -> None:
            self.calls.append(f"leg/{name}")

    rec = Recording.open(Path(__file__).resolve().parents[1] / "data" / "sample")
    spy = Spy()
    replay = Replay(rec, load_config(), {"filter"}, spy)
    assert replay.view.active
    replay.run()
    assert spy.calls.count("time") == rec.num_frames and "leg/gt" in spy.calls
    quiet = Replay(rec, load_config(), {"filter"}, NullVisualizer())
    assert not quiet.view.active
    quiet.view.frame(0, None, None)  # returns before touching its arguments
    lg = quiet.run()
    assert np.array_equal(lg.camera_xz["filter"], replay.log.camera_xz["filter"])


def test_growable_array_reads_like_the_list_it_replaces() -> None:
    """FrameLog's numbers and the estimators' camera paths (vio_graph/growable.py): one
    float64 buffer instead of a Python object per frame, read as the list was."""
    from vio_graph.growable import GrowableArray

    rng = np.random.default_rng(1)
    floats = [float(v) for v in rng.normal(size=300)]  # past the first capacity, 3 times
    rows = [rng.normal(size=(2, 2)) for _ in range(300)]
    col, mats = GrowableArray(), GrowableArray((2, 2))
    assert not col and len(col) == 0 and np.asarray(mats).shape == (0, 2, 2)
    for v, m in zip(floats, rows, strict=True):
        col.append(v)
        mats.append(m)
    assert col and len(col) == 300 and list(col) == floats
    assert type(col[5]) is float and col[-1] == floats[-1]
    np.testing.assert_array_equal(np.asarray(col), floats)
    np.testing.assert_array_equal(col[10:20], floats[10:20])
    np.testing.assert_array_equal(np.asarray(mats), np.stack(rows))
    got = mats[7]
    got[0, 0] = 99.0  # a copy: the store is unchanged
    assert mats[7][0, 0] == rows[7][0, 0]
    arr = np.asarray(col)
    arr[0] = 99.0
    assert col[0] == floats[0]
    with pytest.raises(IndexError):
        col[300]
    with pytest.raises(ValueError):
        mats.append(np.zeros(3))  # a row of another shape


def test_safety_log_gives_back_the_estimates_appended() -> None:
    """FrameLog.safety (vio_graph/safety/online.py SafetyLog): one float64 row a frame, read
    back as SafetyEstimate objects equal field for field (bools, ints, NaN) or None, and
    columns equal to the ones built from the objects."""
    import dataclasses

    from vio_graph.safety.online import SafetyEstimate, SafetyLog

    rng = np.random.default_rng(2)
    ests: list = []
    for k in range(150):
        if k % 9 == 0:
            ests.append(None)
            continue
        ests.append(
            SafetyEstimate(
                float(rng.normal()),
                float("nan") if k % 4 == 0 else float(rng.uniform()),
                rng.normal(size=(2, 2)),
                float(rng.normal()),
                float(rng.normal()),
                float(rng.normal()),
                float(rng.normal()),
                bool(k % 3 == 0),
                float(rng.normal()),
                float(rng.normal()),
                int(k // 10),
                float(rng.normal()),
                float(rng.normal()),
                bool(k % 5 == 0),
                np.where(rng.uniform(size=4) < 0.3, np.nan, rng.normal(size=4)),
                edge_xz_m=rng.normal(size=2),
                near_trip_clearance_m=float(rng.normal()),
                pose_consistency_scale=float(rng.uniform(1, 2)),
            )
        )
    log = SafetyLog()
    assert not log
    for e in ests:
        log.append(e)
    assert len(log) == len(ests) and log[0] is None
    for a, b in zip(ests, log, strict=True):
        if a is None:
            assert b is None
            continue
        for f in dataclasses.fields(SafetyEstimate):
            va, vb = getattr(a, f.name), getattr(b, f.name)
            assert type(va) is type(vb), f.name
            np.testing.assert_array_equal(va, vb)  # NaN where NaN
    for name in ("clearance_sigma_m", "steps_seen", "landing", "placement", "toe_line_xz_m"):
        ref = np.array(
            [
                getattr(e, name)
                if e is not None
                else np.full(np.shape(getattr(ests[1], name)), np.nan)
                for e in ests
            ],
            float,
        )
        np.testing.assert_array_equal(log.column(name), ref)
    with pytest.raises(KeyError):
        log.column("no_such_field")


def test_safety_log_rows_are_the_fields_joined_bit_for_bit() -> None:
    """SafetyLog.append writes each row from a list of Python floats; the row is, bit for
    bit, the fields converted one by one and joined as float64 arrays (NaN payloads, signed
    zeros, float32 arrays, numpy bools and ints included), and None is NaN with a 0 flag."""
    import dataclasses

    from vio_graph.safety.online import _ARRAY_FIELDS, SafetyEstimate, SafetyLog

    rng = np.random.default_rng(5)
    payload_nan = np.array([0x7FF8_0000_0000_1234], dtype=np.uint64).view(np.float64)[0]
    specials = [float("nan"), -0.0, 0.0, float(payload_nan), 1e-310, -np.inf, 5e300]

    def value(k: int) -> float:
        return specials[k % len(specials)] if k % 3 == 0 else float(rng.normal())

    ests: list = []
    for k in range(120):
        if k % 11 == 5:
            ests.append(None)
            continue
        toe_line = rng.normal(size=(2, 2))
        toe_line[0, 0] = value(k)
        placement = np.array([value(k + j) for j in range(4)])
        ests.append(
            SafetyEstimate(
                value(k),
                value(k + 1),
                toe_line.astype(np.float32) if k % 4 == 0 else toe_line,
                value(k + 2),
                value(k + 3),
                value(k + 4),
                value(k + 5),
                np.bool_(k % 2 == 0) if k % 5 else bool(k % 2),
                value(k + 6),
                value(k + 7),
                np.int64(k // 7) if k % 5 else int(k // 7),
                value(k + 8),
                np.float64(value(k + 9)),
                bool(k % 3 == 0),
                placement,
                edge_xz_m=np.array([value(k + 10), -0.0]),
                near_trip_clearance_m=value(k + 11),
                pose_consistency_scale=float(rng.uniform(1, 2)),
            )
        )
    log = SafetyLog()
    for e in ests:
        log.append(e)
    names = [f.name for f in dataclasses.fields(SafetyEstimate)]
    scalars = [n for n in names if n not in _ARRAY_FIELDS]
    arrays = [n for n in names if n in _ARRAY_FIELDS]
    for k, e in enumerate(ests):
        if e is None:
            ref = np.r_[np.full(log._rows.row_shape[0] - 1, np.nan), 0.0]
        else:
            ref = np.concatenate(
                [np.array([float(getattr(e, n)) for n in scalars])]
                + [np.asarray(getattr(e, n), float).reshape(-1) for n in arrays]
                + [[1.0]]
            )
        row = log._rows.view()[k]
        assert row.shape == ref.shape
        np.testing.assert_array_equal(row.view(np.uint64), ref.view(np.uint64), err_msg=str(k))
