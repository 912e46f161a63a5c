"""The generalisation sweep: conditions are valid scenarios, the summary checks the aims."""

from __future__ import annotations

import pytest

from vio_graph.sim.config import load_scenario
from vio_graph.sweep import (
    AIM_CLEARANCE_P95_MM,
    AIM_FUSED_CM,
    SWEEP_CONDITIONS,
    condition_by_name,
    condition_scenario,
    summarise_sweep,
    sweep_markdown,
)


@pytest.mark.parametrize("cond", SWEEP_CONDITIONS, ids=lambda c: c.name)
def test_every_condition_is_a_valid_scenario_that_changes_something(cond) -> None:
    scen = condition_scenario(cond)
    base = load_scenario(cond.scenario)
    if cond.name != "reference":
        changed = scen.model_dump(exclude={"name"}) != base.model_dump(exclude={"name"})
        assert changed or cond.scenario != "upstair", cond.name


def test_unknown_condition_is_named() -> None:
    with pytest.raises(KeyError, match="no_such"):
        condition_by_name("no_such")


def _metrics(filter_x: float, icp_x: float, terrain: float) -> dict:
    cell = lambda v: {"camera": {"x": v, "z": 0.5}, "toe": {"x": v, "z": 0.5}}  # noqa: E731
    return {
        "terrain": "stair_up",
        "ate_cm": {
            "filter": cell(filter_x),
            "smoother": cell(0.4),
            "batch": cell(0.3),
            "icp_only": cell(icp_x),
            "imu_only": cell(90.0),
        },
        "terrain_classification": {"accuracy_visible": terrain},
        "stance_detection": {"precision": 0.9, "recall": 0.8},
        "frontend": {"displacement_nees": {"mean": 0.5, "within_95": 0.99}},
        "health": {"warnings": []},
        "map": {"rise_error_mm": 1.0, "tread_error_mm": 2.0},
    }


def test_summary_checks_each_aim_and_reports_failed_trials() -> None:
    results = [
        {"condition": "reference", "seed": 1000, "metrics": _metrics(1.0, 50.0, 0.99)},
        {"condition": "reference", "seed": 1001, "metrics": _metrics(1.4, 50.0, 0.97)},
        {"condition": "fps_15", "seed": 1000, "metrics": _metrics(3.0, 50.0, 0.99)},
        {"condition": "tof_gaps", "seed": 1000, "metrics": _metrics(1.5, 1.0, 0.5)},
        {"condition": "tof_gaps", "seed": 1001, "error": "SimulationError: boom"},
    ]
    s = summarise_sweep(results)["conditions"]
    assert s["reference"]["ate_cm"]["filter"]["toe"]["x"] == pytest.approx(1.2)
    assert s["reference"]["misses"] == []
    assert any(f"> {AIM_FUSED_CM:g} cm" in m for m in s["fps_15"]["misses"])
    tof = s["tof_gaps"]["misses"]
    assert any("ICP-only" in m for m in tof)  # 1.5 cm is above ICP-only's 1.0 cm
    assert any("terrain accuracy" in m for m in tof)
    assert any("failed" in m for m in tof)
    md = sweep_markdown(summarise_sweep(results), "vio-graph evaluate --sweep", 2)
    assert "| reference |" in md and "Conditions meeting every aim: 1 of 3" in md
    assert "boom" in md


def _with_clearance(m: dict, p95_mm: float, within_1: float) -> dict:
    block = {
        "error_mm": {"median": p95_mm / 3, "p95": p95_mm, "n": 100},
        "within_1sigma": within_1,
        "within_2sigma": 0.95,
        "near_trip": {"events": 1, "warnings": 2, "recall": 1.0, "min_lead_ms": 150.0},
    }
    m["clearance"] = {
        "filter": block,
        "smoother": {"error_mm": {"median": 1.0, "p95": p95_mm / 2, "n": 100}},
    }
    m["placement"] = {"filter": {"error_mm": {"median": 4.0, "p95": 9.0, "n": 8}}}
    return m


def test_clearance_aim_is_judged_on_the_worst_seed() -> None:
    results = [
        {
            "condition": "reference",
            "seed": 1000,
            "metrics": _with_clearance(_metrics(1, 5, 1), 6, 0.6),
        },
        {
            "condition": "reference",
            "seed": 1001,
            "metrics": _with_clearance(_metrics(1, 5, 1), 8, 0.7),
        },
        {
            "condition": "fps_15",
            "seed": 1000,
            "metrics": _with_clearance(_metrics(1, 5, 1), 4, 0.7),
        },
        {
            "condition": "fps_15",
            "seed": 1001,
            "metrics": _with_clearance(_metrics(1, 5, 1), 12, 0.7),
        },
    ]
    s = summarise_sweep(results)["conditions"]
    ref = s["reference"]["clearance"]
    assert ref["filter"]["p95_mm"] == pytest.approx(7.0)
    assert ref["filter"]["worst_p95_mm"] == pytest.approx(8.0)
    assert ref["filter"]["within_1sigma"] == pytest.approx(0.65)
    assert ref["filter"]["near_trip_events"] == 2 and ref["filter"]["min_lead_ms"] == 150.0
    assert ref["smoother"]["p95_mm"] == pytest.approx(3.5) and "batch" not in ref
    assert s["reference"]["clearance_misses"] == []
    # mean p95 8 mm meets the aim, but one seed's 12 mm does not
    assert s["fps_15"]["clearance"]["filter"]["p95_mm"] == pytest.approx(8.0)
    assert any(f"> {AIM_CLEARANCE_P95_MM:g} mm" in m for m in s["fps_15"]["clearance_misses"])
    md = sweep_markdown(summarise_sweep(results), "vio-graph evaluate --sweep", 2)
    assert "## Toe clearance" in md and "Conditions meeting the clearance aim: 1 of 2" in md
    assert "| fps_15 | 2.7 / 8.0 (12.0) | 4.0 | - |" in md
