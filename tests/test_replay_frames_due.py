"""frames_due (vio_graph/replay.py): the diagnostics' time-ordered feed of one recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio_graph.recording.reader import Recording
from vio_graph.replay import frames_due

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample"


class _Recorder:
    """Stands in for an OnlineEstimator: notes what it is fed, initialised after its first
    IMU sample."""

    def __init__(self) -> None:
        self.fed: list[tuple[str, float]] = []
        self.initialised = False

    def add_imu(self, sample) -> None:
        self.fed.append(("imu", float(sample.timestamp_s)))
        self.initialised = True

    def add_joints(self, sample) -> None:
        self.fed.append(("joints", float(sample.timestamp_s)))

    def add_contact(self, sample) -> None:  # pragma: no cover - data/sample has no contact
        self.fed.append(("contact", float(sample.timestamp_s)))


def test_frames_due_feeds_every_sample_in_time_order_and_yields_the_frames_after_it() -> None:
    rec = Recording.open(SAMPLE)
    online = _Recorder()
    frames = []
    for i in frames_due(rec, online):  # type: ignore[arg-type]
        t = float(rec.frame_timestamps_s[i])
        # every sample stamped at or before the frame has been fed, none after it
        assert online.fed[-1][1] <= t
        assert sum(k == "imu" for k, _ in online.fed) == int(np.sum(rec.imu.timestamp_s <= t))
        frames.append(i)
    kinds = [k for k, _ in online.fed]
    assert kinds.count("imu") == rec.imu.timestamp_s.shape[0]
    assert kinds.count("joints") == rec.joints.timestamp_s.shape[0]
    times = [t for _, t in online.fed]
    assert times == sorted(times)
    # the frames from the first one at or after the first IMU sample, each once, in order
    first_imu = float(rec.imu.timestamp_s[0])
    expected = [i for i, t in enumerate(rec.frame_timestamps_s) if t >= first_imu]
    assert frames == expected and len(frames) > 0
