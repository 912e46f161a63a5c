"""Long-trial bookkeeping of the online path: the same answers with less time and memory.

``TerrainMap2D.add_keyframe`` keeps its sorted timestamp cache and skips the sort when the
keyframes come in time order (a replay adds one per keyframe: re-sorting and rebuilding the
cache each time was O(K^2) over a 10-minute trial); ``ClockModel`` keeps its corrections in
a float64 buffer instead of a list of Python floats. Both must behave as before.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.filter.time_offset import ClockModel
from vio_graph.mapping.local_map import TerrainMap2D


def _profile(rng: np.random.Generator) -> np.ndarray:
    x = np.sort(rng.uniform(0.2, 1.0, 40))
    return np.column_stack([x, -0.4 + 0.02 * np.floor(x / 0.1)])


def test_map_in_order_equals_shuffled_insertion() -> None:
    rng = np.random.default_rng(0)
    times = np.round(np.cumsum(rng.uniform(0.05, 0.2, 60)), 6)
    cams = np.column_stack([np.cumsum(rng.uniform(0.0, 0.05, 60)), np.zeros(60)])
    profs = [_profile(rng) for _ in times]
    in_order, shuffled = TerrainMap2D(), TerrainMap2D()
    for t, c, p in zip(times, cams, profs, strict=True):
        in_order.add_keyframe(t, c, p)
    for k in rng.permutation(times.size):
        shuffled.add_keyframe(times[k], cams[k], profs[k])
    assert [kf.timestamp_s for kf in in_order.keyframes] == list(times)
    assert [kf.timestamp_s for kf in shuffled.keyframes] == list(times)
    np.testing.assert_array_equal(in_order.points_xz_m, shuffled.points_xz_m)
    # the cache still finds stored keyframes: same timestamp replaces, refined poses move
    in_order.add_keyframe(times[10], cams[10] + 1.0, profs[10])
    assert len(in_order) == times.size
    assert in_order.keyframes[10].camera_xz_m[0] == cams[10, 0] + 1.0
    assert in_order.update_poses({float(times[-1]): [5.0, 0.0], 1e6: [0.0, 0.0]}) == 1
    assert in_order.keyframes[-1].camera_xz_m[0] == 5.0
    # a late (out of order) keyframe is sorted in, then in-order adds continue
    in_order.add_keyframe(times[5] + 1e-3, cams[5], profs[5])
    in_order.add_keyframe(times[-1] + 1.0, cams[-1], profs[-1])
    ts = [kf.timestamp_s for kf in in_order.keyframes]
    assert ts == sorted(ts) and len(ts) == times.size + 2
    assert in_order.update_poses({times[5] + 1e-3: [7.0, 0.0]}) == 1


def test_clock_correction_report_over_a_long_stream() -> None:
    rng = np.random.default_rng(1)
    period = 0.01
    stamps = np.arange(5000) * period + rng.normal(0, 0.002, 5000)
    stamps = np.maximum.accumulate(stamps) + np.arange(5000) * 1e-9
    clock = ClockModel(period, window=50, gap_periods=5.0)
    outs = np.array([clock.correct(s) for s in stamps])
    corr = outs - stamps
    rep = clock.report()
    assert rep["correction_rms_s"] == float(np.sqrt(np.mean(corr**2)))
    assert rep["correction_max_s"] == float(np.max(np.abs(corr)))
    assert 0 < rep["correction_rms_s"] < 0.003  # smoothing removes part of the 2 ms jitter


def test_map_cells_equal_merge_points_bit_for_bit() -> None:
    """TerrainMap2D.cells merges keyframe by keyframe (vio_graph/mapping/local_map.py
    merge_keyframes, for the peak memory of long trials): the same cells, counts and means,
    bit for bit, as merge_points on all the points at once, also with empty and partly
    non-finite profiles and keyframes that share cells."""
    from vio_graph.mapping.config import MapConfig
    from vio_graph.mapping.local_map import merge_points

    rng = np.random.default_rng(3)
    for cfg in (MapConfig(), MapConfig(min_keyframes_per_cell=1), MapConfig(cell_size_m=0.02)):
        tmap = TerrainMap2D(cfg)
        for k in range(80):
            prof = _profile(rng) + rng.normal(0.0, 0.004, (40, 2))
            if k % 7 == 0:
                prof[rng.integers(0, 40, 3)] = np.nan
            if k % 11 == 0:
                prof = np.zeros((0, 2))
            tmap.add_keyframe(0.1 * k, [0.03 * k - 2.0, rng.normal(0.0, 0.01)], prof)
        raw, index = tmap.raw_points_xz_m()
        ref = merge_points(raw, index, cfg)
        got = tmap.cells
        assert len(got) > 100
        for name in ("points_xz_m", "point_counts", "keyframe_counts"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))
            assert getattr(got, name).dtype == getattr(ref, name).dtype
    empty = TerrainMap2D()
    empty.add_keyframe(0.0, [0.0, 0.0], np.zeros((0, 2)))
    assert len(empty.cells) == 0 and empty.cells.points_xz_m.shape == (0, 2)


def test_map_cells_equal_merge_points_across_batches(monkeypatch) -> None:
    """merge_keyframes in batches of consecutive keyframes (``_KEY_BATCH`` points; here a few
    dozen, so that batches end mid-map, around empty keyframes and at the last one) gives
    merge_points' cells bit for bit; its sorted distinct keys are np.unique's."""
    from vio_graph.mapping import local_map
    from vio_graph.mapping.config import MapConfig
    from vio_graph.mapping.local_map import merge_points

    rng = np.random.default_rng(11)
    keys = rng.integers(-50, 50, 400)
    np.testing.assert_array_equal(local_map._sorted_distinct(keys), np.unique(keys))
    assert local_map._sorted_distinct(np.zeros(0, np.int64)).shape == (0,)
    cfg = MapConfig(min_keyframes_per_cell=2)
    tmap = TerrainMap2D(cfg)
    for k in range(60):
        prof = _profile(rng) + rng.normal(0.0, 0.004, (40, 2))
        if k % 9 == 0 or k == 59:  # empty ones, the last keyframe too
            prof = np.zeros((0, 2))
        tmap.add_keyframe(0.1 * k, [0.02 * k - 1.0, rng.normal(0.0, 0.01)], prof)
    raw, index = tmap.raw_points_xz_m()
    ref = merge_points(raw, index, cfg)
    for batch in (1, 37, 80, 10**6):
        monkeypatch.setattr(local_map, "_KEY_BATCH", batch)
        got = local_map.merge_keyframes(tmap.keyframes, cfg)
        assert len(got) > 100
        for name in ("points_xz_m", "point_counts", "keyframe_counts"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))


def test_map_without_copy_shares_finite_profiles_only() -> None:
    prof = np.column_stack([np.linspace(0.2, 1.0, 10), np.full(10, -0.4)])
    tmap = TerrainMap2D()
    tmap.add_keyframe(0.0, [0.0, 0.0], prof, copy=False)
    tmap.add_keyframe(1.0, [0.0, 0.0], prof)
    assert tmap.keyframes[0].profile_xz_m is prof
    assert not np.shares_memory(tmap.keyframes[1].profile_xz_m, prof)
    bad = prof.copy()
    bad[3] = np.nan
    tmap.add_keyframe(2.0, [0.0, 0.0], bad, copy=False)  # rows dropped: a new array
    assert tmap.keyframes[2].profile_xz_m.shape == (9, 2)
    assert not np.shares_memory(tmap.keyframes[2].profile_xz_m, bad)


# ------------------------------------------------------------------ the online estimator
#: what may grow over a trial, and why: the safety monitor's height map is a grid along x
#: (it grows with the distance walked, not with the frames), and the two clock models keep
#: their corrections (8 bytes a sample in one float64 buffer) for metrics.json's RMS and max
GROWS_WITH_DISTANCE = ("online.safety.map.", "online.safety.map[")
COMPACT_PER_SAMPLE = ("online.imu_clock._corr", "online.frame_clock._corr")


def _container_sizes(root: object, name: str) -> dict[str, tuple[str, int]]:
    """Every list, tuple, dict, deque and set (("len", length)) and numpy array (("bytes",
    nbytes)) reachable from ``root`` through vio_graph objects' attributes, by path."""
    import collections

    out: dict[str, tuple[str, int]] = {}
    seen: set[int] = set()

    def visit(obj: object, path: str, depth: int) -> None:
        if id(obj) in seen or depth > 8:
            return
        seen.add(id(obj))
        if isinstance(obj, np.ndarray):
            out[path] = ("bytes", obj.nbytes)
        elif isinstance(obj, list | tuple | collections.deque | set | frozenset):
            out[path] = ("len", len(obj))
            for i, v in enumerate(list(obj)[:3]):
                visit(v, f"{path}[{i}]", depth + 1)
        elif isinstance(obj, dict):
            out[path] = ("len", len(obj))
            for i, v in enumerate(list(obj.values())[:3]):
                visit(v, f"{path}[{i}]", depth + 1)
        elif type(obj).__module__.startswith("vio_graph") and hasattr(obj, "__dict__"):
            for k, v in vars(obj).items():
                visit(v, f"{path}.{k}", depth + 1)

    visit(root, name, 0)
    return out


@pytest.fixture(scope="module")
def upstair_10s(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from vio_graph.sim import load_scenario, simulate

    cfg = load_scenario("upstair")  # 10 s, 300 frames
    return simulate(cfg, seed=2, out_dir=tmp_path_factory.mktemp("bounded") / "up")


@pytest.mark.slow
def test_online_estimator_state_stays_bounded(upstair_10s: Path) -> None:
    """Nothing the online estimator keeps grows with the number of frames: between frame
    120 and the last (~180 frames later) no container reachable from it gains more than a
    quarter entry per frame or 64 bytes per frame, except the height map (grows with the
    distance) and the clock corrections (8 bytes a sample). The clock-model window is cut to
    30 samples so that every window is full by frame 120 on a 10 s trial."""
    from vio_graph.config import load_config
    from vio_graph.recording import Recording
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = load_config(None)
    to = cfg.filter.time_offset.model_copy(update={"clock_window": 30})
    cfg = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"time_offset": to})})
    rec = Recording.open(upstair_10s)
    replay = Replay(rec, cfg, {"filter"}, NullVisualizer())
    first, snaps = 120, {}
    run_frame = replay._frame

    def frame(i: int) -> None:
        run_frame(i)
        if i in (first, rec.num_frames - 1):
            snaps[i] = _container_sizes(replay.online, "online")

    replay._frame = frame  # type: ignore[method-assign]
    lg = replay.run()
    last = rec.num_frames - 1
    assert len(lg.t_s) == rec.num_frames and set(snaps) == {first, last}
    n = last - first
    mid, end = snaps[first], snaps[last]
    assert len(end) > 100  # the walk reached the estimator's parts
    grown = {}
    for path, (kind, size) in end.items():
        if path.startswith(GROWS_WITH_DISTANCE + COMPACT_PER_SAMPLE):
            continue
        before = mid.get(path, (kind, 0))[1]
        if size - before > (64 * n if kind == "bytes" else 0.25 * n):
            grown[path] = (before, size)
    assert not grown, f"grows with the frames: {grown}"
    # the height map does grow (the walk covers ~8 m): the allowance is not vacuous
    assert any(
        size > mid.get(p, ("", 0))[1]
        for p, (_, size) in end.items()
        if p.startswith(GROWS_WITH_DISTANCE)
    )
