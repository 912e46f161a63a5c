"""Sagittal-plane projection of the ToF depth image (paper Section II.A.1, eq. 1-2).

Eq. 1 keeps the points "directly in front of the prosthesis", |y| < 0.05 m in the paper's
camera axes. In vio_graph's optical convention the lateral camera axis is ``x_C`` (x right,
y down, z forward; docs/conventions.md), so the slice is |x_C| < half_width_m. Eq. 2 then
rotates the slice into the gravity-aligned ground frame with the IMU attitude (heading removed),
``p_G = R_ground_cam @ p_C``, and keeps its (x, z) components. The result is RELATIVE to the
camera optical centre (the rotation has no translation), with world axes: x forward, z up.

Speed: the lateral test needs only the pixel column and the depth, because
``x_C = (u - c_x) * depth / f_x``. :func:`sagittal_slice_from_depth` applies it per pixel on
the depth image and back-projects only the pixels that pass (a few thousand of the 38k).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import FrontendError


def _check_image(depth_m: NDArray, confidence: NDArray, K: NDArray | None = None) -> None:
    """Depth and confidence are equal (H, W) images; K (if given) is 3x3."""
    if depth_m.ndim != 2 or depth_m.shape != confidence.shape:
        raise FrontendError(
            f"depth {depth_m.shape} and confidence {confidence.shape} must be equal (H, W) images"
        )
    if K is not None and np.shape(K) != (3, 3):
        raise FrontendError(f"K must be 3x3, got {np.shape(K)}")


def _valid_mask(
    depth_m: NDArray[np.float32],
    confidence: NDArray[np.uint8],
    min_depth_m: float,
    max_depth_m: float,
    min_confidence: int,
) -> NDArray[np.bool_]:
    return (confidence >= min_confidence) & (depth_m > min_depth_m) & (depth_m < max_depth_m)


def slice_pixel_mask(
    depth_m: NDArray,
    confidence: NDArray[np.uint8],
    K: NDArray[np.float64],
    half_width_m: float,
    min_depth_m: float,
    max_depth_m: float,
    min_confidence: int,
) -> NDArray[np.bool_]:
    """(H, W) the pixels eq. 1 keeps: valid (confidence, min < depth < max) and inside the
    sagittal slab, depth * |u - c_x| / f_x < half_width_m (the tests of
    :func:`sagittal_slice_from_depth`, per pixel). For a float image, tested as that
    function tests them: per column, depth in [lower, upper[column]] of the cached
    ``_slice_tables``, in the image's dtype and on the column band only (no float64
    temporaries); the same mask as :func:`slice_pixel_mask_reference`."""
    depth_m = np.asarray(depth_m)
    tables = None
    if (
        depth_m.ndim == 2
        and depth_m.dtype.kind == "f"
        and np.shape(confidence) == depth_m.shape
        and np.ndim(min_depth_m) == np.ndim(max_depth_m) == 0
    ):
        K = np.asarray(K, dtype=float)
        tables = _slice_tables(
            K.tobytes(), depth_m.shape, depth_m.dtype, half_width_m, min_depth_m, max_depth_m
        )
    if tables is None:
        return slice_pixel_mask_reference(
            depth_m, confidence, K, half_width_m, min_depth_m, max_depth_m, min_confidence
        )
    c0, c1, lower, upper, _, _ = tables
    out = np.zeros(depth_m.shape, dtype=bool)
    band = out[:, c0:c1]
    depth = depth_m[:, c0:c1]
    np.less_equal(depth, upper, out=band)  # max depth and eq. 1 per pixel (NaN fails)
    band &= depth >= lower
    band &= np.asarray(confidence)[:, c0:c1] >= min_confidence
    return out


def slice_pixel_mask_reference(
    depth_m: NDArray,
    confidence: NDArray[np.uint8],
    K: NDArray[np.float64],
    half_width_m: float,
    min_depth_m: float,
    max_depth_m: float,
    min_confidence: int,
) -> NDArray[np.bool_]:
    """:func:`slice_pixel_mask` with the per-pixel tests written out."""
    x_per_m = np.abs(np.arange(np.shape(depth_m)[1]) - K[0, 2]) / K[0, 0]
    with np.errstate(invalid="ignore"):
        keep = _valid_mask(depth_m, confidence, min_depth_m, max_depth_m, min_confidence)
        return keep & (depth_m * x_per_m[None, :] < half_width_m)


def depth_to_points_cam(
    depth_m: NDArray[np.float32],
    confidence: NDArray[np.uint8],
    K: NDArray[np.float64],
    min_depth_m: float = 0.0,
    max_depth_m: float = np.inf,
    min_confidence: int = 1,
) -> NDArray[np.float64]:
    """Back-project every valid pixel into the camera optical frame.

    Args:
        depth_m: (H, W) depth along the optical axis, metres; 0 = invalid.
        confidence: (H, W) uint8; pixels below ``min_confidence`` (default: 0) are invalid.
        K: (3, 3) pinhole intrinsics (pixels).
        min_depth_m, max_depth_m: valid depth range (exclusive), metres.

    Returns:
        (N, 3) points (x right, y down, z forward) in metres, row-major pixel order.
    """
    _check_image(depth_m, confidence, K)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    valid = _valid_mask(depth_m, confidence, min_depth_m, max_depth_m, min_confidence)
    rows, cols = np.nonzero(valid)
    z = depth_m[rows, cols].astype(np.float64)
    return np.column_stack([z * ((cols - cx) / fx), z * ((rows - cy) / fy), z])


def sagittal_slice(
    points_cam: NDArray[np.float64],
    R_ground_cam: NDArray[np.float64],
    half_width_m: float = 0.05,
) -> NDArray[np.float64]:
    """Eq. 1 + eq. 2: keep |x_C| < half_width_m, rotate into the ground frame, return (x, z).

    Args:
        points_cam: (N, 3) points in the camera optical frame, metres.
        R_ground_cam: (3, 3) rotation camera -> gravity-aligned ground frame (heading removed).
        half_width_m: half-width of the sagittal slab along the lateral axis x_C, metres.

    Returns:
        (M, 2) ``points_xz_m`` relative to the camera centre, world axes (x forward, z up).
    """
    points_cam = np.asarray(points_cam, dtype=float)
    if points_cam.ndim != 2 or points_cam.shape[1] != 3:
        raise FrontendError(f"points_cam must be (N, 3), got {points_cam.shape}")
    keep = np.abs(points_cam[:, 0]) < half_width_m  # eq. 1
    R_xz = np.asarray(R_ground_cam, dtype=float)[[0, 2], :]
    return points_cam[keep] @ R_xz.T  # eq. 2, rows x and z only


_MAX_STEPS = 64


@functools.lru_cache(maxsize=8)
def _slice_tables(
    K_bytes: bytes,
    shape: tuple[int, int],
    dtype: np.dtype,
    half_width_m: float,
    min_depth_m: float,
    max_depth_m: float,
) -> tuple[int, int, NDArray, NDArray, NDArray[np.float64], NDArray[np.float64]] | None:
    """Per-camera tables of :func:`sagittal_slice_from_depth` (cached: K and the thresholds
    are the same for every frame).

    The per-pixel tests ``min < depth < max`` and ``depth * |x_per_m(column)| < half_width``
    are monotone in the depth, so per column they hold exactly for depth values in
    [lower, upper[column]], two numbers of the image's dtype. They are found by evaluating the
    original expressions (same operands, same numpy promotion) on candidate values and stepping
    to the neighbouring representable value until the boundary: bit-exact, no rounding
    argument needed.

    Returns:
        c0, c1 (the column band that can hold a slice point), lower (scalar), upper (c1 - c0,),
        x_per_m and y_per_m grids (H, c1 - c0) of the band (x_C, y_C per metre of depth);
        None if the boundaries are not found within a few steps (degenerate thresholds).
    """
    K = np.frombuffer(K_bytes).reshape(3, 3)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    H, W = shape
    x_per_m = (np.arange(W) - cx) / fx
    ax = np.abs(x_per_m)

    def passes_upper(d: NDArray) -> NDArray[np.bool_]:  # the original tests, per column
        return (d < max_depth_m) & (d * ax < half_width_m)

    down, up = dtype.type(-np.inf), dtype.type(np.inf)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        upper = np.minimum(max_depth_m, half_width_m / ax).astype(dtype)
        lower = np.array([min_depth_m], dtype=dtype)
        for _ in range(_MAX_STEPS):  # the first guesses are within an ulp or two
            ok = passes_upper(upper)
            nxt = np.nextafter(upper, up)
            ok_next = passes_upper(nxt)
            if ok.all() and not ok_next.any():
                break
            upper = np.where(ok, np.where(ok_next, nxt, upper), np.nextafter(upper, down))
        else:
            return None
        for _ in range(_MAX_STEPS):
            prev = np.nextafter(lower, down)
            if (lower > min_depth_m)[0] and not (prev > min_depth_m)[0]:
                break
            lower = prev if (lower > min_depth_m)[0] else np.nextafter(lower, up)
        else:
            return None
    band = np.flatnonzero(upper >= lower[0])
    if band.size == 0:
        return 0, 0, lower[0], upper[:0], np.empty((H, 0)), np.empty((H, 0))
    c0, c1 = int(band[0]), int(band[-1]) + 1
    y_per_m = (np.arange(H) - cy) / fy
    x_grid = np.ascontiguousarray(np.broadcast_to(x_per_m[c0:c1], (H, c1 - c0)))
    y_grid = np.ascontiguousarray(np.broadcast_to(y_per_m[:, None], (H, c1 - c0)))
    return c0, c1, lower[0], upper[c0:c1], x_grid, y_grid


def sagittal_slice_from_depth(
    depth_m: NDArray[np.float32],
    confidence: NDArray[np.uint8],
    K: NDArray[np.float64],
    R_ground_cam: NDArray[np.float64],
    half_width_m: float = 0.05,
    min_depth_m: float = 0.0,
    max_depth_m: float = np.inf,
    min_confidence: int = 1,
    speckle: tuple[float, float, int] | None = None,
) -> NDArray[np.float64]:
    """Fast path of eq. 1-2 straight from the depth image; same result as
    ``sagittal_slice(depth_to_points_cam(...), R_ground_cam, half_width_m)``.

    The lateral test |x_C| = |u - c_x| * depth / f_x < half_width_m is evaluated per pixel
    before any point is built, so only the slice (a few thousand pixels) is back-projected.
    With it, the depth range is one per-column interval of depth values (cached per camera,
    ``_slice_tables``): two comparisons per pixel of the column band.

    ``speckle`` = (rel_tol, abs_tol_m, min_agree) with min_agree > 0: the speckle test of
    :func:`drop_speckles` is applied too, evaluated only at the pixels the slice keeps
    (a few thousand of the 38k): the same points as
    ``sagittal_slice_from_depth(depth_m, drop_speckles(depth_m, confidence, *speckle), ...)``.

    Returns:
        (M, 2) ``points_xz_m`` relative to the camera centre, world axes, metres.
    """
    _check_image(depth_m, confidence, K)
    if speckle is not None and speckle[2] > 0:
        if min_confidence < 1:  # a pixel of confidence 0 would pass the slice unchecked
            confidence = drop_speckles(depth_m, confidence, *speckle)
            speckle = None
    else:
        speckle = None
    K = np.asarray(K, dtype=float)
    tables = (
        None  # integer depth or per-pixel depth limits: the general path
        if depth_m.dtype.kind != "f" or not np.ndim(min_depth_m) == np.ndim(max_depth_m) == 0
        else _slice_tables(
            K.tobytes(), depth_m.shape, depth_m.dtype, half_width_m, min_depth_m, max_depth_m
        )
    )
    if tables is None:
        if speckle is not None:
            confidence = drop_speckles(depth_m, confidence, *speckle)
        return _sagittal_slice_reference(
            depth_m,
            confidence,
            K,
            R_ground_cam,
            half_width_m,
            min_depth_m,
            max_depth_m,
            min_confidence,
        )
    c0, c1, lower, upper, x_grid, y_grid = tables
    if c1 == c0:
        return np.empty((0, 2))
    R_xz = np.asarray(R_ground_cam, dtype=float)[[0, 2], :]
    kernels = _compiled_slice_kernels(depth_m, confidence, min_confidence)
    if kernels is not None:  # the tests, the speckle test, eq. 2 in one compiled pass
        rel, abs_m, agree = (0.0, 0.0, 0) if speckle is None else speckle
        return kernels.slice_xz(
            depth_m,
            confidence,
            c0,
            c1,
            lower,
            upper,
            int(min_confidence),
            np.float32(rel),
            np.float32(abs_m),
            int(agree),
            x_grid[0],  # the grids' one row and one column: the same values, less memory
            np.ascontiguousarray(y_grid[:, 0]),  # (a strided argument: ~6 us of dispatch)
            R_xz,
        )
    points_cam = _slice_cam_points_numpy(
        depth_m, confidence, c0, c1, lower, upper, min_confidence, speckle, x_grid, y_grid
    )
    return points_cam @ R_xz.T  # eq. 2


def _slice_cam_points_numpy(
    depth_m: NDArray,
    confidence: NDArray[np.uint8],
    c0: int,
    c1: int,
    lower,
    upper: NDArray,
    min_confidence: int,
    speckle: tuple[float, float, int] | None,
    x_grid: NDArray[np.float64],
    y_grid: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Camera-frame points (M, 3) of the slice's pixels of columns c0:c1 (row-major), numpy:
    the per-column depth interval, the confidence and, if given, the speckle test on the
    bounding box of the pixels that pass the others."""
    depth = depth_m[:, c0:c1]
    keep = depth <= upper  # max depth and eq. 1 per pixel (NaN fails)
    keep &= depth >= lower
    keep &= confidence[:, c0:c1] >= min_confidence
    if speckle is not None:  # drop_speckles on the bounding box of the slice's pixels
        in_rows = np.flatnonzero(keep.any(axis=1))
        in_cols = np.flatnonzero(keep.any(axis=0))
        if in_rows.size:
            r0, r1 = int(in_rows[0]), int(in_rows[-1]) + 1
            k0, k1 = int(in_cols[0]), int(in_cols[-1]) + 1
            drops = _speckle_drops_in_box(depth_m, confidence, r0, r1, c0 + k0, c0 + k1, *speckle)
            keep[r0:r1, k0:k1] &= ~drops
    z = depth[keep].astype(np.float64)
    points_cam = np.empty((z.size, 3))
    np.multiply(z, x_grid[keep], out=points_cam[:, 0])
    np.multiply(z, y_grid[keep], out=points_cam[:, 1])
    points_cam[:, 2] = z
    return points_cam


def _compiled_slice_kernels(depth_m: NDArray, confidence: NDArray, min_confidence: int):
    """The numba kernels (frontend/compiled.py) if they run and fit this image (float32
    depth, uint8 confidence, an integer threshold in 1..255), else None (the numpy path)."""
    if depth_m.dtype != np.float32 or confidence.dtype != np.uint8:
        return None
    if not (isinstance(min_confidence, (int, np.integer)) and 1 <= min_confidence <= 255):
        return None
    from vio_graph.frontend.icp import compiled_kernels

    return compiled_kernels()


def _sagittal_slice_reference(
    depth_m: NDArray,
    confidence: NDArray[np.uint8],
    K: NDArray[np.float64],
    R_ground_cam: NDArray[np.float64],
    half_width_m: float,
    min_depth_m: float,
    max_depth_m: float,
    min_confidence: int,
) -> NDArray[np.float64]:
    """Eq. 1-2 with the per-pixel tests written out (any depth dtype); the reference of the
    table-driven :func:`sagittal_slice_from_depth`."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W = depth_m.shape[1]
    x_per_m = (np.arange(W) - cx) / fx  # (W,) x_C per metre of depth
    # columns that can hold a slice point at all: |x_C| at the smallest usable depth
    cols_used = np.nonzero(np.abs(x_per_m) * max(min_depth_m, 1e-6) < half_width_m)[0]
    if cols_used.size == 0:
        return np.empty((0, 2))
    c0, c1 = int(cols_used[0]), int(cols_used[-1]) + 1
    depth = depth_m[:, c0:c1]
    keep = _valid_mask(depth, confidence[:, c0:c1], min_depth_m, max_depth_m, min_confidence)
    keep &= depth * np.abs(x_per_m[c0:c1]) < half_width_m  # eq. 1 per pixel
    rows, cols = np.nonzero(keep)
    z = depth[rows, cols].astype(np.float64)
    points_cam = np.column_stack([z * x_per_m[cols + c0], z * ((rows - cy) / fy), z])
    R_xz = np.asarray(R_ground_cam, dtype=float)[[0, 2], :]
    return points_cam @ R_xz.T  # eq. 2


def _speckle_drops_in_box(
    depth_m: NDArray[np.floating],
    confidence: NDArray[np.uint8],
    r0: int,
    r1: int,
    c0: int,
    c1: int,
    rel_tol: float,
    abs_tol_m: float,
    min_agree: int,
) -> NDArray[np.bool_]:
    """:func:`drop_speckles`' decisions for the pixels of rows r0:r1, columns c0:c1 only
    (True = dropped): the box with a one-pixel halo of its neighbours, zero outside the
    image, and the same float32 operations on the same operands, so the same decisions."""
    d = np.asarray(depth_m, dtype=np.float32)
    h, w = d.shape
    a0, a1, b0, b1 = max(r0 - 1, 0), min(r1 + 1, h), max(c0 - 1, 0), min(c1 + 1, w)
    dh = d[a0:a1, b0:b1]
    valid = (np.asarray(confidence)[a0:a1, b0:b1] > 0) & np.isfinite(dh) & (dh > 0)
    hh, ww = r1 - r0, c1 - c0
    pad = np.zeros((hh + 2, ww + 2), dtype=np.float32)
    pad[a0 - r0 + 1 : a1 - r0 + 1, b0 - c0 + 1 : b1 - c0 + 1] = np.where(valid, dh, 0.0)
    db = d[r0:r1, c0:c1]
    tol = abs_tol_m + rel_tol * db
    agree = np.zeros((hh, ww), dtype=np.int8)
    n_valid = np.zeros((hh, ww), dtype=np.int8)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            nb = pad[1 + dy : 1 + dy + hh, 1 + dx : 1 + dx + ww]
            n_valid += nb > 0
            agree += (nb > 0) & (np.abs(nb - db) <= tol)
    need = np.clip(n_valid, 1, min_agree)
    box_valid = valid[r0 - a0 : r0 - a0 + hh, c0 - b0 : c0 - b0 + ww]
    return box_valid & (agree < need)


def drop_speckles(
    depth_m: NDArray[np.floating],
    confidence: NDArray[np.uint8],
    rel_tol: float,
    abs_tol_m: float,
    min_agree: int,
) -> NDArray[np.uint8]:
    """Confidence with isolated depth pixels set to 0 (invalid).

    A pixel is kept when at least ``min_agree`` of its 8 neighbours are valid and within
    ``abs_tol_m`` + ``rel_tol`` x depth of it; where fewer than ``min_agree`` neighbours are
    valid at all (dropout around the pixel), as many as are valid, and at least one. A surface
    is continuous in the image, so its pixels agree with several neighbours, even on either
    side of a depth edge; a spurious return (multipath, a glitch) lands at a random range and
    agrees with none. The same idea
    as a ToF driver's flying-pixel or speckle filter, applied in the image before the slice
    (in the sagittal slice the spurious points near the camera are as dense as a surface)."""
    h, w = np.shape(depth_m)
    # where the sensor returned little around a pixel (dropout at range or at grazing
    # angles), only as many agreeing neighbours as there are valid ones are asked for, but
    # one at least: an isolated return cannot be told from a spurious one
    drop = _speckle_drops_in_box(depth_m, confidence, 0, h, 0, w, rel_tol, abs_tol_m, min_agree)
    out = np.array(confidence, copy=True)
    out[drop] = 0
    return out


def mixed_pixel_drops(
    depth_m: NDArray[np.floating],
    confidence: NDArray[np.uint8],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    jump_m: float,
    abs_tol_m: float,
    rel_tol: float,
    radius_px: int = 1,
) -> NDArray[np.bool_]:
    """The mixed-pixel test at the pixels (rows, cols) only (True = mixed, drop it).

    A ToF pixel whose footprint straddles a depth edge (a stair nosing over the tread below)
    integrates both surfaces and returns a depth in between. Such a pixel is flagged when the
    valid pixels of its (2 radius_px + 1)^2 window span more than ``jump_m``, its depth lies
    farther than ``abs_tol_m + rel_tol * depth`` from both the nearest and the farthest of
    them, and it is on no plane through its 3x3 neighbours: for a plane the inverse depth is
    affine in the pixel coordinates, so a surface pixel (a floor seen at a grazing angle spans
    a large depth range too) matches the mean inverse depth of every opposite pair of valid
    3x3 neighbours within the same tolerance, while a mixed pixel straddles the edge with at
    least one pair. A pixel without a valid opposite pair is kept (nothing to judge it by).
    A surface pixel at the edge itself sits at one of the extremes and is kept."""
    d = np.asarray(depth_m, dtype=np.float64)
    h, w = d.shape
    rows = np.asarray(rows, dtype=np.intp)
    cols = np.asarray(cols, dtype=np.intp)
    valid = (np.asarray(confidence) > 0) & np.isfinite(d) & (d > 0)
    p = max(int(radius_px), 1)
    pad = np.zeros((h + 2 * p, w + 2 * p))
    pad[p:-p, p:-p] = np.where(valid, d, 0.0)
    r, c = rows + p, cols + p
    z = pad[r, c]
    zmax = np.full(z.shape, -np.inf)
    zmin = np.full(z.shape, np.inf)
    for dy in range(-p, p + 1):
        for dx in range(-p, p + 1):
            if dy == 0 and dx == 0:
                continue
            nb = pad[r + dy, c + dx]
            ok = nb > 0
            zmax = np.where(ok, np.maximum(zmax, nb), zmax)
            zmin = np.where(ok, np.minimum(zmin, nb), zmin)
    tol = abs_tol_m + rel_tol * z
    between = (zmax - zmin > jump_m) & (z - zmin > tol) & (zmax - z > tol) & (z > 0)
    planar = np.ones(z.shape, dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):  # the four opposite pairs
            a, b = pad[r + dy, c + dx], pad[r - dy, c - dx]
            both = (a > 0) & (b > 0)
            mid = 2.0 / (1.0 / a + 1.0 / b)  # the plane's depth between them
            planar &= ~both | (np.abs(z - mid) <= tol)
    return between & ~planar


def drop_mixed_pixels(
    depth_m: NDArray[np.floating],
    confidence: NDArray[np.uint8],
    jump_m: float,
    abs_tol_m: float,
    rel_tol: float,
    at: NDArray[np.bool_] | None = None,
    radius_px: int = 1,
) -> NDArray[np.uint8]:
    """Confidence with the mixed pixels (:func:`mixed_pixel_drops`) set to 0, tested at the
    pixels of the mask ``at`` only (e.g. the slice's pixels; None = every valid pixel)."""
    _check_image(np.asarray(depth_m), np.asarray(confidence))
    if at is None:
        at = np.asarray(confidence) > 0
    rows, cols = np.nonzero(at)
    drop = mixed_pixel_drops(depth_m, confidence, rows, cols, jump_m, abs_tol_m, rel_tol, radius_px)
    out = np.array(confidence, copy=True)
    out[rows[drop], cols[drop]] = 0
    return out
