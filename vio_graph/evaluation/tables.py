"""Aggregate per-trial ATE into mean +- sd per experiment, with the paper's numbers beside.

Pure functions: no file I/O (the CLI writes the markdown this returns).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from vio_graph.errors import EvaluationError
from vio_graph.evaluation.metrics import M_TO_CM, AteResult

#: Toe ATE (cm) of the paper, mean and sd over 5 trials, keyed by experiment then axis.
#: Chen, Chen, Yin, Wang, Huang, Leng and Fu, "Enhancing Prosthetic Safety and Environmental
#: Adaptability: A Visual-Inertial Prosthesis Motion Estimation Approach on Uneven Terrains",
#: Section III (Results): able-bodied upstair / downstair / obstacle (obstacle: visible
#: periods only) and powered-prosthesis upstair.
PAPER_TOE_ATE_CM: Mapping[str, Mapping[str, tuple[float, float]]] = {
    "upstair": {"x": (2.96, 0.92), "z": (2.16, 0.46)},
    "downstair": {"x": (2.79, 0.79), "z": (1.63, 0.23)},
    "obstacle": {"x": (2.20, 0.14), "z": (4.68, 0.47)},
    "prosthesis_upstair": {"x": (4.14, 0.85), "z": (2.73, 0.71)},
}


@dataclass(frozen=True)
class TrialAte:
    """One trial's ATE per axis (m)."""

    experiment: str
    trial: str
    rmse_x_m: float
    rmse_z_m: float

    @classmethod
    def from_result(cls, experiment: str, trial: str, result: AteResult) -> TrialAte:
        return cls(experiment, trial, result.rmse_x_m, result.rmse_z_m)


@dataclass(frozen=True)
class ExperimentSummary:
    """Mean and sample standard deviation (ddof = 1; NaN for a single trial) in cm."""

    experiment: str
    n_trials: int
    x_mean_cm: float
    x_sd_cm: float
    z_mean_cm: float
    z_sd_cm: float


def summarise(trials: Iterable[TrialAte]) -> list[ExperimentSummary]:
    """Group trials by experiment (first-seen order) and compute mean +- sd in cm."""
    groups: dict[str, list[TrialAte]] = {}
    for tr in trials:
        groups.setdefault(tr.experiment, []).append(tr)
    if not groups:
        raise EvaluationError("no trials to summarise")
    out = []
    for name, items in groups.items():
        xz_cm = np.array([[t.rmse_x_m, t.rmse_z_m] for t in items]) * M_TO_CM
        mean = xz_cm.mean(axis=0)
        sd = xz_cm.std(axis=0, ddof=1) if len(items) > 1 else np.full(2, np.nan)
        out.append(
            ExperimentSummary(
                name, len(items), float(mean[0]), float(sd[0]), float(mean[1]), float(sd[1])
            )
        )
    return out


def _pm(mean: float, sd: float) -> str:
    if np.isnan(sd):
        return f"{mean:.2f}"
    return f"{mean:.2f} ± {sd:.2f}"


def markdown_table(
    summaries: Iterable[ExperimentSummary],
    paper: Mapping[str, Mapping[str, tuple[float, float]]] = PAPER_TOE_ATE_CM,
    title: str = "Toe ATE (cm), mean ± sd over trials",
) -> str:
    """Markdown table: per experiment, our x / z ATE beside the paper's (— where absent)."""
    lines = [
        f"**{title}**",
        "",
        "| experiment | trials | x ours | x paper | z ours | z paper |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for s in summaries:
        ref = paper.get(s.experiment)
        px = _pm(*ref["x"]) if ref else "—"
        pz = _pm(*ref["z"]) if ref else "—"
        lines.append(
            f"| {s.experiment} | {s.n_trials} | {_pm(s.x_mean_cm, s.x_sd_cm)} | {px} | "
            f"{_pm(s.z_mean_cm, s.z_sd_cm)} | {pz} |"
        )
    return "\n".join(lines) + "\n"


def report_header(title: str, command: str) -> list[str]:
    """The first lines of a generated report page: its title and the command that
    reproduces it, as markdown lines."""
    return [f"# {title}", "", "Reproduce with:", "", "```bash", command, "```", ""]
