"""Depth pixels that move with the camera: an object fixed to the rig, not terrain.

A foot (the other leg) swinging past a shank-mounted camera, a trouser leg or a strap close to
the lens stays at the same pixels and the same depth while the camera moves. In the sagittal
slice such an object is a rounded surface that ICP registers with zero motion, which pulls
the displacement towards zero, and the terrain rules can read it as a step or a floor.

Two hypotheses are tested at every slice pixel p of the current frame, each against the
previous depth image, with the camera motion between the frames that the IMU predicts
(rotation from the attitude, translation from the filter's velocity):

* camera-fixed: the previous frame saw the same depth at the same pixel,
  ``r_fixed = |d_k(p) - d_{k-1}(p)|``;
* world-static: the point ``Q = d_k(p) K^-1 p`` moved into the previous camera frame,
  ``Q' = R_prev_cur Q + t_prev_cur``, is seen there, ``r_world = min |d_{k-1}(p' + e) - Q'_z|``
  over the 3x3 pixels ``e`` around its projection ``p'`` (pixel quantisation on slanted
  surfaces).

A pixel moves with the camera when the first hypothesis holds (``r_fixed`` within the depth
noise) and the second is refused (``r_world`` beyond the noise plus what the predicted motion's
own uncertainty can explain). When the predicted motion is too small to tell the two apart
(stance; a floor under a camera moving parallel to it) both hold and the pixel is kept: the
test only removes what the IMU says cannot be terrain. A pixel once found camera-fixed stays
so while its depth does not change (``r_fixed`` within the noise), so the object is not
re-admitted when the camera pauses.

Both hypotheses use the predicted motion, so a confidently wrong prediction makes terrain that
keeps its depth read as camera-fixed. A surface therefore leaves only if most of its
camera-fixed pixels also show an occlusion onset (:class:`OnsetTracker`): their depth dropped
far below what they saw before, or they were first seen, and has stayed since. That evidence
comes from the depth images alone. Pure functions plus a small per-frame state; no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vio_graph.frontend.icp import compiled_kernels


@dataclass(frozen=True)
class CameraMotion:
    """Camera motion between two frames in the PREVIOUS camera's optical frame:
    ``p_prev = R_prev_cur @ p_cur + t_prev_cur_m``, with the translation's (3, 3)
    covariance in m^2 and the rotation's sd in rad."""

    R_prev_cur: NDArray[np.float64]
    t_prev_cur_m: NDArray[np.float64]
    t_cov_m2: NDArray[np.float64]
    rot_sigma_rad: float = 0.0


def motion_from_ground(
    R_ground_cam_prev: NDArray[np.float64],
    R_ground_cam_cur: NDArray[np.float64],
    delta_xz_m: NDArray[np.float64],
    delta_cov_m2: NDArray[np.float64],
    rot_sigma_rad: float = 0.0,
    motion_share_sigma: float = 0.0,
) -> CameraMotion:
    """The camera motion of :class:`CameraMotion` from the two frames' camera -> ground
    rotations (3, 3) and the predicted camera displacement in ground x-z (m) with its
    (2, 2) covariance (m^2); the ground's lateral axis is y. ``motion_share_sigma``: a
    further sd of the motion as a share of itself (the frame stamps' jitter over the frame
    interval), added to the translation's covariance and the rotation's sd.

    The small steps on Python floats (the (3, 3) covariance written out, the norm as the
    dot product numpy's norm takes, the trace summed in numpy's order, the clip as min /
    max); the three matrix products, the arccos and the hypot stay numpy's: the same floats
    as :func:`motion_from_ground_reference` (tests/test_camera_fixed.py)."""
    Rp = np.asarray(R_ground_cam_prev, dtype=float)
    Rc = np.asarray(R_ground_cam_cur, dtype=float)
    c = np.asarray(delta_cov_m2, dtype=float)
    g = np.array([delta_xz_m[0], 0.0, delta_xz_m[1]], dtype=float)
    extra = (motion_share_sigma * math.sqrt(g.dot(g))) ** 2  # np.linalg.norm's sum
    if c.shape != (2, 2) or not math.isfinite(extra):  # (inf x the eye's zeros: NaN)
        return motion_from_ground_reference(
            Rp, Rc, delta_xz_m, delta_cov_m2, rot_sigma_rad, motion_share_sigma
        )
    (c00, c01), (c10, c11) = c.tolist()
    # np.zeros, the [0, 2] x [0, 2] block, then + eye * extra (+0.0 off the diagonal)
    cov_g = np.array(
        [[c00 + extra, 0.0, c01 + 0.0], [0.0, extra, 0.0], [c10 + 0.0, 0.0, c11 + extra]]
    )
    R = Rp.T @ Rc
    (r00, _, _), (_, r11, _), (_, _, r22) = R.tolist()
    cos_angle = (r00 + r11 + r22 - 1.0) / 2.0  # np.trace's order: (r00 + r11) + r22
    angle = float(np.arccos(min(max(cos_angle, -1.0), 1.0)))
    rot_sigma = float(np.hypot(rot_sigma_rad, motion_share_sigma * angle))
    return CameraMotion(R, Rp.T @ g, Rp.T @ cov_g @ Rp, rot_sigma)


def motion_from_ground_reference(
    R_ground_cam_prev: NDArray[np.float64],
    R_ground_cam_cur: NDArray[np.float64],
    delta_xz_m: NDArray[np.float64],
    delta_cov_m2: NDArray[np.float64],
    rot_sigma_rad: float = 0.0,
    motion_share_sigma: float = 0.0,
) -> CameraMotion:
    """numpy formulation of :func:`motion_from_ground` (the tested reference)."""
    Rp = np.asarray(R_ground_cam_prev, dtype=float)
    Rc = np.asarray(R_ground_cam_cur, dtype=float)
    g = np.array([delta_xz_m[0], 0.0, delta_xz_m[1]], dtype=float)
    cov_g = np.zeros((3, 3))
    cov_g[np.ix_([0, 2], [0, 2])] = np.asarray(delta_cov_m2, dtype=float)
    cov_g += np.eye(3) * (motion_share_sigma * float(np.linalg.norm(g))) ** 2
    R = Rp.T @ Rc
    angle = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    rot_sigma = float(np.hypot(rot_sigma_rad, motion_share_sigma * angle))
    return CameraMotion(R, Rp.T @ g, Rp.T @ cov_g @ Rp, rot_sigma)


def camera_fixed_mask(
    depth_prev_m: NDArray,
    depth_cur_m: NDArray,
    candidates: NDArray[np.bool_],
    K: NDArray[np.float64],
    motion: CameraMotion,
    depth_sigma_m: float,
    k_sigma: float = 3.0,
    held: NDArray[np.bool_] | None = None,
    same_out: NDArray[np.bool_] | None = None,
    stats: dict | None = None,
    view_step_px: int = 4,
    view_share: float = 0.05,
) -> NDArray[np.bool_]:
    """(H, W) mask of the ``candidates`` pixels that move with the camera (module docstring).

    Args:
        depth_prev_m, depth_cur_m: (H, W) depth images, m; 0 (or non-finite) = invalid.
        candidates: (H, W) pixels to test (e.g. the valid pixels of the sagittal slice).
        K: (3, 3) intrinsics, pixels.
        motion: the predicted camera motion between the frames.
        depth_sigma_m: depth noise sd of one pixel, m.
        k_sigma: both tests at this many sigmas.
        held: (H, W) the previous frame's camera-fixed mask; such a pixel stays camera-fixed
            while its depth is unchanged, whatever the motion.
        same_out: (H, W) if given, set to the tested pixels whose depth is unchanged.
        stats: if given, receives the view test's counts ("confirm", "refute").
        view_step_px: the view test uses every this-many-th pixel in both directions.
        view_share: ... or needs this share of its valid pixels confirming the motion.

    Compiled (``compiled.camera_fixed``, numba) when the front end's kernels are on
    (``VIO_GRAPH_COMPILED``, :func:`vio_graph.frontend.icp.compiled_kernels`): one call, no
    whole-image temporaries, the same tests on the same floats as
    :func:`camera_fixed_mask_reference` (the numpy formulation; the projection summed as
    numpy's BLAS sums ``Q @ R.T`` here), so the same masks and counts
    (tests/test_frontend_fastpaths.py).
    """
    kernels = compiled_kernels()
    if kernels is not None:
        out = _camera_fixed_mask_compiled(
            kernels,
            depth_prev_m,
            depth_cur_m,
            candidates,
            K,
            motion,
            depth_sigma_m,
            k_sigma,
            held,
            same_out,
            stats,
            view_step_px,
            view_share,
        )
        if out is not None:
            return out
    return camera_fixed_mask_reference(
        depth_prev_m,
        depth_cur_m,
        candidates,
        K,
        motion,
        depth_sigma_m,
        k_sigma,
        held,
        same_out,
        stats,
        view_step_px,
        view_share,
    )


def _camera_fixed_mask_compiled(
    kernels,
    depth_prev_m: NDArray,
    depth_cur_m: NDArray,
    candidates: NDArray[np.bool_],
    K: NDArray[np.float64],
    motion: CameraMotion,
    depth_sigma_m: float,
    k_sigma: float,
    held: NDArray[np.bool_] | None,
    same_out: NDArray[np.bool_] | None,
    stats: dict | None,
    view_step_px: int,
    view_share: float,
) -> NDArray[np.bool_] | None:
    """:func:`camera_fixed_mask` through the compiled kernel, or None when the inputs do not
    fit it (float32 / float64 (H, W) images, bool masks of the same shape): the numpy path."""
    dp, dc = np.asarray(depth_prev_m), np.asarray(depth_cur_m)
    cand = np.asarray(candidates)
    shape = dc.shape
    if (
        dc.ndim != 2
        or dp.shape != shape
        or cand.shape != shape
        or cand.dtype != np.bool_
        or dp.dtype not in (np.float32, np.float64)
        or dc.dtype not in (np.float32, np.float64)
        or (held is not None and (held.shape != shape or held.dtype != np.bool_))
        or (same_out is not None and (same_out.shape != shape or same_out.dtype != np.bool_))
        or int(view_step_px) < 1
    ):
        return None
    # the scalars of camera_fixed_mask_reference and _world_test, as they compute them
    tol_fixed = k_sigma * np.sqrt(2.0) * depth_sigma_m
    var_t = float(np.asarray(motion.t_cov_m2)[2, 2])
    s_world = 2.0 * depth_sigma_m**2 + var_t
    same = np.zeros(shape, dtype=bool)
    out = np.zeros(shape, dtype=bool)
    ran, n_confirm, n_refute, n_changed = kernels.camera_fixed(
        dp,
        dc,
        cand,
        float(K[0, 0]),
        float(K[1, 1]),
        float(K[0, 2]),
        float(K[1, 2]),
        np.ascontiguousarray(motion.R_prev_cur, dtype=float),
        np.ascontiguousarray(motion.t_prev_cur_m, dtype=float),
        float(s_world),
        float(motion.rot_sigma_rad),
        float(k_sigma),
        float(tol_fixed),
        same if held is None else held,
        held is not None,
        int(view_step_px),
        float(view_share),
        out,
        same,
    )
    if same_out is not None:
        same_out |= same
    if ran and stats is not None:
        stats.update(confirm=int(n_confirm), refute=int(n_refute), changed=int(n_changed))
    return out


def camera_fixed_mask_reference(
    depth_prev_m: NDArray,
    depth_cur_m: NDArray,
    candidates: NDArray[np.bool_],
    K: NDArray[np.float64],
    motion: CameraMotion,
    depth_sigma_m: float,
    k_sigma: float = 3.0,
    held: NDArray[np.bool_] | None = None,
    same_out: NDArray[np.bool_] | None = None,
    stats: dict | None = None,
    view_step_px: int = 4,
    view_share: float = 0.05,
) -> NDArray[np.bool_]:
    """:func:`camera_fixed_mask` in numpy (the tested reference of the compiled kernel)."""

    dp = np.asarray(depth_prev_m, dtype=np.float64)
    dc = np.asarray(depth_cur_m, dtype=np.float64)
    h, w = dc.shape
    out = np.zeros((h, w), dtype=bool)
    prev_ok = np.isfinite(dp) & (dp > 0)
    rows, cols = np.nonzero(candidates & prev_ok & np.isfinite(dc) & (dc > 0))
    if rows.size == 0:
        return out
    z = dc[rows, cols]
    tol_fixed = k_sigma * np.sqrt(2.0) * depth_sigma_m
    same = np.abs(z - dp[rows, cols]) <= tol_fixed
    if same_out is not None:
        same_out[rows[same], cols[same]] = True
    if held is not None:
        keep = same & held[rows, cols]
        out[rows[keep], cols[keep]] = True
    pad = np.full((h + 4, w + 4), np.inf)  # previous depth, 2 invalid (inf) pixels around
    pad[2:-2, 2:-2] = np.where(prev_ok, dp, np.inf)
    pad_cur = np.full((h + 4, w + 4), np.inf)  # the current depth, likewise
    pad_cur[2:-2, 2:-2] = np.where(np.isfinite(dc) & (dc > 0), dc, np.inf)
    # world-static hypothesis at the candidates whose depth did not change
    idx = np.flatnonzero(same)
    if idx.size == 0:
        return out
    r, c = rows[idx], cols[idx]
    seen, world = _world_test(pad, r, c, z[idx], K, motion, depth_sigma_m, k_sigma, pad_cur)
    # a point that would leave the previous view cannot be tested: kept (not seen = unknown)
    fixed = seen & ~world
    if not fixed.any():
        return out
    # the motion the IMU predicts must show in the view: over the whole image (every
    # ``view_step_px``-th pixel), the pixels whose depth changed as that motion says must be
    # at least as many as the unchanged ones it refuses, or ``view_share`` of the view. A
    # camera that stood still while the filter's velocity was wrong changes no depth (noise
    # and depth edges change 0.5-1.2 % of the pixels), and its whole view would otherwise
    # read as moving with the camera; the terrain around an object close to the lens
    # confirms the motion, even where the object covers most of the valid pixels.
    k = view_step_px
    gr, gc = np.nonzero(prev_ok[::k, ::k] & (dc[::k, ::k] > 0))
    gr, gc = gr * k, gc * k
    gz = dc[gr, gc]
    g_same = np.abs(gz - dp[gr, gc]) <= tol_fixed
    g_seen, g_world = _world_test(pad, gr, gc, gz, K, motion, depth_sigma_m, k_sigma, pad_cur)
    n_confirm = int(np.count_nonzero(g_seen & ~g_same & g_world))
    n_refute = int(np.count_nonzero(g_seen & g_same & ~g_world))
    if stats is not None:
        stats.update(
            confirm=n_confirm, refute=n_refute, changed=int(np.count_nonzero(g_seen & ~g_same))
        )
    n_seen = int(np.count_nonzero(g_seen))
    if n_confirm >= n_refute or n_confirm >= view_share * n_seen:
        out[r[fixed], c[fixed]] = True
    return out


def _padded_pixel(
    K: NDArray[np.float64],
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    z: NDArray[np.float64],
    h: int,
    w: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
    """Camera points (x, y, z) (m) projected by ``K`` to the nearest pixel of an h x w image
    padded by 2 pixels: (row, column) in the padded image, clipped to one pixel beyond the
    image, and whether the point is in front of the camera (z > 1 mm) and within that one
    pixel of the image."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    front = z > 1e-3
    u = np.rint(np.where(front, fx * x / np.where(front, z, 1.0) + cx, -10.0)).astype(np.int64)
    v = np.rint(np.where(front, fy * y / np.where(front, z, 1.0) + cy, -10.0)).astype(np.int64)
    inside = (u >= -1) & (u <= w) & (v >= -1) & (v <= h)
    return np.clip(v, -1, h) + 2, np.clip(u, -1, w) + 2, inside


def _nearest_depth_3x3(
    pad: NDArray[np.float64], vi: NDArray[np.int64], ui: NDArray[np.int64], z: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Per point, the smallest |depth - z| (m) over the 3 x 3 pixels of the padded depth
    ``pad`` around (vi, ui); inf where none of them is valid."""
    best = np.full(z.shape, np.inf)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            np.minimum(best, np.abs(pad[vi + dv, ui + du] - z), out=best)
    return best


def _world_test(
    pad: NDArray[np.float64],
    r: NDArray[np.int64],
    c: NDArray[np.int64],
    z: NDArray[np.float64],
    K: NDArray[np.float64],
    motion: CameraMotion,
    depth_sigma_m: float,
    k_sigma: float,
    pad_cur: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """World-static hypothesis at pixels (r, c) of depth z (m): (seen, consistent). The point
    moved into the previous camera frame by ``motion`` is looked up in the previous depth
    (``pad``: padded by 2 invalid (inf) pixels, so the 3 x 3 lookups need no bounds test);
    a projection further out than one pixel, or onto no valid pixel, is not seen.

    Occlusion (with ``pad_cur``, the current depth padded the same way): where every valid
    pixel around the projection is nearer than the moved point by more than the tolerance,
    the previous frame may simply not have seen it, hidden behind a nearer surface (the lower
    tread just past a nosing, revealed as the camera moves). The nearer surface is taken as
    such an occluder when it is itself world-static: its pixel among the 9 closest in depth to
    the moved point, moved into the current frame by the inverse motion, is seen there within
    the same tolerance, or not seen there at all (out of view, no valid pixel). The point is
    then not seen (no evidence either way), instead of refused. An object fixed to the
    camera fails that second test (its own surface, seen again in the current frame, does
    not follow the inverse motion), so it is still refused."""
    h, w = pad.shape[0] - 4, pad.shape[1] - 4
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Q = np.column_stack([z * (c - cx) / fx, z * (r - cy) / fy, z])
    Qp = Q @ np.asarray(motion.R_prev_cur, dtype=float).T + motion.t_prev_cur_m
    zp = Qp[:, 2]
    vi, ui, inside = _padded_pixel(K, Qp[:, 0], Qp[:, 1], zp, h, w)
    best = _nearest_depth_3x3(pad, vi, ui, zp)
    seen = np.isfinite(best) & inside
    # what the predicted motion's own uncertainty can move a point along the optical axis
    var_t = float(np.asarray(motion.t_cov_m2)[2, 2])
    var_rot = (np.linalg.norm(Q[:, :2], axis=1) * motion.rot_sigma_rad) ** 2
    tol_world = k_sigma * np.sqrt(2.0 * depth_sigma_m**2 + var_t + var_rot)
    world = best <= tol_world
    if pad_cur is not None:
        seen &= ~_hidden(pad, pad_cur, seen & ~world, ui, vi, zp, tol_world, K, motion)
    return seen, world


def _hidden(
    pad: NDArray[np.float64],
    pad_cur: NDArray[np.float64],
    refused: NDArray[np.bool_],
    ui: NDArray[np.int64],
    vi: NDArray[np.int64],
    zp: NDArray[np.float64],
    tol: NDArray[np.float64],
    K: NDArray[np.float64],
    motion: CameraMotion,
) -> NDArray[np.bool_]:
    """Of the ``refused`` points (moved into the previous frame at padded pixel (vi, ui),
    depth zp), those hidden there behind a nearer surface that nothing shows to move with the
    camera (:func:`_world_test`): every valid neighbour nearer than ``zp - tol``, and the
    neighbour closest to ``zp`` (first in raster order on ties), moved back into the current
    frame by the inverse motion, not seen there on valid depth further than ``tol`` (m) from
    where it should be."""
    out = np.zeros(zp.shape, dtype=bool)
    j = np.flatnonzero(refused)
    if j.size == 0:
        return out
    offsets = [(dv, du) for dv in (-1, 0, 1) for du in (-1, 0, 1)]
    nb = np.stack([pad[vi[j] + dv, ui[j] + du] for dv, du in offsets], axis=1)
    ok = np.isfinite(nb)
    nearer = np.all(~ok | (nb < (zp[j] - tol[j])[:, None]), axis=1)
    k = np.argmin(np.where(ok, np.abs(nb - zp[j][:, None]), np.inf), axis=1)
    v = nb[np.arange(j.size), k]
    dv = np.array([o[0] for o in offsets])[k]
    du = np.array([o[1] for o in offsets])[k]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u0 = (ui[j] + du - 2).astype(np.float64)
    v0 = (vi[j] + dv - 2).astype(np.float64)
    R = np.asarray(motion.R_prev_cur, dtype=float)
    t = np.asarray(motion.t_prev_cur_m, dtype=float)
    d0 = v * (u0 - cx) / fx - t[0]
    d1 = v * (v0 - cy) / fy - t[1]
    d2 = v - t[2]
    # R^T (P - t), each sum in this order (the compiled kernel sums likewise)
    x = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
    y = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
    zc = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
    h, w = pad.shape[0] - 4, pad.shape[1] - 4
    vci, uci, inside = _padded_pixel(K, x, y, zc, h, w)
    best = _nearest_depth_3x3(pad_cur, vci, uci, zc)
    # the occluder refutes the occlusion only where its own test is decided against it:
    # moved back, it lands on valid current depth that disagrees (an object fixed to the
    # lens does); out of view or on no valid pixel, the occlusion stands unrefuted
    # ... and only if it shows the signature of something fixed to the lens itself: the same
    # depth at the same pixel in the current frame (a mixed pixel between two surfaces, which
    # flickers from frame to frame, or an edge the motion moved, does not)
    here = pad_cur[vi[j] + dv, ui[j] + du]
    fixed_here = np.abs(here - v) <= tol[j]
    refuted = inside & np.isfinite(best) & (best > tol[j]) & fixed_here
    out[j] = ok.any(axis=1) & nearer & ~refuted
    return out


def surface_majority(
    mask: NDArray[np.bool_],
    depth_m: NDArray,
    same: NDArray[np.bool_],
    rel_tol: float,
    abs_tol_m: float,
    min_pixels: int,
    onset: NDArray[np.bool_] | None = None,
    onset_share: float = 0.5,
) -> NDArray[np.bool_]:
    """Decide per surface as well as per pixel. The pixels of ``same`` (depth unchanged since
    the previous frame) are split into surfaces at depth edges (a 4-neighbour differing by
    more than ``rel_tol * depth + abs_tol_m``, the speckle test's agreement). A surface with
    fewer than ``min_pixels`` pixels of ``mask`` is no object (an odd pixel that passed the
    test by chance): none of them is kept. A surface at least half in ``mask`` is camera-fixed
    as a whole (a pixel of the object whose own test was ambiguous, its warped point having
    landed on the object again, goes with its surface); in any other surface only the
    pixels of ``mask`` are. Pixels at a depth edge go with the camera-fixed surface next to
    them (the object's rim). (H, W) bool.

    ``onset`` (H, W), if given: the pixels whose depth has stayed since an occlusion onset
    (:class:`OnsetTracker`); a surface where fewer than ``onset_share`` of its pixels of
    ``mask`` are in ``onset`` keeps none of its pixels, whatever the test said (terrain that
    keeps its depth while a confidently wrong prediction says it should have moved has no
    such onset).

    With the compiled kernels the surfaces are labelled by ``compiled.label4`` and the rim
    dilated by :func:`dilate4` (the same labels and pixels as ``scipy.ndimage``'s ``label``
    and ``binary_dilation``, which a run on the kernels then does not import); the numpy
    path calls scipy."""
    kernels = compiled_kernels()
    d = np.asarray(depth_m, dtype=np.float64)
    tol = rel_tol * d + abs_tol_m
    smooth = same.copy()
    for axis in (0, 1):  # a pixel at a depth edge separates two surfaces
        jump = np.abs(np.diff(d, axis=axis))
        if axis == 0:
            edge = jump > np.minimum(tol[:-1, :], tol[1:, :])
            smooth[:-1, :] &= ~edge
            smooth[1:, :] &= ~edge
        else:
            edge = jump > np.minimum(tol[:, :-1], tol[:, 1:])
            smooth[:, :-1] &= ~edge
            smooth[:, 1:] &= ~edge
    if kernels is not None:
        labels, n = kernels.label4(smooth)
        dilate = dilate4
    else:
        from scipy import ndimage

        labels, n = ndimage.label(smooth)
        dilate = ndimage.binary_dilation
    size = np.bincount(labels.ravel(), minlength=n + 1)
    hits = np.bincount(labels.ravel(), weights=mask.ravel(), minlength=n + 1)
    counts = hits >= min_pixels
    if onset is not None:
        began = np.bincount(labels.ravel(), weights=(mask & onset).ravel(), minlength=n + 1)
        counts &= began >= onset_share * hits
    whole = counts & (hits >= 0.5 * size)
    counts[0] = whole[0] = False
    out = whole[labels] | (counts[labels] & mask)
    rim = same & ~smooth
    if out.any() and rim.any():
        out |= rim & dilate(out)
    return out


def dilate4(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """A pixel or one of its 4 neighbours in ``mask``: ``scipy.ndimage.binary_dilation`` with
    its default structure (the cross), one iteration, nothing beyond the border. (H, W)."""
    out = mask.copy()
    out[1:, :] |= mask[:-1, :]
    out[:-1, :] |= mask[1:, :]
    out[:, 1:] |= mask[:, :-1]
    out[:, :-1] |= mask[:, 1:]
    return out


class OnsetTracker:
    """Per pixel: has the depth stayed where it went at an occlusion onset? Evidence about
    an object in front of the terrain that does not come from the predicted motion.

    An object that enters the view close to the lens covers terrain: at its first frame its
    pixels' depth drops far below what they saw before, and from then on it stays. Terrain
    that keeps its depth while a wrong prediction says it should have moved has no such
    onset: its depth history is the terrain's. Per pixel, against the depth it last saw
    valid (an invalid frame changes nothing, so a ToF gap makes no onset):

    * never valid before (the first frame of the trial, or a pixel that saw nothing): onset
      (a strap in view from the start);
    * nearer by more than ``drop_tols`` x the speckle test's agreement
      (``rel_tol * depth + abs_tol_m`` of the depth before): onset;
    * within ``keep_sigmas`` depth-noise sigmas (of a difference of two pixels): the status is
      kept;
    * any other change: no onset (the depth moved as terrain's does).
    """

    def __init__(
        self, drop_tols: float, rel_tol: float, abs_tol_m: float, keep_sigmas: float
    ) -> None:
        self.drop_tols = float(drop_tols)
        self.rel_tol = float(rel_tol)
        self.abs_tol_m = float(abs_tol_m)
        self.keep_sigmas = float(keep_sigmas)
        self._last: NDArray[np.float64] | None = None  # last valid depth, nan = never valid
        self.onset: NDArray[np.bool_] | None = None
        # counts of the last update: pixels that got an onset in it (a drop or a first valid
        # depth), and pixels with an onset whose depth stayed within ``same_tol_m`` of the
        # last valid one
        self.n_fresh = 0
        self.n_same = 0

    def reset(self) -> None:
        self._last = None
        self.onset = None
        self.n_fresh = self.n_same = 0

    def update(
        self, depth_m: NDArray, depth_sigma_m: float, same_tol_m: float = 0.0
    ) -> NDArray[np.bool_]:
        """The (H, W) onset status after this depth image (0 / non-finite = invalid); the
        returned array is the tracker's own, updated in place by the next call. Also sets
        :attr:`n_fresh` and :attr:`n_same` (``same_tol_m``: m). Compiled
        (``compiled.onset_update``) with the front end's kernels: the same status and counts."""
        d = np.asarray(depth_m)
        if self._last is None or self._last.shape != d.shape:
            valid = np.isfinite(d) & (d > 0)
            self._last = np.where(valid, d, np.nan).astype(np.float64)
            self.onset = valid
            self.n_fresh, self.n_same = int(np.count_nonzero(valid)), 0
            return self.onset
        assert self.onset is not None
        keep_tol = self.keep_sigmas * np.sqrt(2.0) * float(depth_sigma_m)
        kernels = compiled_kernels()
        if kernels is not None and d.ndim == 2 and d.dtype in (np.float32, np.float64):
            n_fresh, n_same = kernels.onset_update(
                d,
                self._last,
                self.onset,
                self.drop_tols,
                self.rel_tol,
                self.abs_tol_m,
                keep_tol,
                float(same_tol_m),
            )
            self.n_fresh, self.n_same = int(n_fresh), int(n_same)
        else:
            self._update_reference(d, keep_tol, float(same_tol_m))
        return self.onset

    def _update_reference(self, depth_m: NDArray, keep_tol_m: float, same_tol_m: float) -> None:
        """:meth:`update` in numpy (the tested reference of the compiled kernel)."""
        assert self._last is not None and self.onset is not None
        d = np.asarray(depth_m, dtype=np.float64)
        valid = np.isfinite(d) & (d > 0)
        last = self._last
        with np.errstate(invalid="ignore"):
            change = d - last
            drop = change < -self.drop_tols * (self.rel_tol * last + self.abs_tol_m)
            kept = np.abs(change) <= keep_tol_m
            same = np.abs(change) <= same_tol_m
        first = np.isnan(last)
        status = first | drop | (kept & self.onset)
        self.n_fresh = int(np.count_nonzero(valid & (first | drop)))
        self.n_same = int(np.count_nonzero(valid & status & same))
        np.copyto(self.onset, status, where=valid)
        np.copyto(self._last, d, where=valid)


class CameraFixedFilter:
    """Per-frame state of :func:`camera_fixed_mask`: the previous depth image, its camera ->
    ground rotation and camera-fixed mask. :meth:`update` returns the current mask."""

    def __init__(
        self,
        k_sigma: float = 3.0,
        edge_rel_tol: float = 0.03,
        edge_abs_tol_m: float = 0.01,
        min_pixels: int = 20,
        onset_drop_tols: float | None = 3.0,
        onset_share: float = 0.5,
        confirm_frames: int = 1,
        skip_unable: bool = True,
    ) -> None:
        self.k_sigma = float(k_sigma)
        # skip the test on frames where it cannot remove a pixel (update); the same masks
        self.skip_unable = bool(skip_unable)
        # a pixel is returned once it has been camera-fixed on this many consecutive tested
        # frames (1: at once); the held state below follows the unconfirmed decision
        self.confirm_frames = int(confirm_frames)
        self._run: NDArray[np.int32] | None = None
        self.onset_share = float(onset_share)
        # with onset_drop_tols, a surface leaves only if most of its pixels kept their depth
        # since an occlusion onset (OnsetTracker); the status survives 2 x k_sigma of noise
        self._onset: OnsetTracker | None = None
        if onset_drop_tols is not None:
            self._onset = OnsetTracker(
                onset_drop_tols, edge_rel_tol, edge_abs_tol_m, 2.0 * float(k_sigma)
            )
        self.min_pixels = int(min_pixels)
        self.edge_rel_tol = float(edge_rel_tol)
        self.edge_abs_tol_m = float(edge_abs_tol_m)
        self._prev: tuple[NDArray, NDArray[np.float64]] | None = None
        self._prev_t: float | None = None
        self._held: NDArray[np.bool_] | None = None
        # the onset tracker saw the previous frame (its last depths are that frame's where
        # it was valid): the count that skips the test (update) then bounds what it finds
        self._onset_saw_prev = False
        self.n_tested = 0  # frames the full test ran on / were skipped as unable to remove
        self.n_skipped = 0

    def reset(self) -> None:
        self._prev = None
        self._prev_t = None
        self._held = None
        self._run = None
        # the occlusion onsets are kept: across a gap an object still in view keeps its
        # depth (and its onset), and terrain is compared with what it was before the gap

    @property
    def holding(self) -> bool:
        """True if the last tested frame had camera-fixed pixels."""
        return self._held is not None and bool(self._held.any())

    def remember(
        self,
        depth_m: NDArray,
        R_ground_cam: NDArray[np.float64],
        timestamp_s: float | None = None,
        depth_sigma_m: float | None = None,
    ) -> None:
        """A frame that is not tested (report-only mode between checks): kept as the
        previous frame for the next :meth:`update`, with nothing held; its depth feeds the
        occlusion onsets (``depth_sigma_m``: the depth noise sd, m, as :meth:`update`'s)."""
        self._onset_saw_prev = self._onset is not None and depth_sigma_m is not None
        if self._onset is not None and depth_sigma_m is not None:
            self._onset.update(depth_m, depth_sigma_m)
        self._prev_t = None if timestamp_s is None else float(timestamp_s)
        self._prev = (np.asarray(depth_m), np.asarray(R_ground_cam, dtype=float))
        self._held = None
        self._run = None

    def update(
        self,
        depth_m: NDArray,
        candidates: NDArray[np.bool_] | Callable[[], NDArray[np.bool_]],
        K: NDArray[np.float64],
        R_ground_cam: NDArray[np.float64],
        predicted_delta_xz_m: NDArray[np.float64] | None,
        predicted_cov_m2: NDArray[np.float64] | None,
        depth_sigma_m: float,
        rot_sigma_rad: float = 0.0,
        ground_turn_rad: float = 0.0,
        timestamp_s: float | None = None,
        stamp_sigma_s: float = 0.0,
    ) -> NDArray[np.bool_]:
        """Camera-fixed pixels of this frame (all False without a previous frame or a
        prediction); remembers this frame for the next call. ``ground_turn_rad``: the caller
        turned its ground frame by rot_y(``ground_turn_rad``) since the previous frame (a
        pitch correction); the previous rotation is re-expressed in the turned frame.
        ``timestamp_s``, ``stamp_sigma_s``: the frame's stamp and the sd of a stamp's jitter
        (s); the predicted motion is uncertain by sqrt(2) sd / (frame interval) of itself.
        ``candidates``: the (H, W) pixels to test, or a function that returns them, called
        only when the test runs.

        With the occlusion-onset requirement (and ``skip_unable``) the full test runs only
        when it can remove a pixel: a surface needs ``onset_share`` x ``min_pixels`` pixels
        that pass the test and are in the onset status (:func:`surface_majority`). So the
        test is skipped when fewer pixels of the whole image are in the onset status with the
        previous frame's depth (the onset update counts them at no cost), or when the test
        run on the image's pixels in the onset status alone (a pixel's test does not depend
        on the other pixels tested; a superset of the candidates in that status) passes
        fewer of them. The skipped frames return the all-False
        mask the full test would have returned (:attr:`n_tested`, :attr:`n_skipped` count
        the frames)."""
        share = 0.0
        if timestamp_s is not None and self._prev_t is not None:
            dt = float(timestamp_s) - self._prev_t
            if dt > 0:
                share = np.sqrt(2.0) * stamp_sigma_s / dt
        self._prev_t = None if timestamp_s is None else float(timestamp_s)
        if self._prev is not None and ground_turn_rad != 0.0:
            c, s = np.cos(ground_turn_rad), np.sin(ground_turn_rad)
            turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
            self._prev = (self._prev[0], turn @ self._prev[1])
        depth = np.asarray(depth_m)
        mask = np.zeros(depth.shape, dtype=bool)
        onset = None
        able = True
        if self._onset is not None:
            # the test's "same depth" tolerance (camera_fixed_mask's, the same floats)
            tol_fixed = self.k_sigma * np.sqrt(2.0) * depth_sigma_m
            onset = self._onset.update(depth, depth_sigma_m, tol_fixed)
            # a surface leaves only with onset_share x min_pixels (at least) of its pixels
            # both in the onset status and of the same depth as in the previous frame (the
            # test's pixels, held ones included, all have that depth): with fewer such
            # pixels in the whole image the test removes nothing, and is skipped
            able = not (self.skip_unable and self._onset_saw_prev) or (
                self._onset.n_same >= self.onset_share * self.min_pixels
            )
            self._onset_saw_prev = True
        prev = self._prev
        if (
            able
            and prev is not None
            and predicted_delta_xz_m is not None
            and predicted_cov_m2 is not None
            and prev[0].shape == depth.shape
        ):
            motion = motion_from_ground(
                prev[1],
                R_ground_cam,
                predicted_delta_xz_m,
                predicted_cov_m2,
                rot_sigma_rad,
                share,
            )
            if onset is not None and self.skip_unable:
                # first the pixels in the onset status alone, anywhere in the image: the test
                # decides each pixel by itself (the view test looks at the whole image,
                # whatever is tested), so it finds at least the full test's pixels in that
                # status; with fewer than onset_share x min_pixels no surface can leave (and
                # the slice's candidates are not needed)
                first = camera_fixed_mask(
                    prev[0], depth, onset, K, motion, depth_sigma_m, self.k_sigma, self._held
                )
                able = bool(np.count_nonzero(first) >= self.onset_share * self.min_pixels)
            if able:
                mask = self._full_test(prev[0], depth, candidates, K, motion, depth_sigma_m, onset)
        if able:
            self.n_tested += 1
        else:
            self.n_skipped += 1
        self._prev = (depth, np.asarray(R_ground_cam, dtype=float))
        self._held = mask
        if self.confirm_frames <= 1:
            return mask
        run = self._run
        if run is None or run.shape != mask.shape:
            run = np.zeros(mask.shape, dtype=np.int32)
        self._run = np.where(mask, run + 1, 0).astype(np.int32)
        return self._run >= self.confirm_frames

    def _full_test(
        self,
        prev_depth: NDArray,
        depth: NDArray,
        candidates: NDArray[np.bool_] | Callable[[], NDArray[np.bool_]],
        K: NDArray[np.float64],
        motion: CameraMotion,
        depth_sigma_m: float,
        onset: NDArray[np.bool_] | None,
    ) -> NDArray[np.bool_]:
        """The test on the candidates, then decided per surface (:func:`surface_majority`)
        on the candidates' bounding box (the slice band) with a pixel of margin for the
        depth edges; (H, W) bool."""
        if callable(candidates):
            candidates = candidates()
        same = np.zeros(depth.shape, dtype=bool)
        mask = camera_fixed_mask(
            prev_depth,
            depth,
            candidates,
            K,
            motion,
            depth_sigma_m,
            self.k_sigma,
            self._held,
            same,
        )
        if not mask.any():
            return mask
        rr, cc = np.nonzero(same)
        r0, r1 = max(rr.min() - 1, 0), rr.max() + 2
        c0, c1 = max(cc.min() - 1, 0), cc.max() + 2
        box = (slice(r0, r1), slice(c0, c1))
        decided = surface_majority(
            mask[box],
            depth[box],
            same[box],
            self.edge_rel_tol,
            self.edge_abs_tol_m,
            self.min_pixels,
            None if onset is None else onset[box],
            self.onset_share,
        )
        mask = np.zeros(depth.shape, dtype=bool)
        mask[box] = decided
        return mask
