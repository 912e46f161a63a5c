"""`vio-graph compare` on the sample recording: the report names its scenario and the
filter's toe ATE against the recording's ground truth."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from vio_graph.cli import app

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample"


def test_compare_writes_a_report_with_the_filter_ate(tmp_path: Path) -> None:
    out = tmp_path / "cmp"
    res = CliRunner().invoke(app, ["compare", str(SAMPLE), "--out", str(out), "--mode", "filter"])
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    text = json.dumps(summary)
    assert "sample" in text
    report = (out / "results.md").read_text()
    assert report.startswith("# Results on simulated trials\n\nReproduce with:")
    assert "vio-graph compare" in report
    metrics = json.loads(next(out.rglob("metrics.json")).read_text())
    toe = metrics["ate_cm"]["filter"]["toe"]
    assert 0.0 < toe["x"] < 2.0 and 0.0 < toe["z"] < 2.0, toe
