"""vio_graph: sagittal-plane visual-inertial motion estimation for prostheses on stairs."""

__version__ = "0.1.0"
