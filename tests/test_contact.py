"""The optional foot-contact channel (contact.csv): format, validation, use in the estimator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.errors import RecordingError
from vio_graph.evaluation.diagnostics import true_stance
from vio_graph.pipeline import run_recording
from vio_graph.recording import Recording
from vio_graph.recording.metadata import ContactModel
from vio_graph.recording.streams import ContactTable
from vio_graph.recording.writer import write_recording


def with_contact(
    src: Path,
    dst: Path,
    force_n: np.ndarray | None,
    t_s: np.ndarray,
    kind: str = "load_cell",
    threshold_n: float = 100.0,
) -> Path:
    """Copy ``src`` with a contact channel (force_n at t_s)."""
    rec = Recording.open(src)
    meta = rec.metadata.model_copy(
        update={"contact": ContactModel(kind=kind, threshold_n=threshold_n)}
    )
    table = ContactTable(t_s, force_n, force_n >= threshold_n)
    frames = ((f.depth_m, f.confidence) for f in rec.frames())
    return write_recording(
        dst,
        meta,
        rec.imu,
        rec.joints,
        rec.groundtruth,
        rec.frame_timestamps_s,
        frames,
        contact=table,
    )


def _load_cell(rec: Recording, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A pylon load cell at 100 Hz: ~700 N while the true ankle is still, ~0 N in swing."""
    t = rec.imu.timestamp_s
    still = true_stance(rec.groundtruth.trajectories["ankle"], t)
    return t, np.where(still, 700.0, 5.0) + rng.normal(0, 10.0, t.size)


def test_contact_round_trip_and_validation(short_upstair: Path, tmp_path: Path) -> None:
    rec = Recording.open(short_upstair)
    t, f = _load_cell(rec, np.random.default_rng(0))
    out = with_contact(short_upstair, tmp_path / "c", f, t)
    back = Recording.open(out).contact
    assert back is not None and len(back) == t.size
    np.testing.assert_allclose(back.force_n, f, rtol=1e-8)
    assert np.array_equal(back.loaded, f >= 100.0)
    assert Recording.open(short_upstair).contact is None
    # no 'contact' section is written for a recording without the channel (older readers)
    import yaml

    assert "contact" not in yaml.safe_load((short_upstair / "metadata.yaml").read_text())
    # a contact file the metadata does not describe is refused, naming the file
    (short_copy := tmp_path / "nometa").mkdir()
    import shutil

    shutil.copytree(short_upstair, short_copy, dirs_exist_ok=True)
    shutil.copy(out / "contact.csv", short_copy / "contact.csv")
    with pytest.raises(RecordingError, match="contact.csv"):
        Recording.open(short_copy)
    # a switch must read 0 or 1
    bad = with_contact(short_upstair, tmp_path / "sw", f, t, kind="switch", threshold_n=0.5)
    with pytest.raises(RecordingError, match="0 or 1"):
        Recording.open(bad)


@pytest.mark.slow
def test_contact_proposes_stance_and_vision_still_decides(
    short_upstair: Path, tmp_path: Path
) -> None:
    rec = Recording.open(short_upstair)
    t, f = _load_cell(rec, np.random.default_rng(1))
    base = PipelineConfig()
    cfg = base.model_copy(
        update={
            "output": base.output.model_copy(update={"rerun": False, "plots": False}),
            "filter": base.filter.model_copy(update={"stance_contact": "propose"}),
        }
    )
    good = with_contact(short_upstair, tmp_path / "good", f, t)
    m = run_recording(good, tmp_path / "rg", cfg, progress=False, visualize=False).metrics
    assert m["stance_detection"]["precision"] > 0.9
    assert m["stance_detection"]["recall"] > 0.6
    assert max(m["ate_cm"]["filter"]["toe"].values()) < 5.0
    # a stuck load cell (always loaded): the vision test refuses the swings
    stuck = with_contact(short_upstair, tmp_path / "stuck", np.full(t.size, 700.0), t)
    m2 = run_recording(stuck, tmp_path / "rs", cfg, progress=False, visualize=False).metrics
    assert m2["health"]["stance"]["vision_refused"] > 10
    assert m2["ate_cm"]["filter"]["toe"]["x"] < 2.0 * max(m["ate_cm"]["filter"]["toe"]["x"], 1.0)


def test_confirm_role_needs_the_quiet_ankle_as_well(short_upstair: Path, tmp_path: Path) -> None:
    """``filter.stance_contact: confirm``: a stuck load cell (always loaded) proposes nothing
    the acceleration detector does not, so the stance candidates are exactly those of the
    same recording without a contact channel; with ``propose`` it proposes every frame; with
    ``off`` (the default) the channel is not used at all."""
    rec = Recording.open(short_upstair)
    t = rec.imu.timestamp_s
    stuck = with_contact(short_upstair, tmp_path / "stuck", np.full(t.size, 700.0), t)
    base = PipelineConfig()
    output = base.output.model_copy(update={"rerun": False, "plots": False})

    def candidates(path: Path, role: str, out: str) -> int:
        cfg = base.model_copy(
            update={
                "output": output,
                "filter": base.filter.model_copy(update={"stance_contact": role}),
            }
        )
        m = run_recording(path, tmp_path / out, cfg, progress=False, visualize=False).metrics
        return m["health"]["stance"]["candidate_frames"]

    without = candidates(short_upstair, "confirm", "none")
    assert 0 < candidates(stuck, "confirm", "confirm") == without
    assert candidates(stuck, "propose", "propose") > without
    assert candidates(stuck, "off", "off") == without
    assert PipelineConfig().filter.stance_contact == "off"
