"""Realism figures of the simulator -> docs/figures/sim_*.png (small PNGs).

Run: python benchmarks/make_sim_figures.py [--out docs/figures] [--seed 1]

sim_joint_angles.png   hip / knee / ankle vs gait phase (steady strides) with published peaks
sim_depth.png          one depth image (upstair)
sim_slice.png          sagittal slice (|x_cam| < 0.05 m) in the ground frame over the profile
sim_imu.png            accelerometer and gyroscope over a few strides (upstair)
sim_legs.png           the leg over the terrain at several instants, four scenarios
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vio_graph.sim import load_scenario, simulate_trial  # noqa: E402
from vio_graph.sim.gait import rot_xz  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# published peak flexion (deg) and ankle range (dorsi -, plantar +): McFadyen & Winter 1988,
# Protopapadaki 2007, Beaulieu 2008 (docs/simulator.md)
PUBLISHED = {
    "upstair": {"knee": 93, "hip": 64, "ankle": (-16, 16)},
    "downstair": {"knee": 89, "hip": 36, "ankle": (-26, 25)},
    "level": {"knee": 62, "hip": 30, "ankle": (-10, 20)},
}
DPI = 80


def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def joint_angles(trials: dict, out: Path) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), sharex=True)
    colors = {"upstair": "C0", "downstair": "C1", "level": "C2"}
    for name, trial in trials.items():
        m = trial.motion
        for s in m.strides[1:-1]:
            dz = s.next_toe_xz_m[1] - s.toe_xz_m[1]
            if s.arrive_kind != s.swing_kind or (name != "level" and abs(dz) < 0.2):
                continue
            sl = (m.t_s >= s.t_contact_s) & (m.t_s < s.t_next_s)
            ph = 100 * (m.t_s[sl] - s.t_contact_s) / (s.t_next_s - s.t_contact_s)
            for ax, y in zip(axes, (m.thigh_pitch_rad, m.knee_rad, m.ankle_rad), strict=True):
                ax.plot(ph, np.degrees(y[sl]), color=colors[name], lw=0.8, alpha=0.7)
        pub = PUBLISHED[name]
        axes[0].axhline(pub["hip"], color=colors[name], ls="--", lw=1)
        axes[1].axhline(pub["knee"], color=colors[name], ls="--", lw=1)
        for a in pub["ankle"]:
            axes[2].axhline(a, color=colors[name], ls="--", lw=1)
        axes[0].plot([], [], color=colors[name], label=name)
    for ax, title in zip(
        axes, ("hip flexion", "knee flexion", "ankle plantarflexion (+)"), strict=True
    ):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("gait phase (% stride, from contact)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("deg (dashed: published peaks)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    _save(fig, out / "sim_joint_angles.png")


def depth_and_slice(trial, out: Path, i: int) -> None:
    depth, _ = trial.render_frame(i)
    fig, ax = plt.subplots(figsize=(4.2, 3.4))
    im = ax.imshow(np.where(depth > 0, depth, np.nan), cmap="viridis")
    fig.colorbar(im, ax=ax, label="depth along optical axis (m); white = invalid")
    ax.set_title(
        f"upstair seed {trial.seed}, frame {i} (t = {trial.frame_true_time_s[i]:.2f} s)", fontsize=8
    )
    ax.set_axis_off()
    fig.tight_layout()
    _save(fig, out / "sim_depth.png")

    cam = trial.camera
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(float)
    p_c = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
    keep = np.abs(p_c[:, 0]) < 0.05
    p_w = p_c[keep] @ trial.R_world_cam[i].T + trial.camera_position_m[i]
    prof = trial.terrain.profile_xz_m
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    ax.plot(prof[:, 0], prof[:, 1], "k-", lw=1, label="true profile")
    ax.plot(p_w[:, 0], p_w[:, 2], ".", ms=1.5, color="C3", label="slice |x_cam| < 0.05 m")
    c = trial.camera_position_m[i]
    ax.plot(c[0], c[2], "^", color="C0", label="camera")
    ax.set_xlim(c[0] - 0.3, c[0] + 1.6)
    ax.set_ylim(c[2] - 1.0, c[2] + 0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world z (m)")
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, out / "sim_slice.png")


def imu(trial, out: Path, t_max_s: float = 4.0) -> None:
    t = trial.imu.timestamp_s
    sl = t <= t_max_s
    fig, axes = plt.subplots(2, 1, figsize=(7, 4), sharex=True)
    for k, lab in enumerate("xyz"):
        axes[0].plot(t[sl], trial.imu.accel_mps2[sl, k], lw=0.8, label=f"accel {lab}")
        axes[1].plot(t[sl], trial.imu.gyro_radps[sl, k], lw=0.8, label=f"gyro {lab}")
    for s in trial.motion.strides:
        if s.t_contact_s <= t_max_s:
            for ax in axes:
                ax.axvline(s.t_contact_s, color="k", lw=0.5, ls=":")
    axes[0].set_ylabel("specific force (m/s^2)")
    axes[1].set_ylabel("angular rate (rad/s)")
    axes[1].set_xlabel("time (s); dotted: foot contact of the instrumented leg")
    for ax in axes:
        ax.legend(fontsize=7, ncol=3, loc="upper right")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, out / "sim_imu.png")


def legs(trials: dict, out: Path) -> None:
    fig, axes = plt.subplots(2, 2, figsize=(10, 6))
    for ax, (name, trial) in zip(axes.ravel(), trials.items(), strict=True):
        m = trial.motion
        prof = trial.terrain.profile_xz_m
        times = np.arange(0.4, min(trial.config.duration_s, 4.5), 0.2)
        idx = np.searchsorted(m.t_s, times)
        x0, x1 = m.hip_xz_m[idx, 0].min() - 0.5, m.hip_xz_m[idx, 0].max() + 0.5
        sel = (prof[:, 0] > x0 - 1) & (prof[:, 0] < x1 + 1)
        ax.fill_between(prof[sel, 0], prof[sel, 1], prof[sel, 1].min() - 0.2, color="0.85")
        ax.plot(prof[sel, 0], prof[sel, 1], "k-", lw=1)
        cols = plt.cm.viridis(np.linspace(0, 1, idx.size))
        for c, i in zip(cols, idx, strict=True):
            pts = np.array(
                [
                    m.hip_xz_m[i],
                    m.knee_xz_m[i],
                    m.ankle_xz_m[i],
                    m.heel_xz_m[i],
                    m.toe_xz_m[i],
                    m.ankle_xz_m[i],
                ]
            )
            ax.plot(pts[:, 0], pts[:, 1], "-", color=c, lw=1)
            p = m.knee_xz_m[i] + rot_xz(m.shank_pitch_rad[i], trial.camera_in_shank_xz_m)
            ax.plot(p[0], p[1], "s", color=c, ms=2.5)
        ax.plot(m.toe_xz_m[:, 0], m.toe_xz_m[:, 1], color="C3", lw=0.5, alpha=0.6)
        ax.set_xlim(x0, x1)
        ax.set_aspect("equal")
        ax.set_title(f"{name} ({trial.config.rig.rig}, {trial.config.gait.pattern})", fontsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle("leg every 0.2 s (squares: camera, red: toe path)", fontsize=9)
    fig.tight_layout()
    _save(fig, out / "sim_legs.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    trials = {
        n: simulate_trial(load_scenario(n), a.seed)
        for n in ("upstair", "downstair", "level", "obstacle", "prosthesis_upstair")
    }
    joint_angles({n: trials[n] for n in ("upstair", "downstair", "level")}, a.out)
    depth_and_slice(trials["upstair"], a.out, 75)
    imu(trials["upstair"], a.out)
    legs({n: trials[n] for n in ("upstair", "downstair", "obstacle", "prosthesis_upstair")}, a.out)
    for p in sorted(a.out.glob("sim_*.png")):
        print(f"{p.relative_to(ROOT)}: {p.stat().st_size / 1024:.0f} kB")


if __name__ == "__main__":
    main()
