"""PNG plots of a run (matplotlib figures on an Agg canvas; no display, no pyplot).

The figures of ``vio-graph run`` (overview, clearance) use a fixed layout (no constrained or
tight layout pass, which lays every text out a second time) and draw every line from at most
:data:`vio_graph.viz.decimate.MAX_LINE_POINTS` points that keep its extremes
(:func:`vio_graph.viz.decimate.plot_indices`), so their cost does not grow with the trial;
they and the map figure are written by :func:`save_png` at zlib level
:data:`PNG_COMPRESS_LEVEL`.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.io_utils import atomic_path
from vio_graph.viz.decimate import plot_indices

MODE_STYLE = {
    "filter": ("tab:orange", "-"),
    "smoother": ("tab:blue", "-"),
    "batch": ("tab:purple", "--"),
    "imu_only": ("0.6", ":"),
    "icp_only": ("tab:red", ":"),
}


#: zlib effort of the run's PNG figures (overview, clearance, map): the same pixels as
#: matplotlib's default (Pillow's level 6) for ~60 % of its encoding CPU (~0.1 s a run with
#: plots; 3 of 13 figure-drawing tenths on a 60 s trial), files ~4 % larger
PNG_COMPRESS_LEVEL = 3


def save_png(fig: Any, path: Path, **kwargs: Any) -> None:
    """``fig.savefig(path, format="png", **kwargs)`` at zlib level :data:`PNG_COMPRESS_LEVEL`."""
    fig.savefig(path, format="png", pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL}, **kwargs)


@contextlib.contextmanager
def _quiet_axes_log():
    """Silence matplotlib's 'Ignoring fixed x limits to fulfill fixed data aspect' notice."""
    logger = logging.getLogger("matplotlib.axes._base")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def new_figure(**kwargs: Any) -> Any:
    """A matplotlib Figure on its own Agg canvas (not registered with pyplot, so nothing to
    close and no GUI backend); ``kwargs`` go to ``Figure``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def _line(ax: Any, x: NDArray[np.float64], y: NDArray[np.float64], *args: Any, **kw: Any) -> Any:
    """``ax.plot(x, y, ...)`` through at most MAX_LINE_POINTS points keeping the extremes of
    both coordinates (a path in the x-z plane or a series against time alike)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    keep = plot_indices(np.column_stack([x, y]))
    return ax.plot(x[keep], y[keep], *args, **kw)


def zoom_limits(
    arrays: list[NDArray[np.float64]], margin_m: float = 0.12
) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """x and z limits (m) around the finite points of ``arrays`` (each (N, 2), None or empty
    ones skipped), grown by ``margin_m``; None when there is no point."""
    pts = [a[np.all(np.isfinite(a), axis=1)] for a in arrays if a is not None and len(a)]
    pts = [a for a in pts if a.size]
    if not pts:
        return None
    allp = np.vstack(pts)
    lo, hi = allp.min(axis=0) - margin_m, allp.max(axis=0) + margin_m
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


#: fused modes and baselines drawn in the overview (the IMU-only baseline leaves the plot)
_OVERVIEW_MODES = ("filter", "smoother", "batch", "icp_only")


def plot_run_overview(
    path: Path,
    rec,
    t_s: NDArray[np.float64],
    paths: dict[str, dict[str, NDArray[np.float64]]],
    metrics: dict[str, Any],
) -> Path:
    """Write :func:`overview_figure` as a PNG (atomically)."""
    fig = overview_figure(rec, t_s, paths, metrics)
    with atomic_path(Path(path), suffix=".png") as tmp:
        save_png(fig, tmp, dpi=110)
    return Path(path)


def overview_figure(
    rec,
    t_s: NDArray[np.float64],
    paths: dict[str, dict[str, NDArray[np.float64]]],
    metrics: dict[str, Any],
) -> Any:
    """Left: the camera path and the toe path in the sagittal plane over the terrain, one panel
    each, zoomed to the trial (ground truth and fused estimates); right: toe x and z against
    time. Colour = estimator (ground truth green), the same in every panel; every line is in a
    legend with its toe ATE."""
    fig = new_figure(figsize=(13, 8))
    # fixed margins (fractions of the 13 x 8 in figure) instead of a layout engine: one text pass
    gs = fig.add_gridspec(
        2,
        2,
        width_ratios=[1.2, 1],
        left=0.055,
        right=0.99,
        bottom=0.06,
        top=0.965,
        wspace=0.12,
        hspace=0.22,
    )
    prof = np.asarray(rec.metadata.terrain.profile_xz_m, dtype=float)
    gt = rec.groundtruth
    ate = metrics.get("ate_cm", {})
    modes = [m for m in _OVERVIEW_MODES if m in paths]

    def label(mode: str, body: str) -> str:
        a = ate.get(mode, {}).get(body)
        return f"{mode} (ATE {a['total']:.1f} cm in x-z)" if a and "total" in a else mode

    title = metrics.get("scenario") or rec.root.name
    for row, body in enumerate(("camera", "toe")):
        ax = fig.add_subplot(gs[row, 0])
        if prof.size:
            ax.fill_between(
                prof[:, 0], prof[:, 1], prof[:, 1].min() - 1.0, color="0.88", label="terrain (true)"
            )
            _line(ax, prof[:, 0], prof[:, 1], color="0.35", lw=1)
        zoom = []
        if gt is not None:
            g = gt.trajectories[body].position_m[:, [0, 2]]
            _line(ax, g[:, 0], g[:, 1], color="tab:green", lw=2.2, alpha=0.8, label="ground truth")
            zoom.append(g)
        for mode in modes:
            c, ls = MODE_STYLE[mode]
            xz = paths[mode][body]
            _line(ax, xz[:, 0], xz[:, 1], color=c, ls=ls, lw=1.2, label=label(mode, body))
            if mode != "icp_only" or gt is None:
                zoom.append(xz)
        limits = zoom_limits(zoom)
        if limits is not None:
            ax.set_xlim(*limits[0])
            ax.set_ylim(*limits[1])
        # equal aspect by widening one axis range around the zoom (matplotlib logs that it
        # overrides one of the limits we set: intended, so not logged)
        with _quiet_axes_log():
            ax.set_aspect("equal", adjustable="datalim")
            ax.apply_aspect()
        xlim, ylim = ax.get_xlim(), ax.get_ylim()  # keep them: drawing re-applies the aspect
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        ax.set_xlabel("x forward (m)")
        ax.set_ylabel("z up (m)")
        ax.set_title(f"{title}: {body} path (sagittal plane)", y=1.0)  # y: no auto-placement
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    for row, (axis, k) in enumerate((("x", 0), ("z", 1))):
        a = fig.add_subplot(gs[row, 1])
        if gt is not None:
            g = gt.trajectories["toe"]
            _line(
                a,
                g.timestamp_s,
                g.position_m[:, 0 if k == 0 else 2],
                color="tab:green",
                lw=2.2,
                alpha=0.8,
                label="ground truth",
            )
        for mode in modes:
            c, ls = MODE_STYLE[mode]
            v = ate.get(mode, {}).get("toe", {}).get(axis)
            lbl = mode + (f" (ATE {v:.1f} cm)" if v is not None else "")
            _line(a, t_s, paths[mode]["toe"][:, k], color=c, ls=ls, lw=1.1, label=lbl)
        a.set_ylabel(f"toe {axis} (m)")
        a.set_xlabel("time (s)")
        a.set_title(f"toe {axis} against time", y=1.0)
        a.grid(alpha=0.3)
        a.legend(fontsize=8, loc="best")
    return fig


def plot_toe_bands(path: Path, runs, modes: tuple[str, ...] = ("filter", "smoother")) -> Path:
    """Fig. 5 style: per experiment, toe x and z against time since the trial start; mean +- sd
    over trials of each mode's estimate (band) and of the ground truth (line)."""
    from vio_graph.recording.tum import read_tum

    exps = list(dict.fromkeys(r.experiment for r in runs))
    fig = new_figure(figsize=(4.2 * len(exps), 6.5), layout="constrained")
    axes = fig.subplots(2, len(exps), squeeze=False)
    for col, exp in enumerate(exps):
        rs = [r for r in runs if r.experiment == exp]
        series: dict[str, list[NDArray[np.float64]]] = {m: [] for m in (*modes, "gt")}
        grids = []
        for r in rs:
            gt = read_tum(Path(r.recording) / "groundtruth" / "toe.tum")
            t0 = gt.timestamp_s[0]
            grids.append(gt.timestamp_s[-1] - t0)
        t = np.arange(0.0, min(grids), 1.0 / 30.0)
        for r in rs:
            gt = read_tum(Path(r.recording) / "groundtruth" / "toe.tum")
            t0 = gt.timestamp_s[0]
            series["gt"].append(
                np.column_stack(
                    [np.interp(t + t0, gt.timestamp_s, gt.position_m[:, k]) for k in (0, 2)]
                )
            )
            for m in modes:
                f = Path(r.results) / "trajectories" / f"{m}_toe.tum"
                if f.is_file():
                    e = read_tum(f)
                    series[m].append(
                        np.column_stack(
                            [np.interp(t + t0, e.timestamp_s, e.position_m[:, k]) for k in (0, 2)]
                        )
                    )
        for row, axis in enumerate(("x", "z")):
            ax = axes[row, col]
            for m in (*modes, "gt"):
                if not series[m]:
                    continue
                arr = np.stack(series[m])[:, :, row]
                mean, sd = arr.mean(axis=0), arr.std(axis=0)
                color = "tab:green" if m == "gt" else MODE_STYLE[m][0]
                label = "ground truth" if m == "gt" else m
                ax.plot(t, mean, color=color, lw=2 if m == "gt" else 1.2, label=label)
                ax.fill_between(t, mean - sd, mean + sd, color=color, alpha=0.2)
            ax.set_xlabel("time since start (s)")
            ax.set_ylabel(f"toe {axis} (m)")
            if row == 0:
                ax.set_title(f"{exp} (n={len(rs)})")
            ax.legend(fontsize=7)
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    return Path(path)


def plot_batch_summary(path: Path, rows: list[dict[str, Any]]) -> Path:
    """``vio-graph batch``: toe ATE x and z (cm) per trial (and config), one bar per mode,
    every mode named in the legend; a failed task is a red 'failed' mark in its slot."""
    groups = list(dict.fromkeys((r["trial"], r["config"]) for r in rows))
    n_cfg = len({c for _, c in groups})
    modes = list(dict.fromkeys(r["mode"] for r in rows))
    labels = [t if n_cfg == 1 else f"{t}\n{c}" for t, c in groups]
    width_in = min(18.0, max(6.0, 0.35 * len(groups) * max(1, len(modes)) + 2.5))
    fig = new_figure(figsize=(width_in, 6.0), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    bar_w = 0.8 / max(1, len(modes))
    x0 = np.arange(len(groups), dtype=float)
    by = {(r["trial"], r["config"], r["mode"]): r for r in rows}
    for ax, axis in zip(axes, ("x", "z"), strict=True):
        top = 0.0
        for j, mode in enumerate(modes):
            xs = x0 - 0.4 + bar_w * (j + 0.5)
            vals = []
            for g in groups:
                r = by.get((*g, mode))
                v = r.get(f"toe_{axis}_cm") if r and r["status"] == "ok" else None
                vals.append(np.nan if v is None else float(v))
            color = MODE_STYLE.get(mode, ("0.5", "-"))[0]
            bars = ax.bar(xs, vals, width=bar_w * 0.95, color=color, label=mode)
            if len(groups) * len(modes) <= 24:  # values on the bars while they stay legible
                ax.bar_label(bars, fmt="%.2f", fontsize=7, padding=1)
            finite = [v for v in vals if np.isfinite(v)]
            top = max([top, *finite])
        for j, mode in enumerate(modes):
            xs = x0 - 0.4 + bar_w * (j + 0.5)
            for k, g in enumerate(groups):
                r = by.get((*g, mode))
                if r is not None and r["status"] != "ok":
                    ax.text(
                        xs[k],
                        0.02 * (top or 1.0),
                        "failed",
                        color="tab:red",
                        rotation=90,
                        ha="center",
                        va="bottom",
                        fontsize=8,
                    )
        ax.set_ylim(0, 1.15 * top if top > 0 else 1.0)
        ax.set_ylabel(f"toe ATE {axis} (cm)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(title="mode", fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[0].set_title(f"Toe ATE per trial and mode ({len(rows)} tasks)")
    axes[1].set_xticks(
        x0,
        labels,
        rotation=30 if len(groups) > 6 else 0,
        ha="right" if len(groups) > 6 else "center",
        fontsize=8,
    )
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100)
    return Path(path)


def plot_clearance(
    path: Path,
    t_s: NDArray[np.float64],
    safety: Any,
    truth: dict[str, NDArray[np.float64]] | None,
) -> Path:
    """plots/clearance.png: the online toe clearance (cm) with its 1-sigma band, the predicted
    minimum clearance, the truth when known, near-trip warnings and landings."""

    def col(name: str) -> NDArray[np.float64]:
        column = getattr(safety, "column", None)  # the replay's SafetyLog: no objects rebuilt
        if column is not None:
            return column(name)
        return np.array([getattr(s, name) if s is not None else np.nan for s in safety], float)

    t = np.asarray(t_s, dtype=float)[: len(safety)]
    c, sig = col("clearance_m") * 100, col("clearance_sigma_m") * 100
    pred = col("predicted_min_clearance_m") * 100
    true_c = truth["clearance_m"][: len(t)] * 100 if truth is not None else np.full(len(t), np.nan)
    # one subset for all four series: the band edges stay paired with the line they surround
    keep = plot_indices(np.column_stack([c - sig, c + sig, pred, true_c]))
    fig = new_figure(figsize=(10, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    fig.subplots_adjust(left=0.065, right=0.99, bottom=0.13, top=0.97)  # fixed: no tight pass
    tk = t[keep]
    ax.fill_between(
        tk,
        (c - sig)[keep],
        (c + sig)[keep],
        color="tab:blue",
        alpha=0.25,
        lw=0,
        label="estimate 1-sigma",
    )
    ax.plot(tk, c[keep], color="tab:blue", lw=1.2, label="clearance (filter)")
    ax.plot(tk, pred[keep], color="tab:orange", lw=0.8, label="predicted minimum over the horizon")
    if truth is not None:
        ax.plot(tk, true_c[keep], color="k", lw=1.0, ls="--", label="truth")
    warn = col("near_trip_warning") == 1.0  # False without an estimate (NaN)
    land = col("landing") == 1.0
    if warn.any():
        ax.plot(t[warn], np.zeros(int(warn.sum())), "rv", ms=4, label="near-trip warning")
    if land.any():  # one collection of full-height lines instead of one axvline per landing
        ax.vlines(t[land], 0.0, 1.0, transform=ax.get_xaxis_transform(), color="0.6", lw=0.6)
    ax.axhline(2.0, color="r", lw=0.6, ls=":")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("foot clearance (cm)")
    ax.set_ylim(-3, 30)
    ax.legend(loc="upper right", fontsize=7, ncol=3)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(Path(path), suffix=".png") as tmp:
        save_png(fig, tmp, dpi=100)
    return Path(path)
