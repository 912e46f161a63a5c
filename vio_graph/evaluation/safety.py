"""Truth and scores of the foot-to-terrain safety outputs (vio_graph/safety/).

The true clearance and placement per frame come from the ground-truth heel and toe
(groundtruth/heel.tum, toe.tum) against the true terrain profile of the recording's metadata
(``terrain.profile_xz_m`` / ``edges_xz_m``), through the same geometry as the estimate
(vio_graph/safety/clearance.py). Scores (metrics.json ``clearance.<mode>``, ``placement.<mode>``):

- ``error_mm``: estimated minus true clearance (median and p95 of |error|, mm), over frames
  where both exist;
- ``within_1sigma`` / ``within_2sigma``: share of those frames with |error| <= 1 / 2 sigma;
  the same split by what the estimate is: ``contact`` (``share`` of the frames reported in
  contact, clearance exactly 0: a clamped or standing foot, whose sigma is the contact's
  bound and whose error is the true foot's distance to the terrain, e.g. a simulated sole
  sunk 0-3 mm into the profile) and ``not_contact`` (the Gaussian estimates), each with
  ``within_1sigma`` / ``within_2sigma``;
- ``pose_consistency_scale`` / ``map_consistency_scale``: median, max and last value over
  the frames of the factors the keyframes' heights put on the sigma's pose and map terms
  (vio_graph/safety/consistency.py; a pose scale above 1: the filter's covariance
  understates its drift);
- ``near_trip``: a true near-trip frame is a swing frame (ankle not still) with the true toe
  moving forward faster than ``warning_min_forward_speed_mps`` and at least as fast as it
  descends, and a true clearance to the next edge (nosing clearance) below ``near_trip_m``
  after the foot was at least ``near_trip_m`` from that edge earlier in the swing
  (:func:`approached`: lifting off the nosing the foot stood on is not a near-trip);
  consecutive such frames are one event, at its minimum. A warning run
  (consecutive warning frames) is a true positive if it overlaps an event or precedes it by
  at most ``MAX_LEAD_S``; ``precision`` = true-positive warning runs / warning runs,
  ``recall`` = events warned at or before their minimum / events, ``min_lead_ms`` = the
  shortest time from the first warning to the event's minimum over warned events;
- placement ``error_mm``: per landing frame, |estimated - true| heel-to-nosing and
  toe-to-nosing distances (median over the known ones, mm).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.evaluation.diagnostics import true_stance
from vio_graph.recording.metadata import TerrainInfo
from vio_graph.recording.streams import GroundTruth
from vio_graph.safety import clearance
from vio_graph.safety.clearance import (
    Edges,
    HeightProfile,
    Placement,
    edge_clearance_rows,
    next_edge_indices,
    placement_on_tread,
)
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyEstimate, SafetyLog, SafetyMonitor, compiled_kernels

MAX_LEAD_S = 1.0  # a warning up to this long before a near-trip's minimum counts for it
TRUTH_STEP_S = 0.002  # time step of the true near-trip search (the truth is interpolated)


def true_safety(
    gt: GroundTruth,
    terrain: TerrainInfo,
    t_s: NDArray[np.float64],
    landing: NDArray[np.bool_],
    config: SafetyConfig,
) -> dict[str, NDArray] | None:
    """Per frame: true clearance and nosing clearance (m) and the true placement (N, 4) at
    the ``landing`` frames (NaN elsewhere); on a dense grid ``t_dense_s`` (TRUTH_STEP_S): the
    true nosing clearance and near-trip flag. None without a true profile
    or true heel / toe."""
    if len(terrain.profile_xz_m) < 2 or not {"heel", "toe", "ankle"} <= set(gt.trajectories):
        return None
    t = np.asarray(t_s, dtype=float)
    heel = gt.trajectories["heel"].xz_at(t)
    toe = gt.trajectories["toe"].xz_at(t)
    prof = HeightProfile.from_polyline(terrain.profile_xz_m)
    edges = np.asarray(sorted(terrain.edges_xz_m), float).reshape(-1, 2)
    ed = Edges(edges, np.zeros(len(edges)))
    n = len(t)
    clear = np.full(n, np.nan)
    placement = np.full((n, 4), np.nan)
    w = config.window_m
    # the compiled foot geometry when the run uses the compiled kernels (the same distances
    # bit for bit, ~5x faster a frame: a 10-minute trial has 18,000 frames), else numpy
    geometry = compiled_kernels() or clearance
    for k in range(n):  # the foot against the terrain near it: per frame
        h, o = heel[k], toe[k]
        win = prof.window(min(h[0], o[0]) - w, max(h[0], o[0]) + w)
        clear[k] = geometry.foot_clearance(h, o, win, config.sole_thickness_m).distance_m
        if landing[k]:
            placement[k] = placement_on_tread(
                h, o, win, config.tread_tolerance_m, config.edge_max_gap_m, config.edge_min_rise_m
            ).as_array()
    nosing = _nosing_clearance(heel, toe, ed, config)[1]
    # near-trips on a dense time grid: the minimum over a nosing falls between frames
    td = np.arange(t[0], t[-1], TRUTH_STEP_S) if n > 1 else t.copy()
    heel_d, toe_d = gt.trajectories["heel"].xz_at(td), gt.trajectories["toe"].xz_at(td)
    edge_d, nos_d = _nosing_clearance(heel_d, toe_d, ed, config)
    dt = 0.01
    toe_traj = gt.trajectories["toe"]
    v_toe = (toe_traj.xz_at(td + dt) - toe_traj.xz_at(td - dt)) / (2 * dt)
    swing = ~true_stance(gt.trajectories["ankle"], td)
    forward = (v_toe[:, 0] > config.warning_min_forward_speed_mps) & (v_toe[:, 1] > -v_toe[:, 0])
    approach = approached(swing, edge_d, nos_d, config.near_trip_m)
    near = swing & forward & approach & (nos_d < config.near_trip_m)
    return {
        "clearance_m": clear,
        "nosing_clearance_m": nosing,
        "placement": placement,
        "t_dense_s": td,
        "near_trip": near,
        "nosing_dense_m": nos_d,
    }


def _nosing_clearance(
    heel_xz_m: NDArray[np.float64],
    toe_xz_m: NDArray[np.float64],
    edges: Edges,
    config: SafetyConfig,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Per foot pose (heel, toe (T, 2)): the index of the next edge ahead of the toe (-1:
    none) and the clearance to it (m, NaN without one), all poses at once."""
    e = next_edge_indices(edges, toe_xz_m[:, 0] - config.toe_pass_m)
    out = np.full(len(e), np.nan)
    has = e >= 0
    out[has] = edge_clearance_rows(
        heel_xz_m[has], toe_xz_m[has], edges.xz_m[e[has]], config.sole_thickness_m
    )
    return e, out


def approached(
    swing: NDArray[np.bool_],
    edge_index: NDArray[np.int64],
    clearance_m: NDArray[np.float64],
    near_trip_m: float,
) -> NDArray[np.bool_]:
    """Per sample: in a swing, the foot has been at least ``near_trip_m`` from this sample's
    next edge (``edge_index``) at an earlier sample of the same swing. A near-trip is the
    foot coming back close to an edge it was clear of; the edge the foot lifts off from (on
    descent the toe rests on the nosing of its own tread and leaves it at forward speed)
    starts at zero clearance and is not one."""
    out = np.zeros(len(swing), bool)
    cleared, prev = False, -2
    # over Python bools, ints and floats (the same values and comparisons; a 10-minute
    # trial's dense grid has 300,000 samples, and numpy scalars cost ~0.1 us each access)
    sw = np.asarray(swing, dtype=bool).tolist()
    edge = np.asarray(edge_index).tolist()
    clear = np.asarray(clearance_m, dtype=float).tolist()
    near = float(near_trip_m)
    flags = [False] * len(sw)
    for k, s in enumerate(sw):
        if not s:
            cleared, prev = False, -2
            continue
        if edge[k] != prev:
            cleared, prev = False, int(edge[k])
        flags[k] = cleared
        if clear[k] >= near:
            cleared = True
    out[:] = flags
    return out


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """(start, end inclusive) of the runs of True."""
    m = np.r_[False, np.asarray(mask, bool), False].astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1, strict=True))


def near_trip_scores(
    t_s: NDArray[np.float64],
    warning: NDArray[np.bool_],
    t_true_s: NDArray[np.float64],
    near_trip: NDArray[np.bool_],
    true_clearance_m: NDArray[np.float64],
) -> dict[str, Any]:
    """Precision / recall of the warning runs (frame times ``t_s``) against the true
    near-trip events (flags and clearance at ``t_true_s``), and the shortest lead (ms) of a
    warned event (see the module docstring)."""
    t = np.asarray(t_s, dtype=float)
    td = np.asarray(t_true_s, dtype=float)
    events = []
    for a, b in _runs(near_trip):
        k = a + int(np.argmin(true_clearance_m[a : b + 1]))
        events.append((td[a], td[b], td[k]))
    warns = [(t[a], t[b]) for a, b in _runs(warning)]
    tp = sum(
        any(ws <= e_end and we >= e_start - MAX_LEAD_S for e_start, e_end, _ in events)
        for ws, we in warns
    )
    leads = []
    for _, _, t_min in events:
        first = [ws for ws, we in warns if ws <= t_min and we >= t_min - MAX_LEAD_S]
        if first:
            leads.append((t_min - min(first)) * 1e3)
    return {
        "events": len(events),
        "warnings": len(warns),
        "precision": tp / len(warns) if warns else float("nan"),
        "recall": len(leads) / len(events) if events else float("nan"),
        "min_lead_ms": float(min(leads)) if leads else float("nan"),
    }


def _mm_stats(err_m: NDArray[np.float64]) -> dict[str, float]:
    e = np.abs(err_m[np.isfinite(err_m)]) * 1e3
    if e.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "n": 0}
    return {"median": float(np.median(e)), "p95": float(np.percentile(e, 95)), "n": int(e.size)}


def score_mode(
    est: list[SafetyEstimate | None] | SafetyLog,
    truth: dict[str, NDArray],
    t_s: NDArray[np.float64],
    with_sigma: bool,
) -> tuple[dict, dict]:
    """(clearance block, placement block) of one mode's per-frame safety estimates."""
    n = len(t_s)

    def col(name: str) -> NDArray[np.float64]:
        if isinstance(est, SafetyLog):  # the replay's compact log: no objects rebuilt
            return est.column(name)
        return np.array([getattr(s, name) if s is not None else np.nan for s in est], float)

    c, sig = col("clearance_m"), col("clearance_sigma_m")
    err = c - truth["clearance_m"][:n]
    ok = np.isfinite(err)
    block: dict[str, Any] = {
        "error_mm": _mm_stats(err),
        "nosing_error_mm": _mm_stats(col("nosing_clearance_m") - truth["nosing_clearance_m"][:n]),
        "coverage": float(ok.mean()) if n else float("nan"),
    }
    if with_sigma:
        ok &= np.isfinite(sig) & (sig > 0)
        z = np.abs(err[ok]) / sig[ok]
        block["within_1sigma"] = float(np.mean(z <= 1)) if z.size else float("nan")
        block["within_2sigma"] = float(np.mean(z <= 2)) if z.size else float("nan")
        contact = c[ok] == 0.0  # reported in contact (the clamp or a standing foot)
        block["contact"] = {"share": float(np.mean(contact)) if z.size else float("nan")}
        for key, m in (("contact", contact), ("not_contact", ~contact)):
            for k in (1, 2):
                block.setdefault(key, {})[f"within_{k}sigma"] = (
                    float(np.mean(z[m] <= k)) if m.any() else float("nan")
                )
        for term in ("pose", "map"):
            sc = col(f"{term}_consistency_scale")
            sc = sc[np.isfinite(sc)]
            block[f"{term}_consistency_scale"] = {
                "median": float(np.median(sc)) if sc.size else float("nan"),
                "max": float(np.max(sc)) if sc.size else float("nan"),
                "last": float(sc[-1]) if sc.size else float("nan"),
            }
    warn = col("near_trip_warning") == 1.0  # False without an estimate (NaN)
    block["near_trip"] = near_trip_scores(
        t_s, warn, truth["t_dense_s"], truth["near_trip"], truth["nosing_dense_m"]
    )
    landing = col("landing") == 1.0
    if isinstance(est, SafetyLog):
        pl_est = est.column("placement")
    else:
        pl_est = np.array([s.placement if s is not None else np.full(4, np.nan) for s in est])
    pl_err = (pl_est - truth["placement"][:n])[landing][:, :2]
    per_landing = [
        float(np.nanmax(np.abs(r)) * 1e3) if np.isfinite(r).any() else None for r in pl_err
    ]
    placement = {
        "error_mm": _mm_stats(pl_err.ravel()),
        "landings": int(landing.sum()),
        "per_landing_mm": per_landing,
    }
    return block, placement


def replay_safety(
    config: SafetyConfig,
    t_s: NDArray[np.float64],
    path: dict[str, NDArray[np.float64]],
    cov_m2: list[NDArray[np.float64]],
    in_stance: list[bool],
    profiles: dict[int, NDArray[np.float64]],
) -> SafetyLog:
    """The safety outputs of another mode's path (camera, heel, toe per frame), with the same
    keyframe profiles placed at that mode's camera positions, frame by frame (causal in the
    profiles; the smoothers' poses themselves may use later data). ``cov_m2``: the filter's.
    ``profiles``: the keyframe profiles at that mode's own keyframe attitude
    (``FrameLog.profiles_of``; the filter's profiles at a smoother's position and the
    filter's pitch are a pose no estimator made, docs/method.md).
    Returned as a :class:`SafetyLog` (one row of floats a frame, read like the list of
    SafetyEstimate or None it stands for), as the online replay keeps its own; its
    ``predicted_min_clearance_m`` is NaN (not computed: :func:`score_mode` does not score
    it, and no other output depends on it)."""
    mon = SafetyMonitor(config, predict_clearance=False)
    out = SafetyLog()
    for k, t in enumerate(t_s):
        out.append(
            mon.update(
                float(t),
                path["camera"][k],
                cov_m2[k],
                path["heel"][k],
                path["toe"][k],
                bool(in_stance[k]),
                profiles.get(k),
            )
        )
    return out


def safety_metrics(
    config: SafetyConfig,
    gt: GroundTruth,
    terrain: TerrainInfo,
    lg,
    paths: dict[str, dict[str, NDArray[np.float64]]],
) -> tuple[dict[str, Any], dict[str, NDArray] | None]:
    """metrics.json ``clearance`` and ``placement`` blocks for the run's modes (filter from
    the online outputs, smoother / batch replayed on their paths) and the per-frame truth."""
    t = np.asarray(lg.t_s, dtype=float)
    landing = lg.safety.column("landing") == 1.0  # False without an estimate (NaN)
    truth = true_safety(gt, terrain, t, landing, config)
    if truth is None or not lg.safety or lg.safety[0] is None:
        return {}, truth
    clearance: dict[str, Any] = {}
    placement: dict[str, Any] = {}
    for mode in ("filter", "smoother", "batch"):
        if mode not in paths:
            continue
        est = (
            lg.safety
            if mode == "filter"
            else replay_safety(  # the profiles at the mode's own attitude
                config, t, paths[mode], lg.cov_position_m2, lg.in_stance, lg.profiles_of(mode)
            )
        )
        clearance[mode], placement[mode] = score_mode(est, truth, t, mode == "filter")
    return {"clearance": clearance, "placement": placement}, truth


__all__ = [
    "Placement",
    "approached",
    "near_trip_scores",
    "replay_safety",
    "safety_metrics",
    "score_mode",
    "true_safety",
]
