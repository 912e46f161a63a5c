"""The foot-to-terrain safety table of docs/results.md from `vio-graph run` results folders.

Reads ``metrics.json`` (keys ``clearance.<mode>``, ``placement.<mode>``, ``latency_ms.safety``)
of every results folder under the given directories and prints one markdown row per trial
and mode, then the pooled numbers per scenario (median of the per-trial medians, max of the
p95s, sums of near-trip events and warnings, minimum lead).

    python benchmarks/safety_table.py results/safety [--mode filter]

With ``--peer`` it prints instead the ATE (cm, first pose anchored) of the filter beside the
GTSAM legged peer (``--mode filter,gtsam_legged`` runs) and the IMU-only baseline.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any


def _f(x: Any, digits: int = 1) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "—"
    return f"{x:.{digits}f}"


def rows_for(root: Path, mode: str) -> list[dict[str, Any]]:
    rows = []
    for m_path in sorted(root.rglob("metrics.json")):
        m = json.loads(m_path.read_text())
        c = m.get("clearance", {}).get(mode)
        if c is None:
            continue
        p = m["placement"][mode]
        rows.append(
            {
                "scenario": m["scenario"],
                "seed": m["seed"],
                "err_med": c["error_mm"]["median"],
                "err_p95": c["error_mm"]["p95"],
                "w1": c.get("within_1sigma"),
                "w2": c.get("within_2sigma"),
                "cov": c["coverage"],
                "events": c["near_trip"]["events"],
                "warnings": c["near_trip"]["warnings"],
                "prec": c["near_trip"]["precision"],
                "rec": c["near_trip"]["recall"],
                "lead": c["near_trip"]["min_lead_ms"],
                "pl_med": p["error_mm"]["median"],
                "landings": p["landings"],
                "lat": m["latency_ms"]["safety"]["median"],
            }
        )
    return rows


def markdown(rows: list[dict[str, Any]], mode: str) -> str:
    head = (
        "| scenario | seed | clearance error median / p95 (mm) | within 1 / 2 sigma | "
        "frames with an estimate | true near-trips | warnings | precision | recall | "
        "min lead (ms) | placement error median (mm), landings | safety ms/frame |"
    )
    lines = [f"Mode `{mode}`.", "", head, "|" + "---|" * 12]
    for r in rows:
        w = "—" if r["w1"] is None else f"{_f(r['w1'], 2)} / {_f(r['w2'], 2)}"
        lines.append(
            f"| {r['scenario']} | {r['seed']} | {_f(r['err_med'])} / {_f(r['err_p95'])} | {w} "
            f"| {_f(r['cov'], 2)} | {r['events']} | {r['warnings']} | {_f(r['prec'], 2)} | "
            f"{_f(r['rec'], 2)} | {_f(r['lead'], 0)} | {_f(r['pl_med'])}, {r['landings']} | "
            f"{_f(r['lat'], 2)} |"
        )
    return "\n".join(lines)


def peer_markdown(roots: list[Path]) -> str:
    """ATE table: filter vs gtsam_legged vs imu_only, toe and camera x / z (cm)."""
    lines = [
        "| scenario | seed | filter toe x / z | gtsam_legged toe x / z | gtsam_legged camera "
        "x / z | imu_only toe x / z | gtsam_legged ms per IMU sample (median) |",
        "|" + "---|" * 7,
    ]
    found = []
    for root in roots:
        for m_path in sorted(root.rglob("metrics.json")):
            m = json.loads(m_path.read_text())
            if "gtsam_legged" in m.get("ate_cm", {}):
                found.append(m)
    found.sort(key=lambda m: (m["scenario"], m["seed"]))
    for m in found:
        a = m["ate_cm"]

        def xz(mode: str, body: str, a: dict = a) -> str:
            return f"{_f(a[mode][body]['x'], 2)} / {_f(a[mode][body]['z'], 2)}"

        lat = m.get("latency_ms", {}).get("gtsam_legged", {}).get("median")
        lines.append(
            f"| {m['scenario']} | {m['seed']} | {xz('filter', 'toe')} | "
            f"{xz('gtsam_legged', 'toe')} | {xz('gtsam_legged', 'camera')} | "
            f"{xz('imu_only', 'toe')} | {_f(lat, 2)} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+", type=Path, help="folders holding results folders")
    ap.add_argument("--mode", default="filter", help="filter, smoother or batch")
    ap.add_argument("--peer", action="store_true", help="the ATE table of the GTSAM peer")
    args = ap.parse_args()
    if args.peer:
        print(peer_markdown(args.roots))
        return
    rows = [r for root in args.roots for r in rows_for(root, args.mode)]
    rows.sort(key=lambda r: (r["scenario"], r["seed"]))
    print(markdown(rows, args.mode))


if __name__ == "__main__":
    main()
