"""A smoother failure must not kill a run: the pipeline records it and keeps the filter going."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio_graph.config import PipelineConfig
from vio_graph.errors import EstimationError
from vio_graph.pipeline import run_recording


def test_failing_smoother_is_recorded_not_fatal(
    short_upstair: Path, tmp_path: Path, monkeypatch
) -> None:
    from vio_graph.smoother import sliding_window

    calls = {"n": 0}
    original = sliding_window.SlidingWindowSmoother._consume

    def flaky(self, u):
        calls["n"] += 1
        if calls["n"] == 15:
            raise EstimationError("fixed-lag update failed: Indeterminant linear system")
        return original(self, u)

    monkeypatch.setattr(sliding_window.SlidingWindowSmoother, "_consume", flaky)
    res = run_recording(
        short_upstair,
        tmp_path / "r",
        PipelineConfig(),
        modes=("filter", "smoother"),
        visualize=False,
        progress=False,
    )
    m = res.metrics
    assert "smoother" in m["smoother_failures"]
    assert np.isfinite(m["ate_cm"]["smoother"]["toe"]["x"])
    assert (tmp_path / "r" / "trajectories" / "smoother_toe.tum").is_file()


def test_injected_wrong_associations_are_counted(short_upstair: Path, tmp_path: Path) -> None:
    cfg = PipelineConfig().model_copy(update={"inject": {"wrong_association_rate": 0.2}})
    cfg = PipelineConfig.model_validate(cfg.model_dump())
    res = run_recording(short_upstair, tmp_path / "r", cfg, visualize=False, progress=False)
    f = res.metrics["filter"]
    assert f["injected_wrong_associations"] > 5
    # the chi-square gate refuses most of the step-sized errors
    assert f["rejected_chi2"] >= 0.5 * f["injected_wrong_associations"]
