"""Draw the smoother's factor graph (docs/figures/factor_graph.png).

Run: python -m vio_graph.viz.graph_figure docs/figures/factor_graph.png
"""

from __future__ import annotations

import sys
from pathlib import Path

from vio_graph.io_utils import atomic_path


def draw_factor_graph(path: Path, n_keyframes: int = 4) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 5.2))
    ax.set_xlim(-0.8, 3 * (n_keyframes - 1) + 0.8)
    ax.set_ylim(-2.9, 2.4)
    ax.axis("off")
    xs = [3.0 * i for i in range(n_keyframes)]
    rows = {"X": 0.9, "V": 0.0, "B": -0.9}

    def node(x: float, y: float, label: str, color: str) -> None:
        ax.add_patch(plt.Circle((x, y), 0.3, color=color, ec="k", zorder=3))
        ax.text(x, y, label, ha="center", va="center", fontsize=10, zorder=4)

    def factor(x: float, y: float, color: str, ends: list[tuple[float, float]], label=None) -> None:
        for ex, ey in ends:
            ax.plot([x, ex], [y, ey], color="0.4", lw=1, zorder=1)
        ax.add_patch(plt.Rectangle((x - 0.1, y - 0.1), 0.2, 0.2, color=color, ec="k", zorder=2))
        if label:
            ax.text(x, y + 0.18, label, ha="center", va="bottom", fontsize=7)

    for i, x in enumerate(xs):
        node(x, rows["X"], f"X{i}", "#9ecae1")
        node(x, rows["V"], f"V{i}", "#c7e9c0")
        node(x, rows["B"], f"B{i}", "#fdd0a2")
        factor(x - 0.55, rows["X"] + 0.75, "#6baed6", [(x, rows["X"])], "attitude + planar")
    for i in range(n_keyframes - 1):
        a, b = xs[i], xs[i + 1]
        m = 0.5 * (a + b)
        factor(
            m,
            0.0,
            "#31a354",
            [
                (a, rows["X"]),
                (b, rows["X"]),
                (a, rows["V"]),
                (b, rows["V"]),
                (a, rows["B"]),
                (b, rows["B"]),
            ],
            "CombinedImuFactor",
        )
        factor(m, 1.75, "#e6550d", [(a, rows["X"]), (b, rows["X"])], "ICP displacement (robust)")
    factor(
        xs[0] - 0.55,
        -1.6,
        "0.2",
        [(xs[0], rows["X"]), (xs[0], rows["V"]), (xs[0], rows["B"])],
        "first-keyframe prior",
    )
    # corner landmarks seen from several keyframes
    for j, (seen, lx) in enumerate(((range(0, 3), 3.0), (range(2, n_keyframes), 7.5))):
        node(lx, -2.35, f"L{j}", "#fcbba1")
        for i in seen:
            fx = 0.5 * (xs[i] + lx)
            factor(fx, -1.65 if j == 0 else -1.45, "#a50f15", [(xs[i], rows["X"]), (lx, -2.35)])
    ax.text(
        xs[-1] + 0.5,
        -2.35,
        "corner landmarks: same nosing\nseen from many keyframes (robust)",
        fontsize=8,
        va="center",
    )
    ax.set_title(
        "vio_graph smoother: keyframe nodes X (IMU pose), V (velocity), B (IMU bias), "
        "L (stair corners)",
        fontsize=10,
    )
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


if __name__ == "__main__":
    draw_factor_graph(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/figures/factor_graph.png"))
