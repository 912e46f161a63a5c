"""Accuracy of one run against ground truth: ATE / APE / RPE per mode and body, the shank
pitch, the terrain class. Pure functions on arrays and ground-truth tables (no I/O); the
replay (``vio_graph.pipeline``) calls them and writes the results into metrics.json."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.evaluation.association import associate
from vio_graph.evaluation.metrics import ape, ate_per_axis, rpe
from vio_graph.recording.streams import GroundTruth, Trajectory


def ate_key(metrics: dict[str, Any]) -> str:
    """The ATE a run reports (the paper's choice): over the frames with the obstacle in view
    for obstacle trials (``ate_cm_visible``), over all frames otherwise (``ate_cm``)."""
    return "ate_cm_visible" if metrics.get("terrain") == "obstacle" else "ate_cm"


def shank_pitch_error_deg(
    groundtruth: GroundTruth, t_s: NDArray[np.float64], shank_pitch_rad: NDArray[np.float64]
) -> dict[str, float]:
    """Error (deg) of the shank pitch the kinematics used, against the pitch of the true
    knee - ankle segment (ground truth at the frame times ``t_s``, s): rms, mean, max |error|."""
    gt = groundtruth.trajectories
    t = np.asarray(t_s, dtype=float)
    seg = gt["knee"].xz_at(t) - gt["ankle"].xz_at(t)  # (N, 2)
    true = np.arctan2(seg[:, 0], seg[:, 1])  # rot_y(pitch) (0, L) = (L sin, L cos)
    err = np.degrees(np.angle(np.exp(1j * (np.asarray(shank_pitch_rad) - true))))
    return {
        "rms": float(np.sqrt(np.mean(err**2))),
        "mean": float(np.mean(err)),
        "max_abs": float(np.max(np.abs(err))),
    }


def evaluate_paths(
    groundtruth: GroundTruth,
    t_s: NDArray[np.float64],
    paths: dict[str, dict[str, NDArray[np.float64]]],
    visible: NDArray[np.bool_] | None,
) -> dict[str, Any]:
    """ATE (paper: first pose anchored, RMSE per axis; also over the frames with an edge in
    view when ``visible`` is given), translation-aligned APE and RPE per mode and body, in cm.
    ``paths[mode][body]`` is (N, 2) x-z in metres at the frame times ``t_s``.

    ``ate_cm_rig``: the same RMSE with one translation for the whole rig, the camera's
    first-sample offset, instead of each body's own (only with a camera path). The paper's
    anchor moves a body's whole path by its first sample's error, so the first frame's
    leg-chain error (the encoders and the shank pitch at that instant) becomes an offset of
    every toe sample; under the rig anchor it stays an error of that frame."""
    out: dict[str, Any] = {
        "ate_cm": {},
        "ate_cm_rig": {},
        "ate_cm_visible": {},
        "ape_se3_cm": {},
        "rpe_cm": {"0.1s": {}, "1.0s": {}},
    }
    # every mode shares the frame times, so a body's association with the ground truth (which
    # frames have truth on both sides, the truth interpolated there, the visible mask) is
    # the same for every mode: made once per body, the modes only pick their kept rows
    shared: dict[str, tuple[Any, NDArray[np.bool_] | None]] = {}

    def association(body: str, est: Trajectory) -> tuple[Any, NDArray[np.bool_] | None]:
        if body not in shared:
            pair = associate(est, groundtruth.trajectories[body], max_diff_s=0.02)
            keep_visible = None
            if visible is not None:
                t_kept = pair.est.timestamp_s
                keep_visible = np.interp(t_kept, t_s, visible.astype(float)) > 0.5
            shared[body] = (pair, keep_visible)
        return shared[body]

    for mode, bodies in paths.items():
        for key in out:
            (out[key] if key != "rpe_cm" else out[key]["0.1s"]).setdefault(mode, {})
        out["rpe_cm"]["1.0s"].setdefault(mode, {})
        trajs = {body: Trajectory.from_xz(t_s, xz) for body, xz in bodies.items()}
        rig_shift_m = None  # the camera's first-sample offset (truth - estimate), m
        if "camera" in trajs:
            cam_pair, _ = association("camera", trajs["camera"])
            if len(cam_pair.est_indices):
                first = trajs["camera"].position_m[cam_pair.est_indices[0]]
                rig_shift_m = cam_pair.ref.position_m[0] - first
        for body, est in trajs.items():
            pair, keep = association(body, est)
            rows = pair.est_indices
            e = Trajectory(  # what associate() keeps of this mode's estimate
                pair.est.timestamp_s.copy(), est.position_m[rows], est.quat_wxyz[rows]
            )
            r = pair.ref
            a = ate_per_axis(e, r, anchor="first")
            out["ate_cm"][mode][body] = {
                "x": a.rmse_x_cm,
                "z": a.rmse_z_cm,
                "total": a.rmse_total_cm,
            }
            if rig_shift_m is not None:
                moved = Trajectory(e.timestamp_s, e.position_m + rig_shift_m, e.quat_wxyz)
                ar = ate_per_axis(moved, r, anchor="none")
                out["ate_cm_rig"][mode][body] = {
                    "x": ar.rmse_x_cm,
                    "z": ar.rmse_z_cm,
                    "total": ar.rmse_total_cm,
                }
            if keep is not None and keep.any():
                av = ate_per_axis(e, r, anchor="first", mask=keep)
                out["ate_cm_visible"][mode][body] = {
                    "x": av.rmse_x_cm,
                    "z": av.rmse_z_cm,
                    "total": av.rmse_total_cm,
                    "fraction": float(keep.mean()),
                }
            ap = ape(e, r, alignment="translation")
            out["ape_se3_cm"][mode][body] = {"x": 100 * ap.rmse_x_m, "z": 100 * ap.rmse_z_m}
            for d in ("0.1s", "1.0s"):
                rp = rpe(e, r, delta_s=float(d[:-1]))
                out["rpe_cm"][d][mode][body] = 100 * rp.stats.rmse
    out["ape_translation_aligned_cm"] = out.pop("ape_se3_cm")
    return out


def terrain_accuracy(
    true_kind: str, predicted: list[str], frame_edge_visible: NDArray[np.int8] | None
) -> dict[str, Any]:
    """Share of frames whose terrain class is the recording's terrain kind, among the frames
    that saw a terrain edge (ground truth; level ground has no edge: every frame counts)."""
    pred = np.asarray(predicted)
    vis = frame_edge_visible
    mask = vis[: len(pred)].astype(bool) if vis is not None else np.ones(len(pred), bool)
    if true_kind == "level" or not mask.any():
        mask = np.ones(len(pred), bool)
    return {
        "truth": true_kind,
        "accuracy_visible": float(np.mean(pred[mask] == true_kind)) if mask.any() else float("nan"),
        "predicted_counts_visible": {
            str(k): int(c)
            for k, c in zip(
                *np.unique(np.asarray(pred[mask], dtype=str), return_counts=True), strict=True
            )
        },
    }
