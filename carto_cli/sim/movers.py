"""Things that move or stay only a while: people walking, a person standing, a cart parked, a door opened.

A ``Mover`` is an outline (segments in its own frame) carried along a track of timed poses; between the track's
first and last time it stands in the world and returns rays as a wall does, outside them it is not there. The
lidar casts each scan against the walls and then against the movers there at that scan's time
(``Simulation.movers``). ``footprint`` is the ground truth of what is not static: every cell a mover's outline
crosses at any scan time.

``crowd`` puts a scene into a world with a route: walkers going up and down the route at walking pace, people
standing beside it for 5-20 s as the robot comes by, carts parked beside it for a minute, and doors (given as a
hinge and a leaf) closed until the middle of the recording and open after. The robot must see a place both with
and without what stood there for a map to be cleaned of it, so a scene is meant for a route driven twice.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.core.enums import TextEnum
from carto_cli.sim.world import World, box, polyline


class MoverKind(TextEnum):
    WALKER = "walker"
    STANDING = "standing"
    CART = "cart"
    DOOR = "door"


PERSON_RADIUS = 0.2  # m: a person's outline at a laser's height, an octagon
WALKING_SPEED = (0.8, 1.4)  # m/s
STANDING_TIME = (5.0, 20.0)  # s
CART_SIZE = (1.0, 0.6)  # m


def person(radius: float = PERSON_RADIUS) -> np.ndarray:
    a = np.arange(8) * math.pi / 4 + math.pi / 8
    return polyline(np.column_stack([radius * np.cos(a), radius * np.sin(a)]).tolist(), closed=True)


@dataclass(frozen=True, eq=False)
class Mover:
    """``outline`` (k, 4) segments in the mover's frame; ``track`` (m, 4) rows ``t x y yaw`` (s since the
    recording's start), increasing in t, poses in between interpolated linearly."""

    kind: MoverKind
    outline: np.ndarray
    track: np.ndarray

    def __post_init__(self):
        track = np.asarray(self.track, np.float64).reshape(-1, 4)
        if len(track) < 1 or np.any(np.diff(track[:, 0]) < 0):
            raise ValueError("a mover's track needs rows t x y yaw in time order")
        object.__setattr__(self, "track", track)
        object.__setattr__(self, "outline", np.asarray(self.outline, np.float64).reshape(-1, 4))

    def pose(self, t: float) -> np.ndarray | None:
        """(x, y, yaw) at ``t``, None when the mover is not there."""
        tr = self.track
        if t < tr[0, 0] or t > tr[-1, 0]:
            return None
        return np.array([np.interp(t, tr[:, 0], tr[:, i]) for i in (1, 2, 3)])

    def segments(self, t: float) -> np.ndarray:
        """The outline placed at ``t`` (k, 4), or (0, 4) when the mover is not there."""
        p = self.pose(t)
        if p is None:
            return np.zeros((0, 4))
        c, s = math.cos(p[2]), math.sin(p[2])
        o = self.outline
        x = np.column_stack([o[:, 0], o[:, 2]])
        y = np.column_stack([o[:, 1], o[:, 3]])
        gx, gy = c * x - s * y + p[0], s * x + c * y + p[1]
        return np.column_stack([gx[:, 0], gy[:, 0], gx[:, 1], gy[:, 1]])


KEEP_CLEAR = 0.3  # m: no mover's outline comes closer than this to the robot's laser (people step aside)


def segments_at(movers: Sequence[Mover], t: float, clear_of: np.ndarray | None = None) -> np.ndarray:
    """Every mover's outline there at ``t``, as one (k, 4) array; with ``clear_of`` (x, y: the laser), not those
    that would come within ``KEEP_CLEAR`` of it: a walker drawn through the robot would blind its laser from
    inside, where a person would have stepped aside."""
    parts = [m.segments(t) for m in movers]
    if clear_of is not None:
        parts = [p for p in parts if not len(p) or _distance(p, clear_of) >= KEEP_CLEAR]
    return np.concatenate(parts) if parts else np.zeros((0, 4))


def _distance(segments: np.ndarray, xy: np.ndarray) -> float:
    a, d = segments[:, :2], segments[:, 2:] - segments[:, :2]
    u = np.clip(((xy - a) * d).sum(1) / np.maximum((d * d).sum(1), 1e-18), 0.0, 1.0)
    return float(np.hypot(*(a + u[:, None] * d - xy).T).min())


def footprint(movers: Sequence[Mover], times: np.ndarray, origin: Sequence[float], resolution: float,
              shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the cells of a grid (row = y, lower-left corner ``origin``) any mover's outline crosses at
    any of ``times`` (s since the recording's start)."""
    out = np.zeros(shape, bool)
    times = np.asarray(times, np.float64)
    for lo in range(0, len(times), 256):
        parts = [segments_at(movers, float(t)) for t in times[lo:lo + 256]]
        seg = np.concatenate(parts) if parts else np.zeros((0, 4))
        if not len(seg):
            continue
        longest = float(np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]).max())
        u = np.linspace(0.0, 1.0, max(int(math.ceil(longest / (resolution / 4))), 1) + 1)[None, :]
        ix = np.floor((seg[:, :1] + u * (seg[:, 2:3] - seg[:, :1]) - origin[0]) / resolution).astype(np.int64)
        iy = np.floor((seg[:, 1:2] + u * (seg[:, 3:4] - seg[:, 1:2]) - origin[1]) / resolution).astype(np.int64)
        inside = (ix >= 0) & (iy >= 0) & (ix < shape[1]) & (iy < shape[0])
        out[iy[inside], ix[inside]] = True
    return out


def _route_points(world: World, step: float = 0.1) -> np.ndarray:
    """The route as points ``step`` apart (closed routes back to the start)."""
    assert world.route is not None
    wp = np.vstack([world.route, world.route[:1]]) if world.closed else world.route
    pts = []
    for a, b in zip(wp[:-1], wp[1:]):
        n = max(int(math.ceil(np.hypot(*(b - a)) / step)), 1)
        pts.append(a + (b - a) * np.arange(n)[:, None] / n)
    pts.append(wp[-1:])
    return np.vstack(pts)


def _aside(world: World, at: np.ndarray, heading: np.ndarray, offset: float, clearance: float) -> np.ndarray | None:
    """A point ``offset`` m to the left (negative: right) of the route at ``at``, if it stays ``clearance``
    from every wall and the straight way there crosses none."""
    normal = np.array([-heading[1], heading[0]]) / max(np.hypot(*heading), 1e-9)
    steps = np.linspace(0.0, 1.0, 8)[:, None]
    way = at + steps * offset * normal
    if world.distance_to_walls(way).min() < clearance:
        return None
    return at + offset * normal


def walker(world: World, rng: np.random.Generator, duration: float) -> Mover:
    """A person walking up and down the route (to its end and back, or round a closed one), a little to one
    side, from a random point, for the whole recording."""
    pts = _route_points(world)
    heading = np.gradient(pts, axis=0)
    side = rng.uniform(0.4, 0.7) * rng.choice([-1.0, 1.0])
    lane = np.array([p if (q := _aside(world, p, h, side, PERSON_RADIUS + 0.15)) is None else q
                     for p, h in zip(pts, heading)])
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(lane, axis=0).T))])
    speed = rng.uniform(*WALKING_SPEED)
    times = np.arange(0.0, duration + 0.5, 0.5)
    s = rng.uniform(0.0, arc[-1]) + speed * times * rng.choice([-1.0, 1.0])
    if world.closed:
        s = np.mod(s, arc[-1])
    else:  # to the end and back
        s = arc[-1] - np.abs(np.mod(s, 2 * arc[-1]) - arc[-1])
    xy = np.column_stack([np.interp(s, arc, lane[:, 0]), np.interp(s, arc, lane[:, 1])])
    return Mover(MoverKind.WALKER, person(), np.column_stack([times, xy, np.zeros(len(times))]))


def _beside_robot(world: World, robot: np.ndarray, t: float, ahead: float, offset: float, size: float
                  ) -> np.ndarray | None:
    """A place ``offset`` beside the robot's path where the robot will be ``ahead`` s after ``t`` (robot: (n, 4)
    rows t x y yaw), clear of the walls by ``size``."""
    i = int(np.searchsorted(robot[:, 0], t + ahead).clip(1, len(robot) - 1))
    at, heading = robot[i, 1:3], robot[i, 1:3] - robot[i - 1, 1:3]
    if np.hypot(*heading) < 1e-6:
        heading = np.array([math.cos(robot[i, 3]), math.sin(robot[i, 3])])
    return _aside(world, at, heading, offset, size)


def standing(world: World, robot: np.ndarray, rng: np.random.Generator, until: float) -> Mover | None:
    """A person standing 5-20 s beside the robot's path, there as the robot comes by and gone by ``until`` s
    (None: no room)."""
    stay = rng.uniform(*STANDING_TIME)
    if until - stay <= robot[0, 0] + 5.0:
        return None
    t = rng.uniform(robot[0, 0] + 5.0, until - stay)
    p = _beside_robot(world, robot, t, 0.5 * stay, rng.uniform(0.7, 1.0) * rng.choice([-1.0, 1.0]),
                      PERSON_RADIUS + 0.15)
    if p is None:
        return None
    return Mover(MoverKind.STANDING, person(), np.array([[t, p[0], p[1], 0.0], [t + stay, p[0], p[1], 0.0]]))


def cart(world: World, robot: np.ndarray, rng: np.random.Generator, until: float, stay: float = 60.0
         ) -> Mover | None:
    """A cart parked beside the robot's path for ``stay`` s, there as the robot comes by and gone by ``until``
    (None: no room, or no time)."""
    if until - stay <= robot[0, 0] + 5.0:
        return None
    t = rng.uniform(robot[0, 0] + 5.0, until - stay)
    length, width = CART_SIZE
    p = _beside_robot(world, robot, t, 0.5 * stay, rng.uniform(0.75, 0.85) * rng.choice([-1.0, 1.0]), 0.4)
    if p is None:
        return None
    # along the way, as carts are left in a corridor
    yaw = float(robot[int(np.searchsorted(robot[:, 0], t + 0.5 * stay).clip(0, len(robot) - 1)), 3])
    return Mover(MoverKind.CART, box(0.0, 0.0, length, width), np.array([[t, *p, yaw], [t + stay, *p, yaw]]))


def door(hinge: Sequence[float], leaf: float, closed_yaw: float, open_yaw: float, opens: float, end: float) -> list[
        Mover]:
    """A door leaf ``leaf`` m long turning on ``hinge``: at ``closed_yaw`` until ``opens`` s, then at
    ``open_yaw`` until ``end`` (two movers, one per position)."""
    outline = polyline([(0.0, 0.0), (leaf, 0.0)])
    hx, hy = float(hinge[0]), float(hinge[1])
    return [Mover(MoverKind.DOOR, outline, np.array([[0.0, hx, hy, closed_yaw], [opens, hx, hy, closed_yaw]])),
            Mover(MoverKind.DOOR, outline, np.array([[opens + 1e-3, hx, hy, open_yaw], [end, hx, hy, open_yaw]]))]


def crowd(world: World, robot: np.ndarray, *, walkers: int = 10, standing_people: int = 3, carts: int = 1,
          doors: Sequence[tuple[Sequence[float], float, float, float]] = (), seed: int = 0) -> list[Mover]:
    """A scene for ``world`` along the robot's path (``robot``: (n, 4) rows t x y yaw, t in s since the start,
    driving its route twice): ``walkers`` people walking up and down the route, ``standing_people`` standing
    beside the path as the robot comes by, ``carts`` parked there for a minute, all gone before the second
    time round, so that the robot sees where they stood both ways; and a door for each of ``doors`` (hinge, leaf
    length, closed and open yaw) opened in the middle of the recording (opened flat against a wall, its open
    leaf is a wall's look-alike for the rest of it)."""
    rng = np.random.default_rng(seed)
    end = float(robot[-1, 0])
    movers = [walker(world, rng, end) for _ in range(walkers)]
    for make, n in ((standing, standing_people), (cart, carts)):
        placed, tries = 0, 0
        while placed < n and tries < 20 * n:
            tries += 1
            m = make(world, robot, rng, 0.45 * end)
            if m is not None:
                movers.append(m)
                placed += 1
    for hinge, leaf, closed_yaw, open_yaw in doors:
        movers += door(hinge, leaf, closed_yaw, open_yaw, 0.5 * end, end)
    return movers
