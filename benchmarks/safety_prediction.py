"""How well the safety monitor predicts the swing's minimum clearance to the next edge, per
motion model and horizon, against the simulator's truth (docs/results.md, "Foot-to-terrain
safety outputs").

The filter is replayed once on each recording; then the safety monitor
(vio_graph/safety/online.py) is re-run on the filter's estimate with each motion model
(``constant_velocity``, ``swing_template``) and horizon (0.1, 0.2, 0.3 s). Scores:

- prediction error: at every swing frame (no stance anchor) whose mapped next edge is the
  true next edge (within 3 cm in x), |predicted minimum clearance to the edges ahead over
  [t, t + horizon] - the true foot's minimum clearance to the true edges it reaches over the
  same interval| (mm, median and p95; a swing over two steps passes two nosings);
- motion-model error: the same, but against the estimated foot's own clearance over the
  next frames to the edges the monitor had mapped (the map's and the pose's errors taken
  out);
- near-trip warnings against the true near-trips (``near_trip_scores``: precision, recall,
  shortest lead);
- possible lead: for each true near-trip, the time from the lift-off our stance detector saw
  (the last anchored frame before the event) to the event's minimum: the earliest a model
  that waits for the swing to start can know it (ms).

    python benchmarks/safety_prediction.py data/recordings/upstair_near_trip_s1 [more ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import _common  # pins BLAS threads before numpy
import numpy as np

from vio_graph.config import load_config
from vio_graph.evaluation.safety import near_trip_scores, true_safety
from vio_graph.recording.reader import Recording
from vio_graph.safety.clearance import Edges, edge_clearance_many, next_edge_index
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyMonitor

MODELS = ("constant_velocity", "swing_template")
HORIZONS_S = (0.1, 0.2, 0.3)
EDGE_MATCH_M = 0.03  # a mapped edge within this x of the true next edge is that edge


def _min_to_edges(
    heel: np.ndarray, toe: np.ndarray, edges_xz: np.ndarray, toe_x_now: float, sc: SafetyConfig
) -> float:
    """Minimum over the foot poses (T, 2) of the clearance to the edges ahead of the toe
    (x from ``toe_x_now`` - toe_pass_m to the farthest toe x + toe_pass_m), m."""
    x = edges_xz[:, 0]
    sel = (x > toe_x_now - sc.toe_pass_m) & (x <= float(toe[:, 0].max()) + sc.toe_pass_m)
    if not sel.any():
        sel = x > toe_x_now - sc.toe_pass_m
        sel &= np.cumsum(sel) == 1  # the next edge only
    d = [np.min(edge_clearance_many(heel, toe, ee, sc.sole_thickness_m)) for ee in edges_xz[sel]]
    return float(min(d)) if d else float("nan")


def one_recording(path: Path, config_name: str | None) -> list[dict]:
    cfg = load_config(config_name)
    rec = Recording.open(path)
    if rec.groundtruth is None:
        raise SystemExit(f"{path}: no ground truth (a simulated recording is needed)")
    lg, est = _common.filter_leg_run(rec, cfg)
    t = np.asarray(lg.t_s)
    stance = np.asarray(lg.in_stance, bool)
    landing = np.r_[stance[:1], stance[1:] & ~stance[:-1]]
    truth = true_safety(rec.groundtruth, rec.metadata.terrain, t, landing, cfg.safety)
    if truth is None:
        raise SystemExit(f"{path}: no true terrain profile / heel / toe")
    gt = rec.groundtruth.trajectories
    edges = np.asarray(sorted(rec.metadata.terrain.edges_xz_m), float).reshape(-1, 2)
    ed = Edges(edges, np.zeros(len(edges)))
    # possible lead: the last anchored frame before each true near-trip's minimum
    td, near, nos = truth["t_dense_s"], truth["near_trip"], truth["nosing_dense_m"]
    leads_possible = []
    m = np.r_[False, near, False].astype(np.int8)
    starts, ends = np.flatnonzero(np.diff(m) == 1), np.flatnonzero(np.diff(m) == -1) - 1
    for a, b in zip(starts, ends, strict=True):
        t_min = td[a + int(np.argmin(nos[a : b + 1]))]
        before = np.flatnonzero(stance & (t <= t_min))
        if before.size:
            leads_possible.append((t_min - t[before[-1]]) * 1e3)
    rows = []
    for model in MODELS:
        for H in HORIZONS_S:
            sc = SafetyConfig(**{**cfg.safety.model_dump(), "motion_model": model, "horizon_s": H})
            mon = SafetyMonitor(sc)
            out, mapped = [], []
            for k in range(len(t)):
                out.append(_common.monitor_update(mon, lg, est, k, stance))
                mapped.append(mon.edges.xz_m)  # the edges the monitor knew at frame k
            pred = np.array([s.predicted_min_nosing_clearance_m for s in out])
            edge_x = np.array([s.edge_distance_m for s in out]) + est["toe"][:, 0]
            err, own = [], []
            for k in np.flatnonzero(~stance & np.isfinite(pred)):
                toe_now = gt["toe"].xz_at(np.array([t[k]]))[0]
                e = next_edge_index(ed, float(toe_now[0]) - sc.toe_pass_m)
                if e < 0 or abs(edges[e, 0] - edge_x[k]) > EDGE_MATCH_M:
                    continue  # the map's next edge is not the true one (not mapped yet)
                tt = np.linspace(t[k], t[k] + H, 31)
                err.append(
                    abs(
                        pred[k]
                        - _min_to_edges(
                            gt["heel"].xz_at(tt), gt["toe"].xz_at(tt), edges, toe_now[0], sc
                        )
                    )
                    * 1e3
                )
                # the motion model alone: against the estimated foot's own future clearance
                # to the edges the monitor had mapped (the map's and the pose's errors out)
                fut = (t >= t[k]) & (t <= t[k] + H + 1e-9)
                own.append(
                    abs(
                        pred[k]
                        - _min_to_edges(
                            est["heel"][fut], est["toe"][fut], mapped[k], est["toe"][k, 0], sc
                        )
                    )
                    * 1e3
                )
            own_a = np.asarray(own)
            warn = np.array([bool(s.near_trip_warning) for s in out])
            nt = near_trip_scores(t, warn, td, near, nos)
            err_a = np.asarray(err)
            rows.append(
                {
                    "recording": path.name,
                    "model": model,
                    "horizon_ms": int(round(H * 1e3)),
                    "frames": int(err_a.size),
                    "err_med": float(np.median(err_a)) if err_a.size else float("nan"),
                    "err_p95": float(np.percentile(err_a, 95)) if err_a.size else float("nan"),
                    "own_med": float(np.median(own_a)) if own_a.size else float("nan"),
                    "own_p95": float(np.percentile(own_a, 95)) if own_a.size else float("nan"),
                    **nt,
                    "possible_lead_ms": leads_possible,
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+", type=Path, help="simulated recording folders")
    ap.add_argument("--config", default=None, help="pipeline config (default: default.yaml)")
    args = ap.parse_args()
    print(
        "| recording | model | horizon (ms) | swing frames | error vs truth median / p95 "
        "(mm) | motion-model error median / p95 (mm) | true near-trips | warnings | "
        "precision | recall | min lead (ms) | lift-off to minimum (ms) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for path in args.recordings:
        for r in one_recording(path, args.config):
            lead = ", ".join(f"{x:.0f}" for x in r["possible_lead_ms"]) or "—"

            def f(x: float, d: int = 2) -> str:
                return "—" if not np.isfinite(x) else f"{x:.{d}f}"

            print(
                f"| {r['recording']} | {r['model']} | {r['horizon_ms']} | {r['frames']} | "
                f"{f(r['err_med'], 1)} / {f(r['err_p95'], 1)} | "
                f"{f(r['own_med'], 1)} / {f(r['own_p95'], 1)} | {r['events']} | "
                f"{r['warnings']} | {f(r['precision'])} | {f(r['recall'])} | "
                f"{f(r['min_lead_ms'], 0)} | {lead} |"
            )


if __name__ == "__main__":
    main()
