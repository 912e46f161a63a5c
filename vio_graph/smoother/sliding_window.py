"""Online fixed-lag smoother over keyframes (GTSAM IncrementalFixedLagSmoother).

Per keyframe: build its factors (graph.py), drop any factor touching a key that already left
the window (GTSAM would raise and the batch variant would stay broken), store the last
estimate (and marginal) of keyframes about to be marginalised, update the smoother, re-read
the newest state for the next prediction.

Keys leave the window in batches (``smoother.marginalization_slack_s``): GTSAM's lag is set
per update, to the configured lag when the oldest key is older than lag + slack and to "never"
otherwise, because an update that marginalises constrains iSAM2's ordering in a way that
lets the Bayes tree's root drift away from the newest keyframe (docs/method.md section 4).
A Cholesky update that fails (an indeterminate system, or any other GTSAM error) is redone by
rebuilding the window in QR (``smoother.fixed_lag_qr_fallback``).
"""

from __future__ import annotations

import time
from typing import Any, cast

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.evaluation.latency import stats_ms
from vio_graph.protocol import EstimatorReport
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.graph import (
    B,
    KeyframeUpdate,
    V,
    X,
    camera_from_pose,
    camera_xz_cov_from_pose_cov,
)
from vio_graph.smoother.interface import KeyframeEstimate, KeyframeSmootherBase

_NAN2 = np.full((2, 2), np.nan)
#: the lag (s) given to GTSAM for an update that marginalises nothing (marginalization_slack_s)
_HOLD_LAG_S = 1e9
# gtsam.Symbol keys: the character in the top 8 bits, the index below
_CHR_X, _CHR_L = ord("x"), ord("l")
_INDEX_MASK = (1 << 56) - 1


def isam2_params(config: SmootherConfig, factorization: str) -> gtsam.ISAM2Params:
    """iSAM2 settings of the fixed-lag smoother with the given factorisation ("QR" or
    "CHOLESKY"): the configured relinearisation threshold, checked at every update."""
    p = gtsam.ISAM2Params()
    p.setFactorization(factorization)
    p.setRelinearizeThreshold(config.relinearize_threshold)
    p.relinearizeSkip = 1
    return p


def _tail_equals(graph: gtsam.NonlinearFactorGraph, tail: gtsam.NonlinearFactorGraph) -> bool:
    """Whether the last ``tail.size()`` factors of ``graph`` equal those of ``tail``."""
    m, n = tail.size(), graph.size()
    if m > n:
        return False
    for j in range(m):
        f = graph.at(n - m + j)
        if f is None or not f.equals(tail.at(j), 0.0):
            return False
    return True


class SlidingWindowSmoother(KeyframeSmootherBase):
    """Fixed-lag smoother, lag = ``config.smoother_lag_s()`` (window_s rounded to n*dt + dt/2).

    Attributes:
        update_times_ms: wall time (ms) of each keyframe's smoother update, bookkeeping
            included (factor building is in ``build_times_ms``).
    """

    name = "smoother"

    def __init__(self, config: SmootherConfig | None = None, imu_T_cam: ArrayLike | None = None):
        config = config or SmootherConfig()
        super().__init__(config, np.eye(4) if imu_T_cam is None else imu_T_cam)
        self.lag_s = config.smoother_lag_s()
        if config.fixed_lag_batch_solver:
            lm = gtsam.LevenbergMarquardtParams()
            if config.fixed_lag_factorization == "QR":
                lm.setLinearSolverType("MULTIFRONTAL_QR")
            self._smoother: gtsam.BatchFixedLagSmoother | gtsam.IncrementalFixedLagSmoother = (
                gtsam.BatchFixedLagSmoother(self.lag_s, lm)
            )
        else:
            self._smoother = gtsam.IncrementalFixedLagSmoother(
                self.lag_s, isam2_params(config, config.fixed_lag_factorization)
            )
        self._incremental = not config.fixed_lag_batch_solver
        self._gtsam_lag_s = self.lag_s  # the lag GTSAM holds now (_marginalisation_lag)
        #: keyframe time (s) at which a Cholesky update failed and the window was rebuilt in
        #: QR (``smoother.fixed_lag_qr_fallback``), None if it never happened
        self.qr_fallback_at_s: float | None = None
        self._live: dict[int, float] = {}  # key -> timestamp (s), mirrors GTSAM's window
        # keyframe -> (camera x-z, its covariance, R_world_imu) read just before it left
        self._frozen: dict[
            int, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
        ] = {}
        self._newest_cov: dict[int, NDArray[np.float64]] = {}
        self._newest_s: float | None = None  # newest key time handed to GTSAM so far
        # the first velocity prior's index in iSAM2 and whether it was relaxed
        # (KeyframeGraphBuilder.first_velocity_fails)
        self._first_velocity_index: int | None = None
        self.first_velocity_relaxed = False
        self.update_times_ms: list[float] = []

    # ---- one keyframe --------------------------------------------------------------------------
    def _consume(self, u: KeyframeUpdate) -> None:
        t0 = time.perf_counter()
        live = self._live
        new_keys = set(u.values.keys())
        # drop factors that touch keys already marginalised (never re-add dead keys)
        if any(not all(k in live or k in new_keys for k in ks) for ks in u.factor_keys):
            kept = gtsam.NonlinearFactorGraph()
            for n, ks in enumerate(u.factor_keys):
                if all(k in live or k in new_keys for k in ks):
                    kept.add(u.factors.at(n))
            factors = kept
        else:
            factors = u.factors
        stamps = {k: s for k, s in u.timestamps.items() if k in live or k in new_keys}

        # keys that this update will marginalise (same rule as GTSAM: stamp < newest - lag);
        # every key of an update is stamped with the keyframe time, so ``live`` (re-stamped
        # keys moved to its end) stays ordered by time and the leaving keys are its head
        newest = u.timestamp_s if self._newest_s is None else max(u.timestamp_s, self._newest_s)
        cutoff = newest - self._marginalisation_lag(live, stamps, newest)
        in_order = all(s >= newest for s in stamps.values())
        leaving: list[int] = []
        for k, s in live.items():
            if s >= cutoff and in_order:
                break
            if s < cutoff and k not in stamps:
                leaving.append(k)
        for k in leaving:
            if k >> 56 == _CHR_X:
                i_old = k & _INDEX_MASK
                cov_now = self.config.marginal_covariance == "at_exit"
                xz, cov, R = self._camera_estimate(i_old, with_covariance=cov_now)
                cov = cov if cov_now else self._newest_cov.pop(i_old, _NAN2)
                self._frozen[i_old] = (xz, cov, R)

        self._update(factors, u.values, stamps, (), f"fixed-lag update at {u.timestamp_s:.3f} s")

        if in_order:
            for k in leaving:
                del live[k]
            for k, s in stamps.items():
                live.pop(k, None)
                live[k] = s
        else:  # not ordered by time (never from KeyframeGraphBuilder): rebuild in time order
            merged = {**live, **stamps}
            self._live = {
                k: s for k, s in sorted(merged.items(), key=lambda ks: ks[1]) if s >= cutoff
            }
        self._newest_s = newest
        if self._incremental:
            self._test_first_velocity(u)
        dead_landmarks = [k for k in leaving if k >> 56 == _CHR_L]
        if dead_landmarks:
            self._builder.forget_landmarks(dead_landmarks)
        i = u.index
        pose = self._smoother.calculateEstimatePose3(X(i))
        self._builder.set_latest_state(
            pose,
            self._smoother.calculateEstimateVector(V(i)),
            self._smoother.calculateEstimateConstantBias(B(i)),
            index=i,
        )
        levels = self._builder.graph_level_keys
        if levels:  # (graph association of level surfaces: the landmarks' estimates)
            self._builder.set_level_heights(
                {
                    k: float(self._smoother.calculateEstimatePose3(k).translation()[2])
                    for k in levels
                    if k in self._live
                }
            )
        if self.config.marginal_covariance == "when_newest" and self._incremental:
            self._newest_cov[i] = self._camera_estimate(i, with_covariance=True, pose=pose)[1]
        self.update_times_ms.append((time.perf_counter() - t0) * 1e3)

    def _marginalisation_lag(
        self, live: dict[int, float], stamps: dict[int, float], newest_s: float
    ) -> float:
        """The lag (s) of this update: ``lag_s`` when keys leave the window now, else one so
        long that none does (``smoother.marginalization_slack_s``: keys leave in batches,
        once the oldest one not re-stamped by this update is older than lag + slack). Sets it
        in GTSAM when it changes."""
        slack = self.config.marginalization_slack_s
        if slack <= 0 or not self._incremental:
            return self.lag_s
        oldest = next((s for k, s in live.items() if k not in stamps), None)
        due = oldest is not None and oldest < newest_s - self.lag_s - slack
        lag = self.lag_s if due else _HOLD_LAG_S
        if lag != self._gtsam_lag_s:
            self._smoother.setSmootherLag(lag)
            self._gtsam_lag_s = lag
        return lag

    def _test_first_velocity(self, u: KeyframeUpdate) -> None:
        """Remember the first velocity prior's iSAM2 index (keyframe 0); after a keyframe
        that calls for it, test the prior at the estimate and, if it fails, replace it by its
        relaxed form in one more update (``smoother.first_velocity_test``)."""
        smoother = cast(gtsam.IncrementalFixedLagSmoother, self._smoother)
        fv = self._builder.first_velocity_prior
        if u.index == 0 and fv is not None:
            self._first_velocity_index = int(
                smoother.getISAM2Result().getNewFactorsIndices()[fv.position]
            )
            return
        k = self._first_velocity_index
        if (
            u.flagged_imu_factor is None  # (most keyframes: nothing to test)
            or self.first_velocity_relaxed
            or k is None
            or fv is None
            or V(0) not in self._live
            or not self._builder.first_velocity_testable(u)
        ):
            return
        relaxed = fv.relaxed_factor()
        if relaxed is None or not self._builder.first_velocity_fails(
            smoother.calculateEstimateVector(V(0))
        ):
            return
        graph = gtsam.NonlinearFactorGraph()
        graph.add(relaxed)
        what = f"fixed-lag update at {u.timestamp_s:.3f} s (first velocity prior)"
        self._update(graph, gtsam.Values(), {}, (k,), what)
        self.first_velocity_relaxed = True

    def _update(
        self,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, float],
        remove: tuple[int, ...],
        what: str,
    ) -> None:
        """One GTSAM update; a Cholesky update that fails (e.g. finds the system
        indeterminate) is redone by rebuilding the window in QR (:meth:`_rebuild_in_qr`) if
        ``smoother.fixed_lag_qr_fallback``; any other failure raises EstimationError."""
        try:
            # (the stubs type the key -> time map with invariant protocol keys; ints are fine)
            if remove:
                self._smoother.update(factors, values, cast(dict[Any, Any], stamps), list(remove))
            else:
                self._smoother.update(factors, values, cast(dict[Any, Any], stamps))
        except RuntimeError as exc:  # GTSAM's exceptions surface as RuntimeError
            if not self._falls_back(exc):
                raise EstimationError(f"{what} failed: {exc}") from exc
            try:
                self._rebuild_in_qr(factors, values, stamps, remove)
            except RuntimeError as exc2:
                raise EstimationError(f"{what} failed: {exc}; in QR: {exc2}") from exc2
            self.qr_fallback_at_s = self._newest_s if not stamps else max(stamps.values())

    def _falls_back(self, exc: RuntimeError) -> bool:
        """Whether ``exc`` is a Cholesky failure :meth:`_rebuild_in_qr` answers: any GTSAM
        error of a Cholesky update (an indeterminate system says so; on a weakly constrained
        window, e.g. displacements without landmarks or stance anchors on a descent, GTSAM
        4.3 has also raised with an empty message), once per smoother."""
        return (
            self._incremental
            and self.config.fixed_lag_qr_fallback
            and self.qr_fallback_at_s is None
            and self.config.fixed_lag_factorization == "CHOLESKY"
        )

    def _rebuild_in_qr(
        self,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, float],
        remove: tuple[int, ...],
    ) -> None:
        """A new incremental smoother with QR factorisation holding what the failed one held:
        its factors (the marginals of keyframes already marginalised included), its
        linearisation point and key times, plus the failed update (if iSAM2 had not taken it
        in yet), solved in one batch step; it replaces the failed smoother for the rest of the
        run. The first velocity prior's factor index follows the re-numbering."""
        old = cast(gtsam.IncrementalFixedLagSmoother, self._smoother)
        held = old.getFactors()
        theta = gtsam.Values(old.getLinearizationPoint())
        # iSAM2 adds the new factors and values before it eliminates; a failure earlier (or
        # a test's) leaves them out, then they are added here. New keys tell; an update
        # without any (the relaxed first velocity prior) is told by its factors at the end
        new_keys = values.keys()
        if len(new_keys):
            taken = all(theta.exists(k) for k in new_keys)
        else:
            taken = _tail_equals(held, factors)
        graph = gtsam.NonlinearFactorGraph()
        renumbered: dict[int, int] = {}
        for n in range(held.size()):
            f = held.at(n)
            if f is None or (not taken and n in remove):
                continue
            renumbered[n] = graph.size()
            graph.add(f)
        if not taken:
            for n in range(factors.size()):
                graph.add(factors.at(n))
            theta.insert(values)
        times = {int(k): float(t) for k, t in old.timestamps().items()}
        times.update(stamps)
        self._smoother = gtsam.IncrementalFixedLagSmoother(
            self._gtsam_lag_s, isam2_params(self.config, "QR")
        )
        self._smoother.update(graph, theta, cast(dict[Any, Any], times))
        if self._first_velocity_index is not None:
            self._first_velocity_index = renumbered.get(self._first_velocity_index)

    def _camera_estimate(
        self, i: int, with_covariance: bool, pose: gtsam.Pose3 | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Camera x-z (m), its 2x2 covariance (NaN unless asked) and R_world_imu (3, 3);
        ``pose``: X(i)'s estimate if already read since the last update."""
        if pose is None:
            pose = self._smoother.calculateEstimatePose3(X(i))
        R, cam = camera_from_pose(pose, self.imu_p_cam_m)
        cov = _NAN2
        if with_covariance and isinstance(self._smoother, gtsam.IncrementalFixedLagSmoother):
            cov = camera_xz_cov_from_pose_cov(
                R, self._smoother.marginalCovariance(X(i)), self.imu_p_cam_m
            )
        return cam[[0, 2]], cov, R

    # ---- outputs -------------------------------------------------------------------------------
    def keyframe_estimates(self, with_covariance: bool = True) -> list[KeyframeEstimate]:
        """Every keyframe ever added: live ones freshly read, marginalised ones frozen; NaN for
        a keyframe whose update failed (it never entered the smoother)."""
        out = []
        for i, t in enumerate(self._kf_times_s):
            R: NDArray[np.float64] | None
            if i in self._frozen:
                xz, cov, R = self._frozen[i]
            else:
                try:
                    xz, cov, R = self._camera_estimate(i, with_covariance)
                except (IndexError, RuntimeError):
                    xz, cov, R = np.full(2, np.nan), _NAN2, None
            out.append(KeyframeEstimate(t, xz.copy(), cov.copy(), None if R is None else R.copy()))
        return out

    def report(self) -> EstimatorReport:
        """Per-keyframe latency (update + factor building, ms) as ``smoother_update``."""
        n = min(len(self.update_times_ms), len(self.build_times_ms))
        per_kf = np.asarray(self.update_times_ms[:n]) + np.asarray(self.build_times_ms[:n])
        rep = EstimatorReport(latency_ms={"smoother_update": stats_ms(per_kf)})
        if self.first_velocity_relaxed:
            rep.metrics["smoother_first_velocity_relaxed"] = True
        if self.qr_fallback_at_s is not None:
            rep.metrics["smoother_qr_fallback_at_s"] = self.qr_fallback_at_s
        return rep

    def live_keys(self) -> set[int]:
        """Keys currently inside the window (our mirror of GTSAM's key-timestamp map)."""
        return set(self._live)

    def smoother_keys(self) -> set[int]:
        """Keys GTSAM itself reports in its window (for checking :meth:`live_keys`)."""
        return {int(k) for k in self._smoother.timestamps().keys()}

    def latest_state(self) -> tuple[gtsam.Pose3, NDArray[np.float64], gtsam.imuBias.ConstantBias]:
        """Newest keyframe's (IMU pose, velocity (3,) m/s, bias)."""
        i = len(self._kf_times_s) - 1
        if i < 0:
            raise EstimationError("no keyframe yet")
        return (
            self._smoother.calculateEstimatePose3(X(i)),
            self._smoother.calculateEstimateVector(V(i)),
            self._smoother.calculateEstimateConstantBias(B(i)),
        )


__all__ = ["SlidingWindowSmoother", "isam2_params"]
