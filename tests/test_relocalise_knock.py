"""A knock the IMU does not flag (60 m/s^2 on two accelerometer axes for 0.1 s, a 6 m/s
velocity error, inside the sensor's range): without the lost-track search the IMU seed is
metres off on every later frame and vision never returns; with it the filter re-anchors its
velocity on the search's displacements and stays within centimetres, and says so."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.frontend.config import TrackerConfig

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample"


@pytest.fixture(scope="module")
def knocked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("knock") / "rec"
    shutil.copytree(SAMPLE, out)
    imu = pd.read_csv(out / "imu.csv")
    hit = (imu["timestamp_s"] >= 2.0) & (imu["timestamp_s"] < 2.1)
    assert hit.sum() == 10
    imu.loc[hit, "acc_x_mps2"] += 60.0
    imu.loc[hit, "acc_z_mps2"] -= 60.0
    imu.to_csv(out / "imu.csv", index=False)
    return out


def _errors_m(rec: Path, out: Path, after_frames: int | None, modes=("filter",)):
    from vio_graph.pipeline import run_recording
    from vio_graph.recording.reader import Recording
    from vio_graph.recording.tum import read_tum

    cfg = PipelineConfig()
    tracker = TrackerConfig(relocalise_after_frames=after_frames)
    cfg = cfg.model_copy(update={"frontend": cfg.frontend.model_copy(update={"tracker": tracker})})
    res = run_recording(rec, out, cfg, modes=modes, visualize=False, progress=False)
    gt = Recording.open(rec).groundtruth.trajectories["camera"]
    err = {}
    for mode in modes:
        est = read_tum(out / "trajectories" / f"{mode}_camera.tum")
        err[mode] = np.linalg.norm(est.xz_m - gt.xz_at(est.timestamp_s), axis=1)
    return err, res.metrics


def test_a_knock_loses_the_filter_without_the_search_and_not_with_it(
    knocked: Path, tmp_path: Path
) -> None:
    err_off, m_off = _errors_m(knocked, tmp_path / "off", None)
    assert err_off["filter"].max() > 0.5  # the premise: metres off, vision lost for good
    assert m_off["health"]["relocalisations"]["found"] == 0
    err_on, m_on = _errors_m(knocked, tmp_path / "on", 0, ("filter", "smoother"))
    assert err_on["filter"].max() < 0.03
    # the smoother was told the IMU was wrong there (FrameRecord.imu_distrust); without it
    # its preintegration of the knock held it 5 cm off
    assert np.sqrt(np.mean(err_on["smoother"] ** 2)) < 0.01
    reloc = m_on["health"]["relocalisations"]
    assert reloc["fused"] >= 1 and 2.0 <= reloc["first_s"] <= 2.2
    assert any("lost track" in w for w in m_on["health"]["warnings"])


def test_the_search_leaves_a_clean_trial_as_it_was(tmp_path: Path) -> None:
    """On the clean sample the seeded registration never fails twice in a row in a way the
    search could change: the same path with and without it."""
    err_off, _ = _errors_m(SAMPLE, tmp_path / "off", None)
    err_on, m_on = _errors_m(SAMPLE, tmp_path / "on", 0)
    assert m_on["health"]["relocalisations"]["fused"] == 0
    np.testing.assert_allclose(err_on["filter"], err_off["filter"], atol=1e-9)
