"""Simulator: terrain meshes, gait, ToF camera, IMU, joints and mocap -> recordings."""

from vio_graph.sim.config import ScenarioConfig, load_scenario
from vio_graph.sim.trial import SimulatedTrial, simulate, simulate_trial

__all__ = ["ScenarioConfig", "SimulatedTrial", "load_scenario", "simulate", "simulate_trial"]
