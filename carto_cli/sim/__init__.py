"""A 2D robot simulator for tests and benchmarks: worlds of wall segments, trajectories,
a ray-cast laser, wheel odometry and a gyro, with exact ground truth."""
from carto_cli.sim.lidar import Lidar, cast
from carto_cli.sim.odometry import ImuModel, OdometryModel
from carto_cli.sim.recording import SimulatedRecording, Simulation, simulate
from carto_cli.sim.trajectory import Limits, Trajectory, follow_route, loop_trajectory
from carto_cli.sim.world import (
    Material,
    World,
    altered,
    changed_cells,
    corridor,
    courtyard,
    glass_office,
    loop_building,
    office,
    rearranged_loop_building,
    room,
)

__all__ = [
    "ImuModel",
    "Lidar",
    "Limits",
    "Material",
    "OdometryModel",
    "SimulatedRecording",
    "Simulation",
    "Trajectory",
    "World",
    "altered",
    "cast",
    "changed_cells",
    "corridor",
    "courtyard",
    "follow_route",
    "glass_office",
    "loop_building",
    "loop_trajectory",
    "office",
    "rearranged_loop_building",
    "room",
    "simulate",
]
