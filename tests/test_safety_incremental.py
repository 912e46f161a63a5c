"""The fast safety paths give the reference's answers: the incremental height map
(vio_graph/safety/height_map.py) against the map that rebuilds its whole profile per keyframe,
and the compiled kernels (vio_graph/safety/compiled.py) against the numpy geometry
(vio_graph/safety/clearance.py), per frame over a filter replay of data/sample and on random
stairs."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from vio_graph.config import load_config
from vio_graph.safety import clearance
from vio_graph.safety.clearance import HeightProfile
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.height_map import IncrementalHeightMap, OnlineHeightMap
from vio_graph.safety.online import SafetyEstimate, SafetyMonitor

TOL_M = 1e-9  # compiled against numpy: rounding only


def _compiled():
    pytest.importorskip("numba")
    from vio_graph.safety import compiled

    return compiled


def _replay(frames: list[tuple], cfg: SafetyConfig, **kw) -> list[np.ndarray]:
    mon = SafetyMonitor(cfg, **kw)
    return [_as_row(mon.update(*f)) for f in frames]


def _as_row(s: SafetyEstimate) -> np.ndarray:
    """Every field of an estimate as one float vector."""
    return np.concatenate([np.ravel(np.asarray(getattr(s, f.name), float)) for f in fields(s)])


@pytest.mark.parametrize("motion_model", ["swing_template", "constant_velocity"])
def test_incremental_map_gives_the_reference_estimates_over_a_replay(
    sample_frames, motion_model: str
) -> None:
    """Every output of every frame of data/sample is the same, to the bit, with the
    incremental map as with the map rebuilt per keyframe (both numpy); the compiled kernels
    agree within 1e-9 m."""
    cfg = load_config(None).safety.model_copy(update={"motion_model": motion_model})
    ref = _replay(sample_frames, cfg, incremental=False)
    inc = _replay(sample_frames, cfg, incremental=True, compiled=False)
    assert sum(f[6] is not None for f in sample_frames) > 20  # keyframes joined the map
    assert np.isfinite(np.array(ref)[:, 0]).sum() > 50  # clearances were computed
    for k, (a, b) in enumerate(zip(ref, inc, strict=True)):
        np.testing.assert_array_equal(a, b, err_msg=f"frame {k}")
    _compiled()
    comp = _replay(sample_frames, cfg, compiled=True)
    assert _replay(sample_frames[:5], cfg, compiled=False)  # numpy: the reference map
    for k, (a, b) in enumerate(zip(ref, comp, strict=True)):
        np.testing.assert_allclose(b, a, rtol=0, atol=TOL_M, err_msg=f"frame {k}")


def _noisy_stairs(rng: np.random.Generator) -> np.ndarray:
    """A polyline (P, 2) of stairs going up, then down, with a platform between, m. Half the
    risers are two 1 cm ramps with a 1 cm landing between: two transitions the edge scan
    joins into one edge."""
    pts, x, z = [(-1.0, 0.0)], 0.0, 0.0
    for k, rise in enumerate([*rng.uniform(0.1, 0.18, 6), *(-rng.uniform(0.1, 0.18, 6))]):
        if k % 2:
            pts += [(x, z), (x + 0.01, z + rise / 2), (x + 0.02, z + rise / 2)]
            pts += [(x + 0.03, z + rise)]
            x += 0.03
        else:
            pts += [(x, z), (x, z + rise)]
        x, z = x + rng.uniform(0.22, 0.34), z + rise
    pts.append((x + 1.0, z))
    return np.asarray(pts)


def _keyframe_profile(rng: np.random.Generator, stairs: np.ndarray, x0: float) -> np.ndarray:
    """Points on the stairs over ~1.2 m from x0 with 2 mm noise, a few mixed pixels and an
    occasional unseen stretch, relative to a camera at (x0, 0.5)."""
    x = np.sort(rng.uniform(x0, x0 + 1.2, 400))
    z = np.interp(x, stairs[:, 0] + 1e-9 * np.arange(len(stairs)), stairs[:, 1])
    z = z + rng.normal(0, 0.002, x.size)
    mixed = rng.random(x.size) < 0.02
    z[mixed] -= rng.uniform(0.0, 0.15, mixed.sum())
    if rng.random() < 0.3:  # an unseen stretch
        a = rng.uniform(x0, x0 + 1.0)
        keep = (x < a) | (x > a + rng.uniform(0.05, 0.3))
        x, z = x[keep], z[keep]
    return np.stack([x - x0, z - 0.5], 1)


@pytest.mark.parametrize("agreement", [None, (2, 0.004)])
@pytest.mark.parametrize("statistic", ["median", "mean"])
def test_incremental_map_queries_equal_the_reference_on_random_stairs(
    statistic: str, agreement: tuple[int, float] | None
) -> None:
    """Keyframes walking up and down noisy stairs (forwards, back, and a jump that grows the
    map on both sides): after each, the edges, windows at random ranges and the bin before an
    x are those of the reference map, exactly; the compiled keyframe step and edge re-scan
    agree within 1e-9 m. ``agreement``: bins used after 2 agreeing views (with mixed pixels
    in the profiles, some bins pass the test and some wait for the 3 views), and a foot
    standing on the stairs after every other keyframe (its contact caps the bins under it,
    on treads and across risers)."""
    rng = np.random.default_rng(11)
    stairs = _noisy_stairs(rng)
    kw = {"statistic": statistic, "edge_min_rise_m": 0.04, "edge_max_gap_m": 0.15}
    if agreement is not None:
        kw |= {"agree_keyframes": agreement[0], "agree_m": agreement[1]}
    ref = OnlineHeightMap(0.005, 3, **kw)
    inc = IncrementalHeightMap(0.005, 3, **kw)
    comp = IncrementalHeightMap(0.005, 3, kernels=_compiled(), **kw)
    xs = [*np.arange(-0.8, 3.5, 0.03), *np.arange(3.5, 0.5, -0.05), 4.5, -1.5, 1.0]
    n_edges = n_contacts = n_gaps = n_kept = 0
    e_comp_prev = None
    for x0 in xs:
        P = np.diag(rng.uniform(1e-6, 1e-4, 2))
        prof = _keyframe_profile(rng, stairs, float(x0))
        for m in (ref, inc, comp):
            m.add_keyframe([x0, 0.5], prof, P)
        if agreement is not None and rng.random() < 0.5:
            hx = float(x0 + rng.uniform(0.0, 1.0))
            hz = float(np.interp(hx, stairs[:, 0] + 1e-9 * np.arange(len(stairs)), stairs[:, 1]))
            heel = np.array([hx, hz + rng.normal(0.0, 0.003)])
            toe = heel + [0.25, rng.normal(0.0, 0.01)]
            changed = [m.add_contact(heel, toe, 0.006, 0.04) for m in (ref, inc, comp)]
            assert changed[0] == changed[1] == changed[2]
            n_contacts += changed[0] is not None
        e_ref, e_inc, e_comp = ref.edges(), inc.edges(), comp.edges()
        np.testing.assert_array_equal(e_inc.xz_m, e_ref.xz_m)
        np.testing.assert_array_equal(e_inc.rise_m, e_ref.rise_m)
        np.testing.assert_array_equal(inc.edge_summary(), ref.edge_summary())
        np.testing.assert_allclose(e_comp.xz_m, e_ref.xz_m, rtol=0, atol=TOL_M)
        np.testing.assert_allclose(e_comp.rise_m, e_ref.rise_m, rtol=0, atol=TOL_M)
        # (the compiled map keeps its edges' summary while the re-scan leaves them as they were)
        np.testing.assert_allclose(comp.edge_summary(), ref.edge_summary(), rtol=0, atol=TOL_M)
        n_kept += comp.edges() is e_comp_prev
        e_comp_prev = e_comp
        n_edges = max(n_edges, len(e_ref))
        for _ in range(5):
            lo = float(rng.uniform(-2.0, 3.5))
            hi = lo + float(rng.uniform(-0.01, 0.8))
            w_ref, w_inc = ref.window(lo, hi, 0.003), inc.window(lo, hi, 0.003)
            w_comp = comp.window(lo, hi, 0.003)
            for name in ("x_lo_m", "x_hi_m", "z_m", "sigma_m"):
                a = getattr(w_ref.profile, name)
                np.testing.assert_array_equal(getattr(w_inc.profile, name), a)
                np.testing.assert_allclose(getattr(w_comp.profile, name), a, rtol=0, atol=TOL_M)
            np.testing.assert_array_equal(w_inc.bins, w_ref.bins)
            np.testing.assert_array_equal(w_comp.bins, w_ref.bins)
            # the compiled early answer of the gap check: a strip to fill exactly when
            # gap_terrain finds floors (numpy: always "ask gap_terrain")
            max_gap = float(rng.choice([0.02, 0.15]))
            floors = clearance.gap_terrain(w_ref.profile, w_ref.bins, max_gap)[0]
            assert comp.bridged_gap(lo, hi, max_gap) == (len(floors) > 0)
            n_gaps += len(floors) > 0
            assert inc.bridged_gap(lo, hi, max_gap)
            for b in w_ref.bins[:3]:
                np.testing.assert_array_equal(inc.bin_cov_at(b), ref.bin_cov_at(b))
                assert inc.bin_sigma(b, 0.003) == ref.bin_sigma(b, 0.003)
            x = float(rng.uniform(-2.0, 3.5))
            assert inc.bin_below(x) == ref.bin_below(x) == comp.bin_below(x)
    assert n_edges >= 10  # the stairs' edges were found, up and down
    assert agreement is None or n_contacts >= 20  # contacts lowered bins
    assert n_gaps >= 5  # windows with strips to fill were checked
    assert n_kept >= 5  # keyframes that left the edges as they were


def _random_case(rng: np.random.Generator):
    """Random stairs (exact height field), a foot near them (penetrating at times), its
    motion over a 0.3 s horizon and an edge."""
    rise, tread = rng.uniform(-0.18, 0.18), rng.uniform(0.2, 0.35)
    pts = [(-1.0, 0.0)]
    for i in range(6):
        pts += [(i * tread, i * rise), (i * tread, (i + 1) * rise)]
    pts.append((6 * tread + 1.0, 6 * rise))
    prof = HeightProfile.from_polyline(sorted(pts, key=lambda p: p[0]))
    x = rng.uniform(-0.2, 1.4)
    toe = np.array([x, np.interp(x, *np.array(sorted(pts)).T) + rng.uniform(-0.05, 0.2)])
    heel = toe + [rng.uniform(-0.3, -0.15), rng.uniform(-0.08, 0.1)]
    v = rng.uniform(-1.5, 1.5, 2)
    edge = np.array([rng.uniform(-0.2, 1.5), rng.uniform(-0.3, 0.9)])
    return prof.window(x - 0.6, x + 0.6), heel, toe, v, edge


def test_compiled_geometry_equals_the_numpy_geometry() -> None:
    """Clearance, its closest points, column and normal, the clearance of many poses, edge
    clearances, coverage, the predictions and the edges: compiled within 1e-9 m of numpy."""
    K = _compiled()
    rng = np.random.default_rng(3)
    inside = 0
    for _ in range(400):
        prof, heel, toe, v, edge = _random_case(rng)
        a, b = (
            clearance.foot_clearance(heel, toe, prof, 0.01),
            K.foot_clearance(heel, toe, prof, 0.01),
        )
        inside += a.distance_m < -0.01
        assert abs(a.distance_m - b.distance_m) <= TOL_M and a.bin == b.bin
        for f in ("foot_xz_m", "terrain_xz_m", "normal_xz"):
            np.testing.assert_allclose(getattr(b, f), getattr(a, f), rtol=0, atol=TOL_M)
        steps = np.linspace(0, 0.3, 11)[:, None] * v[None]
        hp, tp = heel[None] + steps, toe[None] + steps
        for fn, args in [
            ("clearance_many", (hp, tp, prof, 0.01)),
            ("edge_clearance_many", (hp, tp, edge, 0.01)),
            ("coverage", (heel, toe, prof)),
            ("predicted_min_clearance", (heel, toe, v, 0.3, 10, prof, 0.01)),
            ("predicted_min_edge_clearance", (heel, toe, v, 0.3, 10, edge, 0.01)),
        ]:
            want, got = getattr(clearance, fn)(*args), getattr(K, fn)(*args)
            np.testing.assert_allclose(got, want, rtol=0, atol=TOL_M, err_msg=fn)
        ea, eb = clearance.edge_clearance(heel, toe, edge), K.edge_clearance(heel, toe, edge)
        assert abs(ea.distance_m - eb.distance_m) <= TOL_M
        np.testing.assert_allclose(eb.normal_xz, ea.normal_xz, rtol=0, atol=TOL_M)
        (e1, f1), (e2, f2) = clearance.edge_runs(prof, 0.04, 0.15), K.edge_runs(prof, 0.04, 0.15)
        np.testing.assert_array_equal(e2.xz_m, e1.xz_m)
        np.testing.assert_array_equal(f2, f1)
    assert inside > 10  # penetrating feet were among the cases


def test_compiled_swing_edge_loop_equals_the_numpy_loop() -> None:
    """The swing template's edge loop (SafetyMonitor._swing_edges): the minimum clearance to
    the edges reached, the near-trip candidates' minimum and the edges remembered as cleared,
    the same bits from the compiled kernel as from numpy, over random swings across random
    stairs (also with NaN poses, no next edge, and edges already cleared)."""
    _compiled()
    cfg = load_config(None).safety
    rng = np.random.default_rng(11)
    found = {"risk": 0, "cleared": 0, "nan": 0}
    for n in range(600):
        E = int(rng.integers(1, 6))
        x = np.sort(rng.uniform(0.0, 1.5, E))
        edges = clearance.Edges(
            np.stack([x, rng.uniform(-0.3, 0.5, E)], 1), rng.uniform(-0.2, 0.2, E)
        )
        H = cfg.horizon_steps + 1
        start = np.array([rng.uniform(-0.3, 1.2), rng.uniform(-0.1, 0.6)])
        vel = np.array([rng.uniform(-0.5, 2.5), rng.uniform(-1.5, 1.5)])
        tp = start[None] + np.linspace(0.0, cfg.horizon_s, H)[:, None] * vel[None]
        tp = tp + rng.normal(0.0, 0.005, tp.shape)
        hp = tp + [rng.uniform(-0.26, -0.18), rng.uniform(-0.06, 0.06)]
        if n % 17 == 0:
            tp[int(rng.integers(H)), :] = np.nan
            found["nan"] += 1
        e = int(rng.integers(-1, E))
        cleared = [float(c) for c in x[rng.random(E) < 0.3]]
        out = []
        for compiled in (False, True):
            mon = SafetyMonitor(cfg, incremental=True, compiled=compiled)
            mon._cleared = list(cleared)
            pe, risk = mon._swing_edges(hp.copy(), tp.copy(), edges, e, float(np.nanmax(tp[:, 0])))
            out.append((pe, risk, mon._cleared))
        (pa, ra, ca), (pb, rb, cb) = out
        np.testing.assert_array_equal([pb, rb], [pa, ra], err_msg=f"case {n}")
        assert cb == ca, f"case {n}"
        found["risk"] += bool(np.isfinite(ra))
        found["cleared"] += len(ca) > len(cleared)
    assert found["risk"] > 30 and found["cleared"] > 30 and found["nan"] > 20


def test_compiled_clearance_near_the_foot_equals_every_column() -> None:
    """The compiled clearance of many poses searching only the columns near each pose
    (``_clearance_many_near``, the predictions' kernel) gives the plain loop over every
    column, bit for bit: random stairs and swept feet, some poses far off or NaN."""
    K = _compiled()
    rng = np.random.default_rng(5)
    for n in range(3000):
        prof, heel, toe, v, _ = _random_case(rng)
        tau = np.linspace(0.0, 0.3, 11)[:, None]
        a, b = heel[None] + v[None] * tau, toe[None] + v[None] * tau
        if n % 7 == 0:
            a = a + rng.normal(0.0, 0.3, a.shape)
        if n % 101 == 0:
            b[int(rng.integers(11)), 1] = np.nan
        args = (a, b, prof.x_lo_m, prof.x_hi_m, prof.z_m, 0.01)
        np.testing.assert_array_equal(
            K._clearance_many_near(*args), K._clearance_many(*args), err_msg=f"case {n}"
        )


def test_compiled_edge_summary_equals_the_numpy_summary() -> None:
    """The edge count, mean |rise| and mean spacing the compiled map reports
    (``edge_summary``: numpy's pairwise summation, in a kernel) are ``Edges.summary``'s,
    bit for bit, for 0 to 300 edges (every branch of the summation: in order below 8,
    eight running sums to 128, halves beyond) of values over ten orders of magnitude."""
    K = _compiled()
    rng = np.random.default_rng(8)
    for n in [*range(0, 300), *rng.integers(0, 2000, 40).tolist()]:
        x = np.cumsum(rng.uniform(0.0, 0.4, n) * 10 ** rng.uniform(-5, 5, n))
        edges = clearance.Edges(
            np.stack([x - 1.0, rng.normal(0.0, 1.0, n)], 1),
            rng.normal(0.0, 0.2, n) * 10 ** rng.uniform(-5, 5, n),
        )
        want = edges.summary()
        got = K.edge_summary(edges.xz_m, edges.rise_m)
        assert isinstance(got[0], int) and got[0] == want[0], n
        np.testing.assert_array_equal(np.array(got[1:]), np.array(want[1:]), err_msg=f"{n}")


def test_compiled_template_motion_equals_numbas_interp() -> None:
    """The swing templates' median motion with each column interpolated in place
    (``template_motion``) is the one through ``np.interp`` (``template_motion_reference``),
    bit for bit: one to four templates of 2-60 frames, phases before, inside and past them,
    on sample points, NaN displacements, and templates whose phases repeat a value (these
    go through ``np.interp`` itself)."""
    K = _compiled()
    rng = np.random.default_rng(12)
    h = np.linspace(0.0, 0.3, 11)
    repeated = 0
    for n in range(2000):
        lengths = rng.integers(2, 60, int(rng.integers(1, 5)))
        phases, disps = [], []
        for m in lengths:
            ph = np.cumsum(rng.uniform(0.01, 0.05, m)) - 0.02
            if n % 11 == 0:
                ph[int(rng.integers(1, m))] = ph[0]  # a repeated (or decreasing) phase
                repeated += 1
            d = np.cumsum(rng.normal(0.0, 0.01, (m, 4)), 0)
            if n % 13 == 0:
                d[int(rng.integers(m)), int(rng.integers(4))] = np.nan
            phases.append(ph)
            disps.append(d)
        starts = np.cumsum([0, *lengths]).astype(np.int64)
        phase, disp = np.concatenate(phases), np.concatenate(disps)
        tau = float(rng.choice([rng.uniform(-0.1, 1.5), phase[int(rng.integers(len(phase)))]]))
        np.testing.assert_array_equal(
            K.template_motion(tau, h, phase, disp, starts),
            K.template_motion_reference(tau, h, phase, disp, starts),
            err_msg=f"case {n}",
        )
    assert repeated > 100


def _binned(prof: HeightProfile, rng: np.random.Generator) -> HeightProfile:
    """``prof`` as a height map holds it: 5 mm bins, each with the height under its middle
    plus noise, some bins missing (gaps of one to a few bins)."""
    lo = np.arange(np.floor(prof.x_lo_m[0] / 0.005), np.ceil(prof.x_hi_m[-1] / 0.005)) * 0.005
    k = np.clip(np.searchsorted(prof.x_hi_m, lo + 0.0025), 0, len(prof) - 1)
    z = prof.z_m[k] + rng.normal(0.0, rng.choice([0.0, 0.001, 0.004]), lo.shape)
    keep = rng.random(lo.shape) > rng.choice([0.0, 0.05, 0.3])
    return HeightProfile(lo[keep], lo[keep] + 0.005, z[keep], np.zeros(int(keep.sum())))


def test_compiled_foot_clearance_near_the_foot_equals_every_column() -> None:
    """The compiled clearance of one pose skipping the columns and the hypots that cannot
    give the minimum (``_foot_clearance_near``, the per-frame kernel's) returns what the
    loop over every candidate returns (``_foot_clearance``), bit for bit: distance, closest
    points and column, on random stairs as the map bins them (noise, missing bins), the
    foot above, on and inside the terrain, far off, and with NaN inputs."""
    K = _compiled()
    rng = np.random.default_rng(11)
    found = {"inside": 0, "negative": 0, "far": 0}
    for n in range(3000):
        prof, heel, toe, _, _ = _random_case(rng)
        if n % 2:
            prof = _binned(prof, rng)
        if n % 9 == 0:
            heel, toe = heel + [0.0, 0.3], toe + [0.0, 0.3]
            found["far"] += 1
        if n % 13 == 0:
            toe = heel + [rng.uniform(-1e-13, 1e-13), rng.uniform(-0.01, 0.01)]  # upright
        z = prof.z_m.copy()
        if n % 97 == 0 and len(z):
            z[int(rng.integers(len(z)))] = np.nan
        args = (*heel, *toe, prof.x_lo_m, prof.x_hi_m, z)
        ref = K._foot_clearance(*args)
        np.testing.assert_array_equal(K._foot_clearance_near(*args), ref, err_msg=f"case {n}")
        found["negative"] += bool(ref[0] < 0)
        found["inside"] += any(
            np.any((p[0] >= prof.x_lo_m) & (p[0] <= prof.x_hi_m) & (p[1] < prof.z_m))
            for p in (heel, toe)
        )
    assert found["negative"] > found["inside"] > 100 and found["far"] > 300


@pytest.mark.parametrize("motion_model", ["swing_template", "constant_velocity"])
def test_fused_compiled_steps_equal_the_per_operation_kernels(
    sample_frames, motion_model: str
) -> None:
    """The compiled monitor with each step of a frame in one kernel call (``fused``: the
    keyframe step, the clearance and next edge, either prediction) gives every output of
    every frame of data/sample, to the bit, as the kernels of the single operations with
    the Python between them; over the frames the cleared edges and the map agree too. The
    swing template's prediction check keeps the same predicted poses (fused: the ones the
    swing_prediction kernel returns, not the template motion computed again) and measures
    the same errors."""
    _compiled()
    cfg = load_config(None).safety.model_copy(update={"motion_model": motion_model})
    assert cfg.warning_error_check
    fused = SafetyMonitor(cfg, compiled=True)
    steps = SafetyMonitor(cfg, compiled=True, fused=False)
    assert fused.fused and not steps.fused
    kept = 0  # frames with predictions kept for the check
    for k, f in enumerate(sample_frames):
        a, b = _as_row(fused.update(*f)), _as_row(steps.update(*f))
        np.testing.assert_array_equal(a, b, err_msg=f"frame {k}")
        assert fused._cleared == steps._cleared, k
        pf, ps = fused.prediction_errors, steps.prediction_errors
        assert pf._kept == ps._kept, k
        kept += pf._kept > 0
        np.testing.assert_array_equal(pf._t, ps._t, err_msg=f"frame {k}")
        live = ~np.isnan(pf._t)  # (free rows keep stale poses)
        np.testing.assert_array_equal(pf._poses[live], ps._poses[live], err_msg=f"frame {k}")
        np.testing.assert_array_equal(pf.rms(), ps.rms(), err_msg=f"frame {k}")
    assert (kept > 10) == (motion_model == "swing_template")  # the check ran
    for name in ("_z", "_n", "_mid", "_se2", "_cov", "_edge_xz", "_edge_first"):
        np.testing.assert_array_equal(getattr(fused.map, name), getattr(steps.map, name))
    assert fused.consistency.pose_scale == steps.consistency.pose_scale != 1.0


def test_compiled_unseen_distance_equals_the_numpy_one() -> None:
    """The compiled unseen-terrain distance (frame_terrain's check) equals
    clearance.unseen_distance on random bin layouts, spans and gap bridges."""
    from vio_graph.safety.clearance import HeightProfile, unseen_distance

    K = _compiled()
    rng = np.random.default_rng(7)
    for _ in range(300):
        idx = np.sort(rng.choice(200, size=rng.integers(0, 120), replace=False))
        lo, hi = idx * 0.005, (idx + 1) * 0.005
        prof = HeightProfile(lo, hi, np.zeros(len(lo)), np.zeros(len(lo)))
        xa = rng.uniform(0.0, 0.8)
        xb = xa + rng.uniform(0.0, 0.3)
        x0, x1 = xa - 0.3, xb + 0.3
        gap = float(rng.choice([0.0, 0.02, 0.15]))
        a = unseen_distance(xa, xb, prof, x0, x1, gap)
        b = K._unseen_distance(xa, xb, lo, hi, x0, x1, gap)
        assert a == b or abs(a - b) <= TOL_M


def test_fused_warm_up_loads_the_kernels_a_fused_monitor_calls() -> None:
    """``warm_up(fused=True)`` (what a fused monitor runs at construction) loads the kernels
    the monitor calls frame by frame (the edge re-scan too: foot contacts call it) and
    leaves the single-operation kernels, which it reaches only on rare branches, to their
    first call (checked in a fresh interpreter: here other tests have loaded them
    already)."""
    _compiled()
    import json
    import subprocess
    import sys

    probe = (
        "import json; from vio_graph.safety import compiled as c; c.warm_up(fused=True); "
        "print(json.dumps({n: bool(getattr(c, n).signatures) for n in dir(c) "
        "if hasattr(getattr(c, n), 'signatures')}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=600
    )
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    for name in (
        "keyframe_step", "frame_terrain", "swing_prediction", "cv_prediction",
        "swing_edge_risk", "_foot_clearance", "window_bins", "window_bridged_gap",
        "observe_errors", "template_motion", "contact_caps", "edge_summary",
        "rescan_edges",  # (a standing foot's contact lowering map bins)
    ):  # fmt: skip
        assert loaded[name], name
    for name in ("consistency_squares", "add_tops", "keyframe_tops", "_coverage"):
        assert not loaded[name], name


class _PaddedMap(IncrementalHeightMap):
    """The map with the arrays grown as before the growable buffers: every array padded by
    the metre it needs (a copy of all of them each time)."""

    def _grow(self, i_min: int, i_max: int) -> None:
        n = self._n.shape[0]
        if n == 0:
            self._i0 = i_min - int(np.ceil(1.0 / self.bin_m))
        if n and self._i0 <= i_min and i_max < self._i0 + n:
            return
        margin = int(np.ceil(1.0 / self.bin_m))
        lo = self._i0 if i_min >= self._i0 else i_min - margin
        hi = self._i0 + n if i_max < self._i0 + n else i_max + 1 + margin
        pad_l, pad_r = self._i0 - lo, hi - (self._i0 + n)
        self._z = np.pad(self._z, ((pad_l, pad_r), (0, 0)), constant_values=np.nan)
        self._zs = np.pad(self._zs, ((pad_l, pad_r), (0, 0)), constant_values=np.nan)
        self._u = np.pad(self._u, ((pad_l, pad_r), (0, 0)), constant_values=np.inf)
        self._n = np.pad(self._n, (pad_l, pad_r))
        self._used = np.pad(self._used, (pad_l, pad_r))
        self._mid = np.pad(self._mid, (pad_l, pad_r))
        self._se2 = np.pad(self._se2, (pad_l, pad_r))
        self._cov = np.pad(self._cov, ((pad_l, pad_r), (0, 0)))
        self._cap = np.pad(self._cap, (pad_l, pad_r), constant_values=np.inf)
        self._i0 = lo


@pytest.mark.parametrize("compiled", [False, True])
def test_height_map_growth_keeps_the_padded_maps_arrays(compiled: bool) -> None:
    """Keyframes walking 24 m up repeated noisy stairs, then back past the start (the map
    grows ~25 times at its right end, then at its left), with foot contacts: after every
    keyframe and contact the bin arrays (heights, sorted heights, ceilings, counts, use,
    statistic, errors, covariances, caps), their first bin and the edges are those of the
    map that pads every array by a metre at a time, bit for bit, while the buffers behind
    them were allocated only a few times (capacity grown by half the map)."""
    kernels = _compiled() if compiled else None
    rng = np.random.default_rng(5)
    flights = [_noisy_stairs(rng) for _ in range(3)]
    x_off, parts = 0.0, []
    for s in flights:  # one long polyline: the flights one after the other
        s = s[1:] - [s[1, 0], 0.0]
        parts.append(s + [x_off, 0.0])
        x_off += s[-1, 0] + 0.05
    stairs = np.vstack([[[-6.0, 0.0]], *parts, [[x_off + 30.0, 0.0]]])
    kw = {"agree_keyframes": 2, "agree_m": 0.004, "kernels": kernels}
    new, old = IncrementalHeightMap(0.005, 3, **kw), _PaddedMap(0.005, 3, **kw)
    allocations, grows, last_len = set(), 0, 0
    xs = [*np.arange(0.0, 24.0, 0.08), *np.arange(24.0, -4.0, -0.5)]
    for x0 in xs:
        P = np.diag(rng.uniform(1e-6, 1e-4, 2))
        prof = _keyframe_profile(rng, stairs, float(x0))
        changed = [m.add_keyframe([x0, 0.5], prof, P) for m in (new, old)]
        assert changed[0] == changed[1]
        if rng.random() < 0.5:
            hx = float(x0 + rng.uniform(0.0, 1.0))
            hz = float(np.interp(hx, stairs[:, 0] + 1e-9 * np.arange(len(stairs)), stairs[:, 1]))
            heel = np.array([hx, hz + rng.normal(0.0, 0.003)])
            toe = heel + [0.25, rng.normal(0.0, 0.01)]
            assert new.add_contact(heel, toe, 0.006, 0.04) == old.add_contact(
                heel, toe, 0.006, 0.04
            )
        assert new._i0 == old._i0
        for name, _ in IncrementalHeightMap._ARRAYS:
            a, b = getattr(new, name), getattr(old, name)
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b, err_msg=name)
            assert a.base is new._buf[[n for n, _ in new._ARRAYS].index(name)]
        np.testing.assert_array_equal(new.edges().xz_m, old.edges().xz_m)
        np.testing.assert_array_equal(new.edges().rise_m, old.edges().rise_m)
        allocations.add(id(new._buf[0]))
        grows += new._n.shape[0] != last_len
        last_len = new._n.shape[0]
    assert new._n.shape[0] > 5000  # ~29 m of 5 mm bins
    assert grows >= 20  # the map grew a metre or so at a time
    assert len(allocations) <= 10  # the buffers grew by half, not one copy a metre
    assert len(new.edges()) >= 30  # the flights' edges were found


@pytest.mark.parametrize("motion_model", ["swing_template", "constant_velocity"])
@pytest.mark.parametrize("compiled", [False, True])
def test_monitor_without_the_predicted_clearance_keeps_every_other_output(
    sample_frames, motion_model: str, compiled: bool
) -> None:
    """The metrics' replays (``predict_clearance=False``) give every output of every frame
    of data/sample as the full monitor, to the bit, but ``predicted_min_clearance_m``,
    which they leave NaN."""
    if compiled:
        _compiled()
    cfg = load_config(None).safety.model_copy(update={"motion_model": motion_model})
    full = np.array(_replay(sample_frames, cfg, compiled=compiled))
    lean = np.array(_replay(sample_frames, cfg, compiled=compiled, predict_clearance=False))
    names = [f.name for f in fields(SafetyEstimate)]
    first = SafetyMonitor(cfg).update(*sample_frames[0])
    # the column of predicted_min_clearance_m in _as_row
    k = sum(np.size(getattr(first, n)) for n in names[: names.index("predicted_min_clearance_m")])
    assert np.isfinite(full[:, k]).sum() > 50  # the full monitor predicted clearances
    assert np.isnan(lean[:, k]).all()
    np.testing.assert_array_equal(np.delete(lean, k, axis=1), np.delete(full, k, axis=1))
    assert np.isfinite(np.delete(full, k, axis=1)[:, 0]).sum() > 50
