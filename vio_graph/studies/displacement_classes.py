"""Consistency of the front end's visual displacements split by where they came from.

``python -m vio_graph.studies.displacement_classes REC [REC ...] [--config C.yaml]`` replays
each recording (filter only, clean) and prints, per class, the number of displacements, the
2-dof NEES (what the run metrics report) and the x-only NEES e_x^2 / (C_xx + floor^2): a
consistent x claim has mean ~1 and ~95 % of values below 3.84. Classes: the frame's terrain
label crossed with the tracker path (``corner``: a corner was detected this frame, the corner
ICP or its fallback; ``profile``: no corner, the profile fallback). Pure diagnosis, no output
files; the same numbers for the same code and recordings.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from vio_graph.config import PipelineConfig, load_config
from vio_graph.recording.reader import Recording
from vio_graph.replay import FrameLog, Replay
from vio_graph.types import Displacement2D

#: chi^2 95 % quantiles, 1 and 2 dof
_CHI2_95_1DOF = 3.841
_CHI2_95_2DOF = 5.991
#: a displacement "claims x" when its x sigma is below this (m); the rest carry the capped
#: variance of an unobservable direction and say nothing about x
CLAIMS_X_M = 0.1


def nees_by_class(
    displacements: list[Displacement2D],
    classes: list[str],
    true_delta_xz_m: NDArray[np.float64],
    floor_m: float = 0.0,
) -> dict[str, dict[str, float]]:
    """Per class label: n, 2-dof NEES mean / share within 95 %, x-only NEES mean / share
    within 95 %, the same x NEES over the displacements that claim x (x sigma below
    ``CLAIMS_X_M``), claimed x sigma median (mm) and x error RMS (mm). ``true_delta_xz_m`` (N, 2):
    the true camera displacement of each displacement's interval; ``floor_m`` is added to both
    axes' sigma as the filter does."""
    est = np.array([d.delta_xz_m for d in displacements], dtype=float).reshape(-1, 2)
    cov = np.array([d.cov_m2 for d in displacements], dtype=float).reshape(-1, 2, 2)
    cov = cov + np.eye(2) * floor_m**2
    err = est - np.asarray(true_delta_xz_m, dtype=float).reshape(-1, 2)
    labels = np.asarray(classes)
    out: dict[str, dict[str, float]] = {}
    for c in sorted(set(classes)):
        m = labels == c
        e, C = err[m], cov[m]
        n2 = np.einsum("ni,ni->n", e, np.linalg.solve(C, e[..., None])[..., 0])
        nx = e[:, 0] ** 2 / C[:, 0, 0]
        claim = C[:, 0, 0] < CLAIMS_X_M**2
        out[c] = {
            "n": int(m.sum()),
            "nees2_mean": float(np.mean(n2)),
            "nees2_within95": float(np.mean(n2 < _CHI2_95_2DOF)),
            "neesx_mean": float(np.mean(nx)),
            "neesx_within95": float(np.mean(nx < _CHI2_95_1DOF)),
            "n_claim_x": int(claim.sum()),
            "neesx_claim_mean": float(np.mean(nx[claim])) if claim.any() else float("nan"),
            "neesx_claim_within95": float(np.mean(nx[claim] < _CHI2_95_1DOF))
            if claim.any()
            else float("nan"),
            "sigx_med_mm": float(1e3 * np.median(np.sqrt(C[:, 0, 0]))),
            "errx_rms_mm": float(1e3 * np.sqrt(np.mean(e[:, 0] ** 2))),
        }
    return out


def classify_recording(
    recording: Path | str, config: PipelineConfig
) -> tuple[list[Displacement2D], list[str], NDArray[np.float64]]:
    """Replay one recording (filter only) and return its displacements, their class labels
    (``<terrain>/<corner|profile>``) and the true camera displacement of each."""
    rec = Recording.open(recording)
    if rec.groundtruth is None:
        raise ValueError(f"{recording}: no ground truth")
    labels: list[str] = []
    original_add = FrameLog.add

    def add(self: FrameLog, record) -> None:  # the frame's class next to its displacement
        original_add(self, record)
        if record.displacement is not None:
            path = "profile" if record.frontend.corner is None else "corner"
            labels.append(f"{record.frontend.terrain.value}/{path}")

    from vio_graph.viz.rerun_logger import NullVisualizer

    FrameLog.add = add  # type: ignore[method-assign]
    try:
        replay = Replay(rec, config, {"filter"}, NullVisualizer())
        lg = replay.run()
    finally:
        FrameLog.add = original_add  # type: ignore[method-assign]
    labels = labels[-len(lg.displacements) :] if lg.displacements else []  # after a re-run
    cam = rec.groundtruth.trajectories["camera"]
    t0 = np.array([d.t0_s for d in lg.displacements])
    t1 = np.array([d.t1_s for d in lg.displacements])
    return lg.displacements, labels, cam.xz_at(t1) - cam.xz_at(t0)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+")
    ap.add_argument("--config", default=None)
    args = ap.parse_args(argv)
    config = load_config(args.config)
    floor = config.filter.measurement_noise_floor_m
    per: dict[str, list] = defaultdict(lambda: [[], [], []])
    for r in args.recordings:
        d, lab, true = classify_recording(r, config)
        for k, v in nees_by_class(d, lab, true, floor).items():
            print(Path(r).name, k, " ".join(f"{a}={b:.3g}" for a, b in v.items()), flush=True)
        scen = Path(r).name.rsplit("_s", 1)[0]
        for key in (scen, "all"):
            per[key][0] += d
            per[key][1] += lab
            per[key][2].append(true)
    print(
        "| set | class | n | NEES 2-dof mean / <95 % | x NEES mean / <95 % | claim x: n | "
        "x NEES mean / <95 % | x sigma med mm | x err rms mm |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for key, (d, lab, trues) in per.items():
        for k, v in nees_by_class(d, lab, np.concatenate(trues), floor).items():
            print(
                f"| {key} | {k} | {v['n']} | {v['nees2_mean']:.2f} / "
                f"{100 * v['nees2_within95']:.0f} % | {v['neesx_mean']:.2f} / "
                f"{100 * v['neesx_within95']:.0f} % | {v['n_claim_x']} | "
                f"{v['neesx_claim_mean']:.2f} / {100 * v['neesx_claim_within95']:.0f} % | "
                f"{v['sigx_med_mm']:.2f} | "
                f"{v['errx_rms_mm']:.2f} |"
            )


if __name__ == "__main__":
    main()
