"""The estimator protocol (vio_graph/protocol.py): every estimator of a run takes the same
records through the same calls, and the replay treats them alike, failures included."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.errors import EstimationError
from vio_graph.estimator import RigGeometry
from vio_graph.protocol import Estimator, EstimatorReport, FrameRecord, ImuStep
from vio_graph.recording import Recording
from vio_graph.replay import Replay, make_estimators
from vio_graph.viz.rerun_logger import NullVisualizer


class Spy:
    """A protocol estimator that keeps what it is given; fails at frame ``fail_at`` if set."""

    def __init__(self, name: str = "spy", fail_at: int | None = None) -> None:
        self.name = name
        self.fail_at = fail_at
        self.steps: list[ImuStep] = []
        self.records: list[FrameRecord] = []
        self.finished = 0
        self.online = None  # set: note the online estimator's attitude as each frame arrives
        self.attitude_then: list[np.ndarray] = []

    def add_imu(self, step: ImuStep) -> None:
        self.steps.append(step)

    def add_frame(self, record: FrameRecord) -> None:
        self.records.append(record)
        if self.online is not None:
            self.attitude_then.append(self.online.R_world_imu(record.timestamp_s))
        if self.fail_at is not None and len(self.records) == self.fail_at:
            raise EstimationError("spy gives up")

    def finish(self) -> None:
        self.finished += 1

    def camera_path(self, frame_times_s, filter_xz_m):
        if len(self.records) != len(frame_times_s):
            raise EstimationError("spy saw only part of the trial")
        return np.array([r.estimate.camera_xz_m + 1.0 for r in self.records])

    def report(self) -> EstimatorReport:
        return EstimatorReport(metrics={"spy_frames": len(self.records)})


def test_every_estimator_of_a_run_follows_the_protocol(tiny_recording: Path) -> None:
    rec = Recording.open(tiny_recording)
    ests = make_estimators(
        PipelineConfig(),
        RigGeometry.from_metadata(rec.metadata),
        {"smoother", "batch"},
        np.zeros(2),
    )
    assert list(ests) == ["filter", "imu_only", "icp_only", "smoother", "batch"]
    for name, e in ests.items():
        assert isinstance(e, Estimator), name
        assert e.name == name


def test_the_replay_hands_every_estimator_the_same_records(tiny_recording: Path) -> None:
    rec = Recording.open(tiny_recording)
    rp = Replay(rec, PipelineConfig(), {"filter"}, NullVisualizer())
    spy = rp.estimators["spy"] = Spy()  # type: ignore[assignment]
    spy.online = rp.online
    lg = rp.run()
    n = len(lg.t_s)
    assert n > 10 and spy.finished == 1 and not rp.failed
    assert len(spy.steps) == len(rec.imu)  # every IMU sample, in order
    t_imu = np.array([s.timestamp_s for s in spy.steps])
    np.testing.assert_array_equal(t_imu, rec.imu.timestamp_s)
    assert [r.timestamp_s for r in spy.records] == list(lg.t_s)
    # the filter's path is what the records carry; the spy's own answer comes back by name
    np.testing.assert_array_equal(
        lg.camera_xz["filter"], [r.estimate.camera_xz_m for r in spy.records]
    )
    np.testing.assert_array_equal(lg.camera_xz["spy"], lg.camera_xz["filter"] + 1.0)
    # the attitude the measurements were built with, and the leg angles, travel per frame
    for r, R_then in zip(spy.records, spy.attitude_then, strict=True):
        np.testing.assert_array_equal(r.R_world_imu, R_then)
    r = spy.records[-1]
    assert lg.shank_pitch_imu[-1] == r.shank_pitch_imu_rad
    assert r.displacement is r.frontend.displacement
    # both IMU views are the same measurement; only the orientation may carry the offset
    for s in spy.steps:
        np.testing.assert_array_equal(s.shank.accel_mps2, s.corrected.accel_mps2)
        np.testing.assert_array_equal(s.shank.gyro_radps, s.corrected.gyro_radps)


def test_a_failing_estimator_is_recorded_and_no_longer_fed(tiny_recording: Path) -> None:
    rec = Recording.open(tiny_recording)
    rp = Replay(rec, PipelineConfig(), {"filter"}, NullVisualizer())
    spy = rp.estimators["spy"] = Spy(fail_at=5)  # type: ignore[assignment]
    lg = rp.run()
    assert len(spy.records) == 5 and spy.finished == 0
    assert rp.failed["spy"]["t_s"] == pytest.approx(lg.t_s[4])
    assert rp.failed["spy"]["error"] == "spy gives up"
    # IMU samples stopped at the failure too
    assert spy.steps[-1].timestamp_s <= lg.t_s[4]
    # no usable path: the filter's stands in; the other estimators finished the trial
    np.testing.assert_array_equal(lg.camera_xz["spy"], lg.camera_xz["filter"])
    assert lg.camera_xz["icp_only"].shape == (len(lg.t_s), 2)
