"""Trajectory evaluation: time association, ATE / APE / RPE, result tables."""

from vio_graph.evaluation.association import AssociatedTrajectories, associate
from vio_graph.evaluation.metrics import (
    Alignment,
    ApeResult,
    AteResult,
    ErrorStats,
    RpeResult,
    align,
    ape,
    ate_per_axis,
    rpe,
    umeyama_alignment,
)
from vio_graph.evaluation.tables import (
    PAPER_TOE_ATE_CM,
    ExperimentSummary,
    TrialAte,
    markdown_table,
    summarise,
)

__all__ = [
    "PAPER_TOE_ATE_CM",
    "Alignment",
    "ApeResult",
    "AssociatedTrajectories",
    "AteResult",
    "ErrorStats",
    "ExperimentSummary",
    "RpeResult",
    "TrialAte",
    "align",
    "ape",
    "associate",
    "ate_per_axis",
    "markdown_table",
    "rpe",
    "summarise",
    "umeyama_alignment",
]
