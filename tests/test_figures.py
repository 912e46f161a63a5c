"""Figures read at a glance: the map is zoomed to the mapped stair with step labels that do not
overlap and a step table; the overview names every line and keeps camera and toe apart."""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np

from tests.test_mapping_export import _scene
from tests.test_mapping_synth import stair_profile
from vio_graph.mapping.export import map_figure
from vio_graph.recording import Recording
from vio_graph.recording.metadata import TerrainInfo

ROOT = Path(__file__).resolve().parents[1]


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_map_zoomed_labels_apart_and_table() -> None:
    terrain = stair_profile(0.147, 0.28, 8, up=True)
    terrain_map, geometry = _scene(terrain, 2.4)
    # the true profile goes on for 10 m past the stair, as on a real landing: not zoomed to
    prof = [
        *terrain.profile_xz_m,
        (terrain.profile_xz_m[-1][0] + 10.0, terrain.profile_xz_m[-1][1]),
    ]
    far = TerrainInfo(
        kind=terrain.kind, params=terrain.params, profile_xz_m=prof, edges_xz_m=terrain.edges_xz_m
    )
    cams = np.array([kf.camera_xz_m for kf in terrain_map.keyframes])
    fig = map_figure(terrain_map.points_xz_m, geometry, far, camera_xz_m=cams)
    fig.canvas.draw()
    ax, side = fig.axes[0], fig.axes[1]
    pts = terrain_map.points_xz_m
    data_x = max(pts[:, 0].max(), cams[:, 0].max()) - min(pts[:, 0].min(), cams[:, 0].min())
    x0, x1 = ax.get_xlim()
    assert x1 - x0 < data_x + 0.5  # zoomed to the map and camera, not the 10 m profile
    assert len(geometry.steps) >= 4
    renderer = fig.canvas.get_renderer()
    labels = [t for t in ax.texts if t.get_text()]
    assert [t.get_text() for t in labels] == [str(k + 1) for k in range(len(geometry.steps))]
    boxes = [t.get_window_extent(renderer) for t in labels]
    assert not any(_overlaps(a, b) for a, b in combinations(boxes, 2))
    # the step table beside the plot (one text block): header, rule, one row per step, rise in mm
    (table,) = [t for t in side.texts if t.get_text().lstrip().startswith("#")]
    lines = table.get_text().splitlines()
    assert lines[0].split()[:3] == ["#", "kind", "rise"]
    assert len(lines) == 2 + len(geometry.steps)
    assert float(lines[2].split()[2]) == round(1000 * geometry.steps[0].rise_m, 1)
    assert not _overlaps(table.get_window_extent(renderer), side.get_legend().get_window_extent())
    legend = side.get_legend()
    assert "risers" in [t.get_text() for t in legend.get_texts()]


def test_step_table_text_caps_the_rows() -> None:
    from vio_graph.mapping.export import step_table_text

    rows = [[str(k), "up", "147.0", "280.0", "1.00, 0.15"] for k in range(1, 6)]
    text = step_table_text(rows, ["#", "kind", "rise mm", "tread mm", "nosing x, z m"], 3)
    lines = text.splitlines()
    assert len(lines) == 2 + 3 + 1 and lines[-1] == "... 2 more in steps.csv"
    assert len({len(line) for line in lines[:5]}) == 1  # fixed width: the columns line up
    assert lines[2].split() == ["1", "up", "147.0", "280.0", "1.00,", "0.15"]


def test_overview_names_every_line_and_separates_camera_and_toe() -> None:
    from vio_graph.viz.plots import overview_figure

    rec = Recording.open(ROOT / "data" / "sample")
    gt = rec.groundtruth.trajectories
    t_s = np.linspace(gt["toe"].timestamp_s[0], gt["toe"].timestamp_s[-1], 100)

    def at(body: str, dz: float) -> np.ndarray:
        g = gt[body]
        return np.column_stack(
            [
                np.interp(t_s, g.timestamp_s, g.position_m[:, 0]),
                np.interp(t_s, g.timestamp_s, g.position_m[:, 2]) + dz,
            ]
        )

    paths = {
        m: {"camera": at("camera", dz), "toe": at("toe", dz)}
        for m, dz in (("filter", 0.01), ("smoother", 0.005), ("imu_only", 3.0))
    }
    metrics = {
        "ate_cm": {
            "filter": {
                "toe": {"x": 1.0, "z": 1.0, "total": 1.4},
                "camera": {"x": 1.0, "z": 1.0, "total": 1.4},
            }
        }
    }
    fig = overview_figure(rec, t_s, paths, metrics)
    fig.canvas.draw()
    titles = [a.get_title() for a in fig.axes]
    assert any("camera path" in t for t in titles) and any("toe path" in t for t in titles)
    for ax in fig.axes:
        lines = [ln for ln in ax.get_lines() if len(ln.get_xdata()) > 10]
        named = {t.get_text() for t in ax.get_legend().get_texts()}
        for ln in lines:
            if ln.get_label().startswith("_"):  # the terrain outline, drawn under its fill
                assert ln.get_color() == "0.35"
                continue
            assert ln.get_label() in named
        assert "ground truth" in named and any(n.startswith("filter (ATE") for n in named)
        assert not any("imu_only" in n for n in named)  # leaves the plot: not drawn
    toe_ax = next(a for a in fig.axes if "toe path" in a.get_title())
    z0, z1 = toe_ax.get_ylim()
    toe_z = gt["toe"].position_m[:, 2]
    assert z1 - z0 < (toe_z.max() - toe_z.min()) + 1.0  # zoomed to the trial


def test_plot_indices_keep_every_extreme_of_a_long_series() -> None:
    """A 10-minute trial's toe height (18,000 frames, one 3-frame lift per step) drawn from
    at most 4000 samples: every lift's peak, the global extremes, the first and last sample
    stay; a short series is drawn whole."""
    from vio_graph.viz.decimate import plot_indices

    MAX_PLOT_POINTS = 4000  # one lift per bucket (the figures' default, 2000, merges pairs)

    n = 18_000
    z = np.zeros(n)
    peaks = np.arange(40, n - 3, 33)
    for k in peaks:
        z[k : k + 3] = [0.05, 0.1 + 1e-6 * k, 0.05]
    xz = np.column_stack([np.linspace(0.0, 80.0, n), z])
    idx = plot_indices(xz, max_points=MAX_PLOT_POINTS)
    assert idx.size <= MAX_PLOT_POINTS
    assert np.all(np.diff(idx) > 0)
    assert idx[0] == 0 and idx[-1] == n - 1
    assert set((peaks + 1).tolist()) <= set(idx.tolist())  # every lift's top
    np.testing.assert_array_equal(plot_indices(z[:300]), np.arange(300))
    z_nan = z.copy()
    z_nan[::7] = np.nan  # NaN samples never hide a peak
    assert set((peaks + 1).tolist()) - set(np.flatnonzero(np.isnan(z_nan)).tolist()) <= set(
        plot_indices(z_nan, max_points=MAX_PLOT_POINTS).tolist()
    )


def test_overview_png_is_the_default_encodings_pixels(tmp_path: Path) -> None:
    """plot_run_overview writes through save_png (zlib level PNG_COMPRESS_LEVEL): decoded,
    the same pixels and text chunks as the same figure saved matplotlib's default way."""
    from PIL import Image

    from vio_graph.viz.plots import overview_figure, plot_run_overview

    rec = Recording.open(ROOT / "data" / "sample")
    toe = rec.groundtruth.trajectories["toe"]
    t_s = toe.timestamp_s[::10]
    paths = {"filter": {"camera": toe.xz_at(t_s) + [0.0, 0.5], "toe": toe.xz_at(t_s)}}
    ours = plot_run_overview(tmp_path / "overview.png", rec, t_s, paths, {})
    default = tmp_path / "default.png"
    overview_figure(rec, t_s, paths, {}).savefig(default, dpi=110)
    assert ours.read_bytes() != default.read_bytes()
    with Image.open(ours) as a, Image.open(default) as b:
        assert a.size == b.size and a.text == b.text
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
