"""A 2D robot simulator for tests and benchmarks: worlds of wall segments, trajectories,
a ray-cast laser, wheel odometry and a gyro, with exact ground truth."""
from carto_cli.sim.lidar import Lidar, cast
from carto_cli.sim.odometry import ImuModel, OdometryModel
from carto_cli.sim.recording import Simulation, SimulatedRecording, simulate
from carto_cli.sim.trajectory import Limits, Trajectory, follow_route, loop_trajectory
from carto_cli.sim.world import World, corridor, loop_building, office, room

__all__ = [
    "World", "room", "corridor", "loop_building", "office",
    "Trajectory", "Limits", "follow_route", "loop_trajectory",
    "Lidar", "cast", "OdometryModel", "ImuModel",
    "Simulation", "SimulatedRecording", "simulate",
]
