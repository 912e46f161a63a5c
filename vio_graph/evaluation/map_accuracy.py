"""Accuracy of a stair / obstacle map against the recording's ground truth terrain: rise,
tread, nosing position, obstacle height and depth (used by the run's evaluation).

Pure module: no file I/O.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.mapping.steps import TerrainGeometry
from vio_graph.recording.metadata import TerrainInfo


def _true_rise_at_edges(terrain: TerrainInfo, edges: NDArray[np.float64]) -> list[float | None]:
    """True rise at each true edge: height difference to the other end of the vertical
    profile segment that starts at the edge (None when the profile does not show one)."""
    profile = np.asarray(terrain.profile_xz_m, dtype=np.float64).reshape(-1, 2)
    rises: list[float | None] = []
    for edge in edges:
        rise: float | None = None
        if profile.shape[0] >= 2:
            i = int(np.argmin(np.linalg.norm(profile - edge, axis=1)))
            if np.linalg.norm(profile[i] - edge) < 1e-6:
                for j in (i - 1, i + 1):
                    if 0 <= j < profile.shape[0] and abs(profile[j, 0] - edge[0]) < 1e-6:
                        rise = float(abs(edge[1] - profile[j, 1]))
        if rise is None and "rise_m" in terrain.params:
            rise = float(terrain.params["rise_m"])
        rises.append(rise)
    return rises


def _match(
    est: NDArray[np.float64], true: NDArray[np.float64], radius_m: float
) -> list[int | None]:
    """Greedy nearest matching of estimated to true points (each true point used once)."""
    if est.shape[0] == 0 or true.shape[0] == 0:
        return [None] * est.shape[0]
    dist = np.linalg.norm(est[:, None, :] - true[None, :, :], axis=2)
    match: list[int | None] = [None] * est.shape[0]
    used: set[int] = set()
    for flat in np.argsort(dist, axis=None):
        i, j = np.unravel_index(flat, dist.shape)
        if dist[i, j] > radius_m:
            break
        if match[i] is None and j not in used:
            match[i] = int(j)
            used.add(int(j))
    return match


def _mm(value: float | None) -> float | None:
    return None if value is None else 1000.0 * float(value)


def _mean_abs(values: list[float | None]) -> float | None:
    vals = [abs(v) for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def compare_to_truth(
    geometry: TerrainGeometry, terrain_info: TerrainInfo, match_radius_m: float = 0.07
) -> dict[str, Any]:
    """Errors of the estimated step / obstacle geometry against the recording's truth.

    Estimated nosings are matched to the true convex edges (``terrain_info.edges_xz_m``,
    greedy nearest, within ``match_radius_m``). Per step: rise error (estimate minus the true
    riser height at the matched edge, from ``profile_xz_m``, else ``params['rise_m']``) and
    tread error (estimate minus the x distance between the true edges matched to this and
    the next nosing, else ``params['tread_m']``). Obstacles: height and depth against
    ``params['height_m']``/``params['depth_m']`` (else from the edges and the lowest profile
    point), edge errors against the matched true edges.

    Returns a JSON-ready dict; lengths in millimetres (keys end in ``_mm``), None where no
    truth is available: ``kind_true``, ``kind_estimated``, ``kind_correct``, ``n_edges_true``,
    ``n_steps_estimated``, ``n_steps_matched``, per-step lists ``rise_error_mm``,
    ``tread_error_mm``, ``nosing_error_mm`` (norm), ``nosing_dx_mm``, ``nosing_dz_mm``,
    ``matched_edge_index``; summaries ``rise_mae_mm``, ``tread_mae_mm``, ``nosing_mae_mm``,
    ``nosing_max_mm``; and ``obstacles``: a list of dicts with ``height_error_mm``,
    ``depth_error_mm``, ``front_edge_error_mm``, ``back_edge_error_mm``.
    """
    true_edges = np.asarray(terrain_info.edges_xz_m, dtype=np.float64).reshape(-1, 2)
    params = terrain_info.params
    true_rises = _true_rise_at_edges(terrain_info, true_edges)
    true_tread = float(params["tread_m"]) if "tread_m" in params else None

    nosings = np.array([s.nosing_xz_m for s in geometry.steps]).reshape(-1, 2)
    match = _match(nosings, true_edges, match_radius_m)
    rise_err: list[float | None] = []
    tread_err: list[float | None] = []
    nosing_err: list[float | None] = []
    nosing_dx: list[float | None] = []
    nosing_dz: list[float | None] = []
    for k, step in enumerate(geometry.steps):
        j = match[k]
        true_rise = true_rises[j] if j is not None else params.get("rise_m")
        rise_err.append(_mm(step.rise_m - float(true_rise)) if true_rise is not None else None)
        if step.tread_m is not None:
            nxt = match[k + 1] if k + 1 < len(match) else None
            if j is not None and nxt is not None:
                truth = float(abs(true_edges[nxt, 0] - true_edges[j, 0]))
            else:
                truth = true_tread
            tread_err.append(_mm(step.tread_m - truth) if truth is not None else None)
        else:
            tread_err.append(None)
        if j is not None:
            d = step.nosing_xz_m - true_edges[j]
            nosing_err.append(_mm(float(np.linalg.norm(d))))
            nosing_dx.append(_mm(float(d[0])))
            nosing_dz.append(_mm(float(d[1])))
        else:
            nosing_err.append(None)
            nosing_dx.append(None)
            nosing_dz.append(None)

    obstacle_reports: list[dict[str, Any]] = []
    profile = np.asarray(terrain_info.profile_xz_m, dtype=np.float64).reshape(-1, 2)
    for ob in geometry.obstacles:
        edges = np.array([ob.front_edge_xz_m, ob.back_edge_xz_m])
        m = _match(edges, true_edges, match_radius_m)
        if "height_m" in params:
            true_h: float | None = float(params["height_m"])
        elif m[0] is not None and profile.shape[0]:
            true_h = float(true_edges[m[0], 1] - profile[:, 1].min())
        else:
            true_h = None
        if "depth_m" in params:
            true_d: float | None = float(params["depth_m"])
        elif m[0] is not None and m[1] is not None:
            true_d = float(true_edges[m[1], 0] - true_edges[m[0], 0])
        else:
            true_d = None
        obstacle_reports.append(
            {
                "height_m": ob.height_m,
                "depth_m": ob.depth_m,
                "height_error_mm": _mm(ob.height_m - true_h) if true_h is not None else None,
                "depth_error_mm": _mm(ob.depth_m - true_d) if true_d is not None else None,
                "front_edge_error_mm": _mm(float(np.linalg.norm(edges[0] - true_edges[m[0]])))
                if m[0] is not None
                else None,
                "back_edge_error_mm": _mm(float(np.linalg.norm(edges[1] - true_edges[m[1]])))
                if m[1] is not None
                else None,
            }
        )

    matched_norms = [v for v in nosing_err if v is not None]
    return {
        "kind_true": terrain_info.kind,
        "kind_estimated": geometry.kind.value,
        "kind_correct": geometry.kind.value == terrain_info.kind,
        "n_edges_true": int(true_edges.shape[0]),
        "n_steps_estimated": len(geometry.steps),
        "n_steps_matched": sum(j is not None for j in match),
        "matched_edge_index": match,
        "rise_error_mm": rise_err,
        "tread_error_mm": tread_err,
        "nosing_error_mm": nosing_err,
        "nosing_dx_mm": nosing_dx,
        "nosing_dz_mm": nosing_dz,
        "rise_mae_mm": _mean_abs(rise_err),
        "tread_mae_mm": _mean_abs(tread_err),
        "nosing_mae_mm": _mean_abs(nosing_err),
        "nosing_max_mm": float(max(matched_norms)) if matched_norms else None,
        "obstacles": obstacle_reports,
    }
