"""The on-disk recording format: validating reader, atomic writer, TUM trajectories."""

from vio_graph.recording.reader import Recording
from vio_graph.recording.writer import write_recording

__all__ = ["Recording", "write_recording"]
