"""PNG plots of a run (matplotlib, Agg backend; no display needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.io_utils import atomic_path

MODE_STYLE = {
    "filter": ("tab:orange", "-"),
    "smoother": ("tab:blue", "-"),
    "batch": ("tab:purple", "--"),
    "imu_only": ("0.6", ":"),
    "icp_only": ("tab:red", ":"),
}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_run_overview(path: Path, rec, t_s: NDArray[np.float64],
                      paths: dict[str, dict[str, NDArray[np.float64]]],
                      metrics: dict[str, Any]) -> Path:
    """Sagittal view (terrain, camera and toe paths) and toe x / z against time."""
    plt = _plt()
    fig = plt.figure(figsize=(13, 8), constrained_layout=True)
    gs = fig.add_gridspec(2, 2, width_ratios=[1.3, 1])
    ax = fig.add_subplot(gs[:, 0])
    prof = np.asarray(rec.metadata.terrain.profile_xz_m, dtype=float)
    if prof.size:
        ax.fill_between(prof[:, 0], prof[:, 1], prof[:, 1].min() - 0.1, color="0.85", step=None)
        ax.plot(prof[:, 0], prof[:, 1], color="0.3", lw=1)
    gt = rec.groundtruth
    if gt is not None:
        for body in ("camera", "toe"):
            g = gt.trajectories[body]
            ax.plot(g.position_m[:, 0], g.position_m[:, 2], color="tab:green", lw=2, alpha=0.7,
                    label=f"ground truth {body}" if body == "toe" else None)
    for mode, bodies in paths.items():
        if mode not in MODE_STYLE:
            continue
        c, ls = MODE_STYLE[mode]
        if mode in ("imu_only",):
            continue  # diverges off the plot
        ax.plot(bodies["toe"][:, 0], bodies["toe"][:, 1], color=c, ls=ls, lw=1.2, label=f"{mode} toe")
        ax.plot(bodies["camera"][:, 0], bodies["camera"][:, 1], color=c, ls=ls, lw=0.8, alpha=0.6)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("z up (m)")
    ax.set_title(f"{metrics.get('scenario') or rec.root.name}: sagittal paths (camera and toe)")
    ax.legend(loc="upper left", fontsize=8)
    for row, (axis, k) in enumerate((("x", 0), ("z", 1))):
        a = fig.add_subplot(gs[row, 1])
        if gt is not None:
            g = gt.trajectories["toe"]
            a.plot(g.timestamp_s, g.position_m[:, 0 if k == 0 else 2], color="tab:green", lw=2,
                   label="ground truth")
        for mode, bodies in paths.items():
            if mode in MODE_STYLE and mode != "imu_only":
                c, ls = MODE_STYLE[mode]
                ate = metrics.get("ate_cm", {}).get(mode, {}).get("toe", {}).get(axis)
                lbl = f"{mode}" + (f" (ATE {ate:.1f} cm)" if ate is not None else "")
                a.plot(t_s, bodies["toe"][:, k], color=c, ls=ls, lw=1, label=lbl)
        a.set_ylabel(f"toe {axis} (m)")
        a.set_xlabel("time (s)")
        a.legend(fontsize=8)
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return Path(path)
