"""Exception hierarchy. Library code raises these; only the CLI turns them into messages."""

from __future__ import annotations


class VioGraphError(Exception):
    """Base class of every error vio_graph raises on purpose."""


class ConfigError(VioGraphError):
    """A configuration file or value is invalid."""


class RecordingError(VioGraphError):
    """A recording on disk is missing, malformed or inconsistent.

    The message always names the offending file and, where there is one, the field.
    """

    def __init__(self, path: object, problem: str, field: str | None = None) -> None:
        self.path = str(path)
        self.field = field
        self.problem = problem
        where = f"{self.path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {problem}")


class SimulationError(VioGraphError):
    """The simulator was asked for something it cannot produce (e.g. an unreachable pose)."""


class TerrainTooShortError(SimulationError):
    """The walk runs out of terrain before the trial ends; ``field`` is the terrain length
    (``landing_length_m`` or ``exit_length_m``) that lengthens it."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


class ImplausibleMotionError(SimulationError):
    """The simulated leg moves faster than a human shank can (``vio_graph.sim.plausibility``):
    ``peak_g`` is the peak specific force at the IMU (g) at ``t_s``; the message names the
    terrain or gait parameters of the swing it happened in."""

    def __init__(self, message: str, peak_g: float, t_s: float) -> None:
        super().__init__(message)
        self.peak_g = peak_g
        self.t_s = t_s


class EstimationError(VioGraphError):
    """An estimator was fed data it cannot use (e.g. out-of-order timestamps)."""


class OutputError(VioGraphError):
    """An output folder or file cannot be written as asked."""


class MappingError(VioGraphError):
    """The terrain map or the step extraction was given unusable input (e.g. bad shapes)."""


class FrontendError(VioGraphError):
    """The visual front end was given inputs it cannot use (wrong shapes, non-finite values)."""


class EvaluationError(VioGraphError):
    """Trajectories cannot be compared as asked (no time overlap, too few poses, bad mask)."""


class BagImportError(RecordingError):
    """A ROS bag cannot be imported as asked (missing topic, wrong encoding, empty bag, ...).

    The message names the bag and, where there is one, the topic.
    """
