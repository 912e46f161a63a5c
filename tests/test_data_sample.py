"""The sample recording committed at data/sample: it loads, it is what data/sample.yaml makes,
it is small, and the pipeline runs on it with a toe error against its ground truth that a
working estimator reaches (a broken one does not: the IMU-only baseline is off by decimetres)."""

from __future__ import annotations

from pathlib import Path

import pytest

from vio_graph.config import load_config
from vio_graph.recording import Recording

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample"


def test_sample_loads_and_matches_its_scenario() -> None:
    from vio_graph.sim import ScenarioConfig, load_scenario

    rec = Recording.open(SAMPLE)
    s = rec.summary()
    assert tuple(s["image_size"]) == (112, 86)
    assert 3.4 < s["duration_s"] < 3.6 and s["frames"] >= 100
    assert rec.groundtruth is not None
    prov = rec.metadata.provenance
    assert (prov.source, prov.scenario, prov.seed) == ("simulator", "sample", 1)
    assert ScenarioConfig.model_validate(prov.config) == load_scenario(
        ROOT / "data" / "sample.yaml"
    )
    size = sum(p.stat().st_size for p in SAMPLE.rglob("*") if p.is_file())
    assert size < 5e6, f"data/sample is {size / 1e6:.1f} MB; keep it to a few MB"


@pytest.mark.slow
def test_sample_runs_with_small_error(tmp_path: Path) -> None:
    from vio_graph.pipeline import run_recording

    m = run_recording(
        SAMPLE,
        tmp_path / "out",
        load_config(),
        modes=("filter", "batch"),
        visualize=False,
        progress=False,
    ).metrics
    for mode, bound_cm in (("filter", 2.0), ("batch", 1.0)):
        toe = m["ate_cm"][mode]["toe"]
        assert toe["x"] < bound_cm and toe["z"] < bound_cm, (mode, toe)
    assert m["ate_cm"]["imu_only"]["toe"]["x"] > 10.0  # the bound means something
    assert m["map"]["rise_error_mm"] < 5.0
    assert (tmp_path / "out" / "trajectories" / "batch_toe.tum").is_file()
