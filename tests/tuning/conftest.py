"""What the tuning tests share: a simulated drive, and option values that map it poorly."""
import pytest

from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate


@pytest.fixture(scope="package")
def sim():
    world = loop_building()
    return simulate(world, loop_trajectory(world), duration=20.0, scan_rate=5.0, lidar=Lidar(beams=180))


@pytest.fixture(scope="session")
def poor():
    """A deliberately poor profile: local SLAM and the pose graph both pinned to the drifting odometry."""
    return {
        "trajectory_builder_2d.ceres_scan_matcher.translation_weight": 1.0e4,
        "trajectory_builder_2d.ceres_scan_matcher.rotation_weight": 1.0e4,
        "pose_graph.optimization_problem.odometry_translation_weight": 1.0e5,
    }
