"""Smooth planar trajectories through waypoints, sampled at any time.

A ``Trajectory`` is a sequence of knots ``dt`` apart; between two knots the
robot drives a circular arc at constant forward speed ``v`` and yaw rate ``w``.
Poses between knots come from that arc, so positions, headings and velocities
are exactly consistent with each other (what the odometry and IMU models
integrate and differentiate).

``follow`` produces the knots by driving a unicycle along the waypoints with a
pursuit controller under speed, yaw-rate and acceleration limits: corners up
to ``sharp_turn`` are taken as smooth arcs, sharper ones (a reversal at the
end of a dead end) by slowing down, turning on the spot, and driving on.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from carto_cli.core.transform import wrap_angle, wrap_angle_scalar
from carto_cli.sim.world import World


@dataclass(frozen=True)
class Limits:
    v_max: float = 0.5  # m/s
    w_max: float = math.radians(45.0)  # rad/s
    a_max: float = 0.5  # m/s^2
    alpha_max: float = math.radians(180.0)  # rad/s^2


def _arc(x, y, yaw, v, w, tau):
    """Pose after driving ``tau`` seconds at (v, w) from (x, y, yaw); works on arrays."""
    half = 0.5 * w * tau
    chord = v * tau * np.sinc(half / np.pi)  # sin(half) / half, safe at 0
    return x + chord * np.cos(yaw + half), y + chord * np.sin(yaw + half), yaw + w * tau


class Trajectory:
    """Knots at ``t = k * dt`` (k = 0..K-1); the last knot is at rest and held forever."""

    def __init__(self, dt: float, x, y, yaw, v, w):
        self.dt = float(dt)
        self.x, self.y = np.asarray(x, float), np.asarray(y, float)
        self.yaw = np.asarray(yaw, float)  # continuous, not wrapped
        self.v, self.w = np.asarray(v, float), np.asarray(w, float)
        if not (len(self.x) == len(self.y) == len(self.yaw) == len(self.v) == len(self.w) >= 1):
            raise ValueError("knot arrays must be non-empty and of equal length")
        self._travelled = np.concatenate([[0.0], np.cumsum(np.abs(self.v[:-1]) * self.dt)])

    @property
    def duration(self) -> float:
        return (len(self.x) - 1) * self.dt

    @property
    def length(self) -> float:
        """Distance driven over the whole trajectory (m)."""
        return float(self._travelled[-1])

    def _locate(self, times):
        t = np.asarray(times, dtype=np.float64)
        k = np.clip(np.floor(t / self.dt).astype(np.int64), 0, len(self.x) - 1)
        tau = np.clip(t - k * self.dt, 0.0, self.dt)
        tau = np.where(k == len(self.x) - 1, 0.0, tau)
        return k, tau

    def poses(self, times) -> np.ndarray:
        """(n, 3) x, y, yaw (wrapped) at ``times`` (s from the start); held before 0 and after the end."""
        k, tau = self._locate(times)
        x, y, yaw = _arc(self.x[k], self.y[k], self.yaw[k], self.v[k], self.w[k], tau)
        return np.stack([x, y, wrap_angle(yaw)], axis=-1)

    def yaw_unwrapped(self, times) -> np.ndarray:
        k, tau = self._locate(times)
        return self.yaw[k] + self.w[k] * tau

    def velocities(self, times) -> np.ndarray:
        """(n, 2) forward speed and yaw rate (body frame) at ``times``."""
        k, _ = self._locate(times)
        return np.stack([self.v[k], self.w[k]], axis=-1)

    def accelerations(self, times) -> np.ndarray:
        """(n, 2) forward and lateral (centripetal) acceleration in the body frame."""
        k, _ = self._locate(times)
        nxt = np.minimum(k + 1, len(self.v) - 1)
        return np.stack([(self.v[nxt] - self.v[k]) / self.dt, self.v[k] * self.w[k]], axis=-1)

    def travelled(self, times) -> np.ndarray:
        """Distance driven from the start up to ``times``."""
        k, tau = self._locate(times)
        return self._travelled[k] + np.abs(self.v[k]) * tau

    # ------------------------------------------------------------ construction

    @classmethod
    def follow(
        cls,
        waypoints,
        *,
        closed: bool = False,
        laps: int = 1,
        limits: Limits = Limits(),
        dt: float = 0.01,
        lookahead: float = 0.5,
        sharp_turn: float = math.radians(100.0),
        max_duration: float = 24 * 3600.0,
    ) -> Trajectory:
        """Drive along ``waypoints`` (m, 2) from the first to the last (around ``laps`` times if closed)."""
        path = _route(np.asarray(waypoints, dtype=np.float64).reshape(-1, 2), closed, laps)
        return cls(dt, *_drive(path, limits, dt, lookahead, sharp_turn, max_duration))


def _route(wp: np.ndarray, closed: bool, laps: int) -> np.ndarray:
    if len(wp) < 2:
        raise ValueError("a route needs at least two waypoints")
    if closed:
        wp = np.vstack([np.tile(wp, (laps, 1)), wp[:1]])
    keep = np.concatenate([[True], np.hypot(*np.diff(wp, axis=0).T) > 1e-9])
    return wp[keep]


def _drive(path, lim: Limits, dt, lookahead, sharp_turn, max_duration):
    seg_np = np.diff(path, axis=0)
    heading = np.arctan2(seg_np[:, 1], seg_np[:, 0])
    turn = np.abs(wrap_angle(np.diff(heading)))
    # Vertices the robot must stop at (sharp corners), then the end of the path.
    stops = [int(i) + 1 for i in np.nonzero(turn > sharp_turn)[0]] + [len(path) - 1]
    # Plain Python floats from here: the loop runs per time step and numpy scalars are slow.
    pts = path.tolist()
    seg = seg_np.tolist()
    seg_len = np.hypot(seg_np[:, 0], seg_np[:, 1]).tolist()
    s_at = [0.0] + np.cumsum(seg_len).tolist()  # arc length at each vertex

    def point_at(s):
        i = min(max(bisect.bisect_right(s_at, s) - 1, 0), len(seg) - 1)
        u = (s - s_at[i]) / seg_len[i]
        return pts[i][0] + u * seg[i][0], pts[i][1] + u * seg[i][1]

    x, y = pts[0]
    yaw = float(heading[0])
    v = w = 0.0
    k = 0  # current segment
    stop = 0  # index into stops
    a_step, alpha_step = lim.a_max * dt, lim.alpha_max * dt
    out_x: list[float] = []
    out_y: list[float] = []
    out_yaw: list[float] = []
    out_v: list[float] = []
    out_w: list[float] = []
    arrived = False
    for _ in range(int(max_duration / dt)):
        if arrived:
            if v == 0.0 and w == 0.0:
                break
            v_des = w_des = 0.0
        else:
            # Progress: project onto the current segment, moving on once past its end.
            while True:
                (ax, ay), (dx, dy) = pts[k], seg[k]
                u = ((x - ax) * dx + (y - ay) * dy) / (seg_len[k] * seg_len[k])
                if u < 1.0 or k + 1 >= stops[stop]:
                    break
                k += 1
            s = s_at[k] + min(max(u, 0.0), 1.0) * seg_len[k]
            s_stop = s_at[stops[stop]]
            to_stop = s_stop - s
            sx, sy = pts[stops[stop]]
            if to_stop < 0.05 and math.hypot(sx - x, sy - y) < 0.1 and abs(v) < 0.05:
                if stop == len(stops) - 1:
                    arrived = True
                else:
                    k, stop = stops[stop], stop + 1
                continue
            tx, ty = point_at(min(s + lookahead, s_stop))
            if math.hypot(tx - x, ty - y) < 1e-6:
                err = 0.0
            else:
                err = wrap_angle_scalar(math.atan2(ty - y, tx - x) - yaw)
            w_des = max(-lim.w_max, min(lim.w_max, 2.0 * err))
            v_des = lim.v_max * math.cos(err) ** 2 if abs(err) < math.pi / 3 else 0.0
            if abs(v) < 0.05 and abs(err) > math.radians(10.0):
                v_des = 0.0  # from (almost) standstill, turn on the spot before driving off
            # Brake so as to stop at the next stop vertex (distance along the path); creep the last bit.
            v_des = min(v_des, math.sqrt(2.0 * lim.a_max * max(to_stop, 0.0)) + (0.02 if to_stop > 0.01 else 0.0))
        v += max(-a_step, min(a_step, v_des - v))
        w += max(-alpha_step, min(alpha_step, w_des - w))
        for out, value in ((out_x, x), (out_y, y), (out_yaw, yaw), (out_v, v), (out_w, w)):
            out.append(value)
        x, y, yaw = _arc_scalar(x, y, yaw, v, w, dt)
    for out, value in ((out_x, x), (out_y, y), (out_yaw, yaw), (out_v, 0.0), (out_w, 0.0)):
        out.append(value)
    return out_x, out_y, out_yaw, out_v, out_w


def _arc_scalar(x, y, yaw, v, w, tau):
    half = 0.5 * w * tau
    chord = v * tau * (math.sin(half) / half if abs(half) > 1e-12 else 1.0)
    return x + chord * math.cos(yaw + half), y + chord * math.sin(yaw + half), yaw + w * tau


def follow_route(world: World, *, laps: int = 1, limits: Limits = Limits(), dt: float = 0.01) -> Trajectory:
    """The trajectory along a world's route (closed routes are driven ``laps`` times)."""
    if world.route is None:
        raise ValueError(f"world '{world.name}' has no route")
    return Trajectory.follow(world.route, closed=world.closed, laps=laps, limits=limits, dt=dt)


def loop_trajectory(world: World | None = None, *, laps: int = 1, limits: Limits = Limits(),
                    dt: float = 0.01) -> Trajectory:
    """The default loop: around ``loop_building()``'s ring corridor (or ``world``'s), ``laps`` times."""
    if world is None:
        from carto_cli.sim.world import loop_building

        world = loop_building()
    if not world.closed:
        raise ValueError(f"world '{world.name}' has no closed route to loop around")
    return follow_route(world, laps=laps, limits=limits, dt=dt)
