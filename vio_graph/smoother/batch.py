"""Full-batch smoother: the whole recording as one graph, Levenberg-Marquardt (QR, robust).

Same ingestion as :class:`~vio_graph.smoother.sliding_window.SlidingWindowSmoother`; factors
are accumulated and :meth:`BatchSmoother.solve` optimises everything at once (the offline
upper bound of what the graph can do).
"""

from __future__ import annotations

import logging
import math
import time

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.protocol import EstimatorReport
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.graph import (
    KeyframeUpdate,
    V,
    X,
    camera_from_pose,
    camera_xz_cov_from_pose_cov,
)
from vio_graph.smoother.interface import KeyframeEstimate, KeyframeSmootherBase

log = logging.getLogger(__name__)


class BatchSmoother(KeyframeSmootherBase):
    """Accumulate every keyframe's factors; :meth:`solve` runs LM over the whole graph.

    Attributes:
        solve_time_ms: wall time of the last :meth:`solve` (ms).
        solve_iterations: LM iterations of the last :meth:`solve`.
        finish_s: wall time (s) of :meth:`finish` (flush and solve), NaN before.
    """

    name = "batch"

    def __init__(self, config: SmootherConfig | None = None, imu_T_cam: ArrayLike | None = None):
        config = config or SmootherConfig()
        super().__init__(config, np.eye(4) if imu_T_cam is None else imu_T_cam)
        # robust IMU factors here only: the full batch re-weights at every LM iteration
        self._builder.robust_imu = True
        # graph association of level surfaces: by the solution of a first solve
        self._builder.defer_levels = (
            config.factors.height_landmarks
            and config.factors.height_landmark_association == "graph"
        )
        self.graph = gtsam.NonlinearFactorGraph()
        self.initial = gtsam.Values()
        self._result: gtsam.Values | None = None
        self._marginals: gtsam.Marginals | None = None
        self.solve_time_ms = float("nan")
        self.solve_iterations = 0
        self.finish_s = float("nan")
        # the first velocity prior's position in ``graph``; whether a keyframe called for its
        # test (KeyframeGraphBuilder.first_velocity_testable) and whether it was relaxed
        self._first_velocity_index: int | None = None
        self._first_velocity_test = False
        self.first_velocity_relaxed = False
        #: solves done again with QR (``batch_qr_fallback``: a Cholesky solve retried a step)
        self.qr_fallbacks = 0

    def finish(self) -> None:
        """Flush the pending keyframe and solve the whole graph (timed in ``finish_s``)."""
        self.flush()
        t0 = time.perf_counter()
        try:
            self.solve()
        finally:
            self.finish_s = time.perf_counter() - t0

    def report(self) -> EstimatorReport:
        """``batch_solve_s`` (latency) and, once solved, the robust kernels' statistics
        (``batch_robust``, see :meth:`robust_outliers`)."""
        rep = EstimatorReport(latency_ms={"batch_solve_s": self.finish_s})
        if self._result is not None:
            try:
                rep.metrics["batch_robust"] = self.robust_outliers()
            except EstimationError as exc:
                log.warning("batch robust statistics unavailable: %s", exc)
        if self.first_velocity_relaxed:
            rep.metrics["batch_first_velocity_relaxed"] = True
        if self.qr_fallbacks:
            rep.metrics["batch_qr_fallbacks"] = self.qr_fallbacks
        return rep

    def _consume(self, u: KeyframeUpdate) -> None:
        fv = self._builder.first_velocity_prior
        if u.index == 0 and fv is not None:
            self._first_velocity_index = self.graph.size() + fv.position
        if self._builder.first_velocity_testable(u):
            self._first_velocity_test = True
        self.graph.push_back(u.factors)
        self.initial.insert(u.values)
        self._result = None
        self._marginals = None

    def solve(self) -> gtsam.Values:
        """Optimise the whole graph (pending keyframe flushed first); returns the Values."""
        self.flush()
        if self.initial.size() == 0:
            raise EstimationError("no keyframe to optimise")
        params = self._lm_params(self.config.batch_factorization)
        t0 = time.perf_counter()
        opt = self._optimize(params)
        if self._relax_first_velocity():  # the prior failed its test: solve again without it
            opt = self._optimize(params)
        if self._builder.deferred_levels:  # graph association: by this solution, then again
            assert self._result is not None
            first = self._result
            factors, values = self._builder.associate_deferred_levels(
                lambda i: float(first.atPose3(X(i)).translation()[2])
            )
            self.graph.push_back(factors)
            self.initial.insert(values)
            start = gtsam.Values(first)
            start.insert(values)
            opt = self._optimize(params, start)
        self.solve_time_ms = (time.perf_counter() - t0) * 1e3
        self.solve_iterations = int(opt.iterations())
        assert self._result is not None
        return self._result

    def _lm_params(self, factorization: str) -> gtsam.LevenbergMarquardtParams:
        """LM parameters of the configured batch solve with ``factorization`` (QR or
        CHOLESKY, both multifrontal)."""
        params = gtsam.LevenbergMarquardtParams()
        params.setLinearSolverType(f"MULTIFRONTAL_{factorization}")
        params.setMaxIterations(self.config.batch_max_iterations)
        params.setRelativeErrorTol(self.config.batch_relative_error_tol)
        return params

    def _optimize(
        self, params: gtsam.LevenbergMarquardtParams, start: gtsam.Values | None = None
    ) -> gtsam.LevenbergMarquardtOptimizer:
        """LM over the whole graph from ``start`` (default: the initial values); the answer
        in ``_result``. A Cholesky solve that retried a step is done again with QR
        (``batch_qr_fallback``)."""
        opt = self._run_lm(params, start)
        cholesky = params.getLinearSolverType() == "MULTIFRONTAL_CHOLESKY"
        if cholesky and self.config.batch_qr_fallback and not every_step_first_try(opt, params):
            log.info("batch: an LM step was retried with Cholesky; solving again with QR")
            self.qr_fallbacks += 1
            opt = self._run_lm(self._lm_params("QR"), start)
        return opt

    def _run_lm(
        self, params: gtsam.LevenbergMarquardtParams, start: gtsam.Values | None = None
    ) -> gtsam.LevenbergMarquardtOptimizer:
        opt = gtsam.LevenbergMarquardtOptimizer(
            self.graph, self.initial if start is None else start, params
        )
        try:
            self._result = opt.optimize()
        except RuntimeError as exc:
            raise EstimationError(f"batch optimisation failed: {exc}") from exc
        return opt

    def _relax_first_velocity(self) -> bool:
        """If a keyframe called for it and the first velocity prior fails its test at the
        solution, replace the prior by its relaxed form (``smoother.first_velocity_test``);
        True if replaced."""
        fv = self._builder.first_velocity_prior
        k = self._first_velocity_index
        if self.first_velocity_relaxed or not self._first_velocity_test or fv is None or k is None:
            return False
        assert self._result is not None
        relaxed = fv.relaxed_factor()
        if relaxed is None or not self._builder.first_velocity_fails(self._result.atVector(V(0))):
            return False
        self.graph.replace(k, relaxed)
        self.first_velocity_relaxed = True
        return True

    def robust_outliers(self) -> dict[str, float]:
        """How many robust (Huber/Cauchy) factors the solution down-weights: whitened error
        beyond the kernel threshold, i.e. measurements the smoother effectively rejected.
        Returns {"robust_factors": n, "downweighted": k, "max_whitened_error": e}."""
        result = self.solve() if self._result is None else self._result
        # one pass over the graph for both counts (count_downweighted twice, bit for bit)
        out, imu = count_downweighted_both(
            self.graph, result, self.config.robust_threshold, self.config.imu_robust_threshold
        )
        out.update({f"imu_{k}": v for k, v in imu.items()})
        return out

    def keyframe_estimates(self, with_covariance: bool = True) -> list[KeyframeEstimate]:
        """Refined camera x-z of every keyframe (solves first if needed)."""
        if self._result is None:
            self.solve()
        assert self._result is not None
        if with_covariance and self._marginals is None:
            try:  # the wheel's Marginals only offers Cholesky; NaN covariances if it fails
                self._marginals = gtsam.Marginals(self.graph, self._result)
            except RuntimeError:
                self._marginals = None
        out = []
        for i, t in enumerate(self._kf_times_s):
            R, cam = camera_from_pose(self._result.atPose3(X(i)), self.imu_p_cam_m)
            cov: NDArray[np.float64] = np.full((2, 2), np.nan)
            if with_covariance and self._marginals is not None:
                cov = camera_xz_cov_from_pose_cov(
                    R, self._marginals.marginalCovariance(X(i)), self.imu_p_cam_m
                )
            out.append(KeyframeEstimate(t, cam[[0, 2]], cov, R))
        return out


def every_step_first_try(
    opt: gtsam.LevenbergMarquardtOptimizer, params: gtsam.LevenbergMarquardtParams
) -> bool:
    """Whether every iteration of a finished LM run took its step at the first lambda it
    tried. With a fixed lambda factor f, GTSAM divides lambda by f after an accepted step and
    multiplies it by f after a rejected one (an error that did not decrease, or a linear
    system it could not factorise), so n iterations without a retry leave lambda at
    lambda_initial / f**n, and any retry leaves it at least f**2 times that (at least f
    times if LM gave up at the last iteration)."""
    if not params.getUseFixedLambdaFactor():
        return False  # (lambda then also depends on the gain ratio: no such trace)
    factor = params.getlambdaFactor()
    expected = params.getlambdaInitial()
    for _ in range(opt.iterations()):
        expected = max(expected / factor, params.getlambdaLowerBound())
    return bool(opt.lambda_() <= expected * np.sqrt(factor))


def count_downweighted(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    threshold: float,
    imu: bool = False,
) -> dict[str, float]:
    """Count robust factors whose whitened error norm exceeds ``threshold`` at ``values``;
    also the largest whitened error norm (``max_whitened_error``, sigmas). ``imu``: the IMU
    factors only (their own threshold); else every other robust factor."""
    n_robust = n_down = 0
    worst = 0.0
    for k in range(graph.size()):
        f = graph.at(k)
        if f is None or not hasattr(f, "noiseModel"):
            continue
        if isinstance(f, gtsam.CombinedImuFactor) != imu:
            continue
        nm = f.noiseModel()
        if not isinstance(nm, gtsam.noiseModel.Robust):
            continue
        n_robust += 1
        # graph.at() is typed as the base class; a factor with a noise model has the method
        raw = f.unwhitenedError(values)  # type: ignore[attr-defined]
        err = float(np.linalg.norm(nm.noise().whiten(raw)))
        worst = max(worst, err)
        if err > threshold:
            n_down += 1
    return {"robust_factors": n_robust, "downweighted": n_down, "max_whitened_error": worst}


def count_downweighted_both(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    threshold: float,
    imu_threshold: float,
) -> tuple[dict[str, float], dict[str, float]]:
    """``count_downweighted(graph, values, threshold)`` and ``count_downweighted(graph,
    values, imu_threshold, imu=True)`` in one pass over the graph: the same factors, the
    same whitened errors and the same answers (a 10-minute batch graph has ~78,000 factors;
    two passes cost ~0.5 s of CPU at the end of a run). The norm is ``sqrt(e . e)``, what
    ``np.linalg.norm`` computes for a real vector."""
    n_robust = [0, 0]  # [other, imu]
    n_down = [0, 0]
    worst = [0.0, 0.0]
    limit = (threshold, imu_threshold)
    robust_type, imu_type = gtsam.noiseModel.Robust, gtsam.CombinedImuFactor
    for k in range(graph.size()):
        f = graph.at(k)
        if f is None or not hasattr(f, "noiseModel"):
            continue
        nm = f.noiseModel()
        if not isinstance(nm, robust_type):
            continue
        j = 1 if isinstance(f, imu_type) else 0
        n_robust[j] += 1
        w = nm.noise().whiten(f.unwhitenedError(values))  # type: ignore[attr-defined]
        w = w.ravel(order="K")  # (np.linalg.norm: the raveled vector, sqrt of its dot)
        err = math.sqrt(w.dot(w))
        worst[j] = max(worst[j], err)
        if err > limit[j]:
            n_down[j] += 1
    return tuple(  # type: ignore[return-value]
        {"robust_factors": n_robust[j], "downweighted": n_down[j], "max_whitened_error": worst[j]}
        for j in (0, 1)
    )
