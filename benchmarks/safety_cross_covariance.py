"""The clearance sigma's pose term with the filter's cross-covariance (stochastic clones)
against the difference of marginal covariances it uses today (docs/method.md section 8,
"What the sigma covers"): the share of frames within 1 and 2 sigma per model.

The pose term is the covariance of the relative position error between the camera now (e_k)
and the keyframes that mapped the terrain bin (their mean error u_b, as the bin's mean
covariance is their mean). Today it is |P_k - mean_j P_j| (a random walk: no cross-covariance).
With the filter's cross-covariance it is exact for the linearised filter:

    Cov(e_k - u_b) = P_k + Cov(u_b) - X_kb - X_kb^T,  X_kb = mean_j Cov(e_k, e_j),

with Cov(e_k, e_j) tracked as a *frozen* clone of the position at keyframe j: the map keeps
the keyframe's estimate as it was, so the clone's own covariance stays P_j while its
cross-covariance with the state follows the filter: F C at every propagation, (I - K H) C at
every accepted update, J C for an augmented block, rows dropped with a marginalised one.
The filter's own arithmetic is untouched (the tracker only reads P, H, V and F), so its
estimate is the same; the tracker is installed for the replay only (``tracked_filter``) and
needs the numpy filter paths (``VIO_GRAPH_COMPILED=0``, set here).

Models (the monitor re-run on the same filter run, numpy reference map):

- ``marginal``: today's |P_k - mean P_j| with the consistency scales (the run's output);
- ``clone``: the cross-covariance term, scaled by the pose consistency scale as computed today
  (against the marginal model);
- ``clone_consistent``: the cross-covariance term also in the consistency test's prediction
  (so its pose scale is the data's ratio to this model);
- ``clone_unscaled``: the cross-covariance term with no pose scale (map scale kept).

With ``--frames-above MM`` it lists, per recording, the frames whose clearance error (today's
model) exceeds MM millimetres: the error, the true clearance, which foot point is closest,
the camera's error now and at the keyframes that mapped the nearest terrain bin (their mean),
and their age (docs/method.md: why downstair seeds 4 and 5 miss the 1 cm p95).

    VIO_GRAPH_COMPILED=0 python benchmarks/safety_cross_covariance.py REC [REC ...]
"""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

os.environ["VIO_GRAPH_COMPILED"] = "0"  # the tracker follows the numpy filter paths

import _common  # pins BLAS threads before numpy
import numpy as np

from vio_graph.config import load_config
from vio_graph.estimator import OnlineEstimator
from vio_graph.evaluation.safety import true_safety
from vio_graph.filter import eskf
from vio_graph.recording.reader import Recording
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyMonitor, _psd_abs_entries

MODELS = ("marginal", "clone", "clone_consistent", "clone_unscaled")
_CORE = 8  # the filter's core error states (p, v, a_b, g), the rows F touches


def _cross(f: Any) -> np.ndarray:
    """The filter's cross-covariance with the frozen clones (rows as P), growing it by the
    rows of a tilt block the filter inserted with no correlation."""
    C = f._xc
    n = f._P.shape[0]
    if C.shape[0] == n - 2 and f._aug_keys and f._aug_keys[-1] == eskf._TILT:
        C = f._xc = np.vstack([C, np.zeros((2, C.shape[1]))])
    if C.shape[0] != n:
        raise RuntimeError(f"clone tracker lost a block: {C.shape[0]} rows, P has {n}")
    return C


@contextlib.contextmanager
def tracked_filter(records: dict[str, list]) -> Iterator[None]:
    """Install the frozen-clone tracker on ``SagittalEskf`` and a hook on the safety monitor
    that records, per frame, Cov(e_k, e_j) for the clones so far ("X") and freezes a clone
    at each keyframe ("P_jj", "pairs": Cov(e_j, e_i) for the earlier ones, "keyframes")."""
    E = eskf.SagittalEskf
    saved = {n: getattr(E, n) for n in ("propagate", "_correct", "_augment", "_augment_rows")}
    saved["_marginalise"] = E._marginalise
    saved_init, saved_update = OnlineEstimator.__init__, SafetyMonitor.update
    current: list[Any] = [None]

    def propagate(self: Any, imu: Any) -> None:
        t0 = self._t_s
        saved["propagate"](self, imu)
        C = getattr(self, "_xc", None)
        if C is not None and C.shape[1] and self._t_s != t0:  # F_x of this step
            C[:_CORE] = self._Fx[:_CORE, :_CORE] @ C[:_CORE]

    def correct(self: Any, innovation: Any, H: Any, V: Any, *a: Any, **k: Any) -> bool:
        C = _cross(self) if getattr(self, "_xc", None) is not None else None
        P0 = self._P
        ok = saved["_correct"](self, innovation, H, V, *a, **k)
        if ok and C is not None and C.shape[1]:
            HP = H @ P0
            K = np.linalg.solve(HP @ H.T + V, HP).T
            self._xc = C - K @ (H @ C)
        return ok

    def augment(self: Any, key: Any, value: Any, dt: float, extra: Any) -> None:
        C = _cross(self) if getattr(self, "_xc", None) is not None else None
        saved["_augment"](self, key, value, dt, extra)
        if C is not None:
            self._xc = np.vstack([C, C[0:2] + dt * C[2:4]])

    def augment_rows(self: Any, key: Any, value: Any, J: Any, extra: Any) -> None:
        C = _cross(self) if getattr(self, "_xc", None) is not None else None
        saved["_augment_rows"](self, key, value, J, extra)
        if C is not None:
            self._xc = np.vstack([C, J @ C])

    def marginalise(self: Any, key: Any) -> None:
        C = _cross(self) if getattr(self, "_xc", None) is not None else None
        i = self._aug_index(key) if key in self._aug_xz else None
        saved["_marginalise"](self, key)
        if C is not None and i is not None:
            self._xc = np.delete(C, [i, i + 1], axis=0)

    def est_init(self: Any, *a: Any, **k: Any) -> None:
        saved_init(self, *a, **k)
        current[0] = self.filter
        for v in records.values():
            v.clear()  # a replay's second pass starts over

    def update(self: Any, t_s: float, cam: Any, P: Any, *rest: Any) -> Any:
        f = current[0]
        if getattr(f, "_xc", None) is None:
            f._xc = np.zeros((f._P.shape[0], 0))
        C = _cross(f)
        records["X"].append(C[0:2].copy())
        if len(rest) > 3 and rest[3] is not None:  # a keyframe: freeze its position
            records["pairs"].append(C[0:2].copy())
            records["P_jj"].append(f._P[0:2, 0:2].copy())
            records["keyframes"].append(len(records["X"]) - 1)
            f._xc = np.hstack([C, f._P[:, 0:2]])
        return saved_update(self, t_s, cam, P, *rest)

    for n, fn in (
        ("propagate", propagate),
        ("_correct", correct),
        ("_augment", augment),
        ("_augment_rows", augment_rows),
        ("_marginalise", marginalise),
    ):
        setattr(E, n, fn)
    OnlineEstimator.__init__ = est_init  # type: ignore[method-assign]
    SafetyMonitor.update = update  # type: ignore[method-assign]
    try:
        yield
    finally:
        for n, fn in saved.items():
            setattr(E, n, fn)
        OnlineEstimator.__init__ = saved_init  # type: ignore[method-assign]
        SafetyMonitor.update = saved_update  # type: ignore[method-assign]


class CloneMonitor(SafetyMonitor):
    """The numpy reference monitor with the pose term of ``model`` (module docstring), on the
    clone records of one replay; frames fed in order from 0."""

    def __init__(self, config: SafetyConfig, records: dict[str, list], model: str) -> None:
        super().__init__(config, incremental=False, compiled=False)
        self.records, self.model = records, model
        self.k = -1
        self.bin_keyframes: dict[int, list[int]] = {}  # bin -> clone indices that saw it
        self.clone_of = {f: m for m, f in enumerate(records["keyframes"])}
        K = len(records["keyframes"])
        G = np.zeros((2 * K, 2 * K))  # Cov(e_i, e_j) of the frozen clones
        for j in range(K):
            G[2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = records["P_jj"][j]
            X = records["pairs"][j]
            for i in range(X.shape[1] // 2):
                G[2 * j : 2 * j + 2, 2 * i : 2 * i + 2] = X[:, 2 * i : 2 * i + 2]
                G[2 * i : 2 * i + 2, 2 * j : 2 * j + 2] = X[:, 2 * i : 2 * i + 2].T
        self.G = G
        add = self.map.add_keyframe

        def add_keyframe(cam: Any, profile: Any, P: Any) -> Any:
            rel = np.asarray(profile, dtype=float).reshape(-1, 2)
            rel = rel[np.all(np.isfinite(rel), axis=1)]
            x = rel[:, 0] + float(np.asarray(cam, dtype=float)[0])
            for b in np.unique(np.floor(x / config.bin_m).astype(np.int64)).tolist():
                self.bin_keyframes.setdefault(b, []).append(self.clone_of[self.k])
            return add(cam, profile, P)

        self.map.add_keyframe = add_keyframe  # type: ignore[method-assign]

    def update(self, t_s: float, *args: Any, **kw: Any) -> Any:  # type: ignore[override]
        self.k += 1
        return super().update(t_s, *args, **kw)

    def clone_cov(self, P: Any, b: int) -> np.ndarray:
        """Cov(e_k - u_b) (2, 2) for bin ``b`` at the current frame."""
        js = self.bin_keyframes[b]
        Pk = np.asarray(P, dtype=float)
        X = self.records["X"][self.k]
        frames = self.records["keyframes"]
        Xs = sum(Pk if frames[j] == self.k else X[:, 2 * j : 2 * j + 2] for j in js) / len(js)
        idx = np.array([[2 * j, 2 * j + 1] for j in js]).ravel()
        Gs = self.G[np.ix_(idx, idx)]
        V = np.array([[Gs[a::2, c::2].sum() for c in (0, 1)] for a in (0, 1)]) / len(js) ** 2
        R = Pk + V - Xs - Xs.T
        return 0.5 * (R + R.T)

    def _relative_cov(
        self, P: Any, b: int, scale: float, x_factor: float = 1.0
    ) -> list[list[float]]:
        if self.model == "marginal":
            return super()._relative_cov(P, b, scale, x_factor)
        R = self.clone_cov(P, b)
        s = 1.0 if self.model == "clone_unscaled" else scale
        return _psd_abs_entries(R[0, 0], R[0, 1], R[1, 1], s)

    def _add_keyframe(self, camera_xz_m: Any, profile_xz_m: Any, P: Any) -> None:
        if self.model != "clone_consistent":
            return super()._add_keyframe(camera_xz_m, profile_xz_m, P)
        seen = self._keyframe_window(camera_xz_m, profile_xz_m)
        if seen is not None:
            Pk = np.asarray(P, dtype=float)
            now = np.array([Pk[0, 0], (Pk[0, 1] + Pk[1, 0]) / 2, Pk[1, 1]])

            def rows(k: Any) -> np.ndarray:  # P_k minus the relative covariance per bin
                out = [self.clone_cov(P, int(b)) for b in np.atleast_1d(seen.bins[k]).tolist()]
                return np.array([now - [R[0, 0], R[0, 1], R[1, 1]] for R in out]).reshape(-1, 3)

            c = self.config
            self.consistency.observe_keyframe(
                camera_xz_m,
                profile_xz_m,
                P,
                seen.profile,
                rows,
                c.bin_m,
                self.map.top_band_m,
                c.relative_pose_scale,
            )
        self.map.add_keyframe(camera_xz_m, profile_xz_m, P)


def calibration(
    path: Path, frames_above_mm: float | None = None, save: Path | None = None
) -> dict[str, tuple[float, float]]:
    """Share of frames within 1 and 2 sigma per model on one recording (and the listing of
    ``--frames-above``); with ``save``, the per-frame standardised errors per model go to
    ``save / <recording name>.npz`` (for benchmarks/safety_sigma_null.py ``--npz``)."""
    cfg = load_config(None)
    rec = Recording.open(path)
    records: dict[str, list] = {"X": [], "pairs": [], "P_jj": [], "keyframes": []}
    with tracked_filter(records):
        lg, est = _common.filter_leg_run(rec, cfg)
    t = np.asarray(lg.t_s)
    truth = true_safety(
        rec.groundtruth, rec.metadata.terrain, t, np.zeros(len(t), bool), cfg.safety
    )
    if truth is None:
        raise SystemExit(f"{path}: no true terrain / foot (a simulated recording is needed)")
    out = {}
    series: dict[str, np.ndarray] = {"scenario": np.array(str(rec.metadata.provenance.scenario))}
    for model in MODELS:
        mon = CloneMonitor(cfg.safety, records, model)
        c, s = np.full(len(t), np.nan), np.full(len(t), np.nan)
        lines = []
        for k in range(len(t)):
            r = _common.monitor_update(mon, lg, est, k)
            c[k], s[k] = r.clearance_m, r.clearance_sigma_m
            err = c[k] - truth["clearance_m"][k]
            if (
                model == "marginal"
                and frames_above_mm is not None
                and abs(err) * 1e3 > frames_above_mm
            ):
                lines.append(_frame_line(mon, k, t, err, truth, est, rec, r))
        if lines:
            print(
                f"{_common.display_path(path)}: frames with |clearance error| > "
                f"{frames_above_mm} mm"
            )
            print("\n".join(lines))
        e = c - truth["clearance_m"][: len(t)]
        ok = np.isfinite(e) & np.isfinite(s) & (s > 0)
        z = np.abs(e[ok]) / s[ok]
        out[model] = (float(np.mean(z <= 1)), float(np.mean(z <= 2)))
        series[model] = np.where(ok, e / np.where(ok, s, 1.0), np.nan)
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
        np.savez(save / f"{path.name}.npz", **series)
    return out


def _frame_line(
    mon: CloneMonitor, k: int, t: Any, err: float, truth: Any, est: Any, rec: Any, r: Any
) -> str:
    """One frame of the ``--frames-above`` listing (mm, s)."""
    cam_err = est["camera"] - _common.true_leg_paths(rec, t)["camera"]
    foot, terrain = r.toe_line_xz_m
    point = min(("heel", "toe"), key=lambda b: float(np.hypot(*(foot - est[b][k]))))
    if min(np.hypot(*(foot - est[b][k])) for b in ("heel", "toe")) > 1e-6:
        point = "mid"
    b = int(np.floor(terrain[0] / mon.config.bin_m))
    frames = [mon.records["keyframes"][j] for j in mon.bin_keyframes.get(b, [])]
    kf = cam_err[frames].mean(axis=0) * 1e3 if frames else np.full(2, np.nan)
    age = float(np.mean(t[k] - t[frames])) if frames else float("nan")
    now = cam_err[k] * 1e3
    return (
        f"  frame {k} t {t[k]:.2f} s: error {err * 1e3:+.1f},"
        f" true {truth['clearance_m'][k] * 1e3:.1f},"
        f" sigma {r.clearance_sigma_m * 1e3:.1f}, {point}; camera error x / z now"
        f" {now[0]:+.1f} / {now[1]:+.1f}, at the bin's {len(frames)} keyframes {kf[0]:+.1f} /"
        f" {kf[1]:+.1f} ({age:.2f} s before);"
        f" relative {now[0] - kf[0]:+.1f} / {now[1] - kf[1]:+.1f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+", type=Path, help="simulated recording folders")
    ap.add_argument(
        "--frames-above",
        type=float,
        default=None,
        metavar="MM",
        help="list frames with |error| > MM mm",
    )
    ap.add_argument(
        "--save", type=Path, default=None, metavar="DIR", help="per-frame z per model (npz)"
    )
    args = ap.parse_args()
    print("| recording | " + " | ".join(f"{m}: within 1 / 2 sigma" for m in MODELS) + " |")
    print("|---" * (len(MODELS) + 1) + "|")
    for path in args.recordings:
        res = calibration(path, args.frames_above, args.save)
        cells = " | ".join(f"{res[m][0]:.2f} / {res[m][1]:.2f}" for m in MODELS)
        print(f"| {_common.display_path(path)} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
