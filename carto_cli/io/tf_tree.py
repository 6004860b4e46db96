"""Static TF: where the laser sits on the robot."""
from __future__ import annotations

import math

from carto_cli.core.errors import CartoError
from carto_cli.core.records import Transform, strip_frame
from carto_cli.core.transform import wrap_angle_scalar

# Cartographer's usual tracking frames, in order of preference, when several roots exist.
TRACKING_FRAMES = ("base_link", "base_footprint", "imu_link", "imu")


def _compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def parent_map(transforms: list[Transform]) -> dict[str, tuple[str, tuple[float, float, float]]]:
    """child -> (parent, planar pose of child in parent); frame names without leading slashes."""
    parents = {}
    for tf in transforms:
        parents[strip_frame(tf.child)] = (strip_frame(tf.parent), tf.pose2d())
    return parents


def laser_pose_from_tf(transforms: list[Transform], laser_frame: str,
                       tracking_frame: str | None = None) -> tuple[tuple[float, float, float], str] | None:
    """Planar pose of ``laser_frame`` in the tracking frame, and that frame's name; None if TF doesn't know the laser.

    Without an explicit ``tracking_frame`` the chain is followed up to its root, since static TF
    trees of mobile robots are rooted at the robot body.
    """
    parents = parent_map(transforms)
    frame = strip_frame(laser_frame)
    if frame not in parents:
        return None
    pose = (0.0, 0.0, 0.0)
    seen = {frame}
    while frame in parents:
        if tracking_frame is not None and frame == strip_frame(tracking_frame):
            break
        parent, rel = parents[frame]
        pose = _compose(rel, pose)
        frame = parent
        if frame in seen:
            raise CartoError(f"static TF has a cycle through '{frame}'")
        seen.add(frame)
    if tracking_frame is not None and frame != strip_frame(tracking_frame):
        raise CartoError(f"static TF does not connect '{laser_frame}' to tracking frame '{tracking_frame}'")
    return (pose[0], pose[1], wrap_angle_scalar(pose[2])), frame


def format_tree(transforms: list[Transform]) -> list[str]:
    """Indented lines, roots first, for `carto info`."""
    parents = parent_map(transforms)
    children: dict[str, list[str]] = {}
    for child, (parent, _) in parents.items():
        children.setdefault(parent, []).append(child)
    roots = sorted(set(children) - set(parents))
    lines: list[str] = []

    def walk(frame: str, depth: int, seen: frozenset) -> None:
        for child in sorted(children.get(frame, [])):
            if child in seen:
                continue
            x, y, yaw = parents[child][1]
            lines.append(f"{'  ' * depth}{child}  (x {x:.3f} m, y {y:.3f} m, yaw {math.degrees(yaw):.2f}°)")
            walk(child, depth + 1, seen | {child})

    for root in roots:
        lines.append(root)
        walk(root, 1, frozenset({root}))
    return lines
