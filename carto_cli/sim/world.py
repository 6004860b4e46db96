"""Worlds for the simulator: walls as line segments, plus a route through free space.

A world is a ``(k, 4)`` float64 array of segments ``x1 y1 x2 y2`` (metres) and,
for the builders that have an obvious one, a route: waypoints ``(m, 2)`` along
which a robot can drive without touching a wall (see ``trajectory.follow``).
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class World:
    segments: np.ndarray  # (k, 4) float64: x1 y1 x2 y2
    route: np.ndarray | None = None  # (m, 2) waypoints through free space
    closed: bool = False  # the route returns to its first waypoint
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        seg = np.ascontiguousarray(self.segments, dtype=np.float64).reshape(-1, 4)
        object.__setattr__(self, "segments", seg)
        if self.route is not None:
            object.__setattr__(self, "route", np.asarray(self.route, dtype=np.float64).reshape(-1, 2))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of all walls."""
        xs = self.segments[:, [0, 2]]
        ys = self.segments[:, [1, 3]]
        return float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())

    def distance_to_walls(self, points: np.ndarray) -> np.ndarray:
        """Distance from each of ``points`` (n, 2) to the nearest wall."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 1, 2)
        a = self.segments[None, :, 0:2]
        d = self.segments[None, :, 2:4] - a
        length2 = np.maximum((d * d).sum(-1), 1e-18)
        u = np.clip(((p - a) * d).sum(-1) / length2, 0.0, 1.0)
        nearest = a + u[..., None] * d
        return np.sqrt(((p - nearest) ** 2).sum(-1)).min(axis=1)


# ---------------------------------------------------------------- primitives

def polyline(points: Sequence[Sequence[float]], closed: bool = False) -> np.ndarray:
    """Segments joining consecutive points (and the last to the first when closed)."""
    p = np.asarray(points, dtype=np.float64)
    q = np.roll(p, -1, axis=0) if closed else p[1:]
    p = p if closed else p[:-1]
    return np.hstack([p, q])


def box(cx: float, cy: float, w: float, h: float) -> np.ndarray:
    """A closed rectangle (a pillar, or a room's outline) centred at (cx, cy)."""
    x0, x1, y0, y1 = cx - w / 2, cx + w / 2, cy - h / 2, cy + h / 2
    return polyline([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], closed=True)


def wall(p0: Sequence[float], p1: Sequence[float], gaps: Iterable[tuple[float, float]] = ()) -> np.ndarray:
    """A straight wall from p0 to p1 with openings, each ``(centre, width)`` in metres from p0."""
    start_xy, end_xy = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.hypot(*(end_xy - start_xy)))
    direction = (end_xy - start_xy) / length
    cuts = sorted((c - w / 2, c + w / 2) for c, w in gaps)
    pieces, start = [], 0.0
    for a, b in cuts:
        if a > start:
            pieces.append((start, a))
        start = max(start, b)
    if start < length:
        pieces.append((start, length))
    return np.array([[*(start_xy + a * direction), *(start_xy + b * direction)] for a, b in pieces]).reshape(-1, 4)


def merge(*parts: np.ndarray) -> np.ndarray:
    return np.vstack([np.asarray(p, float).reshape(-1, 4) for p in parts])


# ---------------------------------------------------------------- builders

def room(w: float = 8.0, h: float = 6.0) -> World:
    """An empty rectangle [0, w] x [0, h]; the route circles it 1 m from the walls."""
    m = min(1.0, w / 4, h / 4)
    route = [(m, m), (w - m, m), (w - m, h - m), (m, h - m)]
    return World(box(w / 2, h / 2, w, h), route=np.array(route), closed=True, name=f"room {w}x{h}")


def corridor(length: float = 30.0, width: float = 2.0) -> World:
    """A straight, featureless corridor along x, closed at both ends.

    Scan matching is degenerate along its axis on purpose: the world to test that
    a matcher does not invent motion where the walls cannot tell.
    """
    walls = box(length / 2, width / 2, length, width)
    route = [(1.0, width / 2), (length - 1.0, width / 2)]
    return World(walls, route=np.array(route), closed=False, name=f"corridor {length}x{width}")


def loop_building(
    width: float = 24.0,
    height: float = 16.0,
    corridor_width: float = 2.5,
    room_depth: float = 3.5,
    door_width: float = 1.0,
) -> World:
    """A rectangular ring corridor around a closed core, with side rooms and pillars.

    The rooms (behind doors in the outer wall) sit at irregular spacings and the
    pillars stand close to the walls, so that no two stretches of corridor look
    alike: matching is well posed everywhere and the loop can be closed. The
    route runs along the middle of the ring, counter-clockwise from the
    bottom-left corner.
    """
    c, W, H = corridor_width, width, height
    # Doors in each outer wall at these fractions of its length; one room behind each.
    bottom, right, top, left = (0.22, 0.55, 0.8), (0.4,), (0.3, 0.68), (0.6,)
    room_w = min(4.0, 0.18 * min(W, H))
    segs = []

    def outer(p0, p1, fractions, outward):
        length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
        segs.append(wall(p0, p1, [(f * length, door_width) for f in fractions]))
        d = (np.subtract(p1, p0)) / length
        n = np.asarray(outward, float)
        for f in fractions:
            centre = np.asarray(p0) + f * length * d
            a, b = centre - d * room_w / 2, centre + d * room_w / 2
            # side walls of the room, then its back wall
            segs.append(polyline([a, a + n * room_depth, b + n * room_depth, b]))

    outer((0, 0), (W, 0), bottom, (0, -1))
    outer((W, 0), (W, H), right, (1, 0))
    outer((W, H), (0, H), top, (0, 1))
    outer((0, H), (0, 0), left, (-1, 0))
    segs.append(box(W / 2, H / 2, W - 2 * c, H - 2 * c))  # the core

    # Pillars against the walls (0.3 m off), leaving the middle of the corridor free.
    p = 0.4
    off = 0.3 + p / 2
    pillars = [
        (0.35 * W, off), (0.7 * W, c - off),  # bottom stretch: one per side
        (W - off, 0.65 * H),  # right
        (0.55 * W, H - off), (0.15 * W, H - c + off),  # top
        (c - off, 0.3 * H),  # left, inner side
    ]
    segs += [box(x, y, p, p) for x, y in pillars]
    # A short fin off the core wall: the bottom and top stretches no longer mirror each other.
    segs.append(polyline([(0.45 * W, c), (0.45 * W, c - 0.3)]))

    h = c / 2
    route = [(h, h), (W - h, h), (W - h, H - h), (h, H - h)]
    return World(merge(*segs), route=np.array(route), closed=True, name="loop building",
                 meta={"width": W, "height": H, "corridor_width": c})


def office(
    rooms_per_side: int = 3,
    room_width: float = 4.0,
    room_depth: float = 4.0,
    corridor_width: float = 2.0,
    door_width: float = 0.9,
) -> World:
    """Rooms on both sides of a corridor along x, each entered by a door.

    The route runs down the corridor and visits every room on the top side
    (in through the door, to the room's middle, and back out).
    """
    n, rw, rd, c = rooms_per_side, room_width, room_depth, corridor_width
    L = n * rw
    door_at = [(i + 0.5) * rw for i in range(n)]
    # doors slightly off-centre so rooms differ from one another
    door_at = [x + (0.3 if i % 2 else -0.3) for i, x in enumerate(door_at)]
    segs = [
        wall((0, 0), (L, 0), [(x, door_width) for x in door_at]),
        wall((0, c), (L, c), [(x, door_width) for x in door_at]),
        polyline([(0, -rd), (L, -rd)]), polyline([(0, c + rd), (L, c + rd)]),
        polyline([(0, -rd), (0, c + rd)]), polyline([(L, -rd), (L, c + rd)]),
    ]
    for i in range(1, n):
        segs.append(polyline([(i * rw, -rd), (i * rw, 0)]))
        segs.append(polyline([(i * rw, c), (i * rw, c + rd)]))
    # a desk in every other room so they are not all alike
    segs += [box((i + 0.3) * rw, c + rd - 0.6, 1.2, 0.6) for i in range(0, n, 2)]

    route = [(0.7, c / 2)]
    for x in door_at:
        route += [(x, c / 2), (x, c + rd / 2), (x, c / 2)]
    route.append((L - 0.7, c / 2))
    return World(merge(*segs), route=np.array(route), closed=False, name="office",
                 meta={"corridor_width": c, "doors": door_at})


# Campus route: grid nodes (column, row) driven in this order. Each block perimeter is closed once and later
# revisited, so the recording holds several loops of increasing age (the first closes after ~23 min at 1 m/s).
CAMPUS_ROUTE = ((0, 0), (1, 0), (1, 1), (0, 1), (0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (1, 2), (2, 2), (2, 1),
                (3, 1), (3, 2), (2, 2), (2, 3), (1, 3), (1, 2), (0, 2), (0, 1), (1, 1), (1, 0), (0, 0))
CAMPUS_PLAZAS = (((1, 1), (1, 2)), ((2, 0), (2, 1)))  # corridor edges whose middle is an open area


def campus(spacing: float = 340.0, corridor_width: float = 4.0, hall: float = 24.0, plaza: float = 60.0,
           seed: int = 0) -> World:
    """A campus of about 1 km² (``3 × spacing`` square): long corridors between halls at the nodes of a grid,
    two open plazas, and the route :data:`CAMPUS_ROUTE` (≈ 7.5 km, several loops).

    Corridors get a feature every 5-15 m on each wall, at random (``seed``): a pillar beside the wall, a door
    into a small room, or an alcove, so that no stretch matches another and scan matching is well posed along
    the corridor. Halls (``hall`` m square, a door where each corridor enters) hold four pillars off their
    axes; a plaza (``plaza`` m square) holds sparse pillars ("trees") away from the route, most walls of which
    are out of a 30 m scanner's reach."""
    rng = np.random.default_rng(seed)
    c, h, half = corridor_width, hall / 2, corridor_width / 2
    edges = {tuple(sorted((a, b))) for a, b in zip(CAMPUS_ROUTE[:-1], CAMPUS_ROUTE[1:])}
    plazas = {tuple(sorted(e)) for e in CAMPUS_PLAZAS}
    nodes = sorted({n for e in edges for n in e})
    segs: list[np.ndarray] = []

    def xy(node) -> np.ndarray:
        return np.array(node, float) * spacing

    def features(p0, p1, outward) -> tuple[list[tuple[float, float]], list[np.ndarray]]:
        """Openings in the wall p0 -> p1 and what lies at them (rooms, alcoves), plus pillars inside."""
        p0, p1, n = np.asarray(p0, float), np.asarray(p1, float), np.asarray(outward, float)
        length = float(np.hypot(*(p1 - p0)))
        d = (p1 - p0) / length
        gaps, parts = [], []
        s = rng.uniform(2.0, 8.0)
        while s < length - 4.0:
            kind = rng.random()
            at = p0 + s * d
            if kind < 0.5:  # a pillar 0.4 m square, 0.3 m off the wall
                size = rng.uniform(0.3, 0.6)
                centre = at - n * (0.3 + size / 2)
                parts.append(box(centre[0], centre[1], size, size))
            elif kind < 0.8:  # a door and a room behind it
                w, depth = rng.uniform(3.0, 5.0), rng.uniform(2.5, 4.0)
                gaps.append((s, 1.0))
                a, b = at - d * w / 2, at + d * w / 2
                parts.append(polyline([a, a + n * depth, b + n * depth, b]))
            else:  # an alcove
                w, depth = rng.uniform(1.5, 2.5), rng.uniform(0.5, 1.0)
                gaps.append((s, w))
                a, b = at - d * w / 2, at + d * w / 2
                parts.append(polyline([a, a + n * depth, b + n * depth, b]))
            s += rng.uniform(5.0, 15.0)
        return gaps, parts

    def corridor_walls(a, b) -> None:
        """Both walls of a corridor from point a to point b (axis-aligned), with features."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        d = (b - a) / float(np.hypot(*(b - a)))
        n = np.array([-d[1], d[0]])
        for side in (1.0, -1.0):
            p0, p1 = a + side * half * n, b + side * half * n
            gaps, parts = features(p0, p1, side * n)
            segs.append(wall(p0, p1, gaps))
            segs.extend(parts)

    def square_with_doors(centre, size, doors) -> None:
        """A square room of ``size`` at ``centre`` with a corridor-wide door in each wall facing ``doors``."""
        s = size / 2
        corners = [centre + (-s, -s), centre + (s, -s), centre + (s, s), centre + (-s, s)]
        for k, direction in enumerate(((0, -1), (1, 0), (0, 1), (-1, 0))):
            p0, p1 = corners[k], corners[(k + 1) % 4]
            gaps = [(s, c)] if direction in doors else []
            segs.append(wall(p0, p1, gaps))

    for node in nodes:
        centre = xy(node)
        doors = {tuple(int(v) for v in np.subtract(other, node)) for e in edges if node in e
                 for other in e if other != node}
        square_with_doors(centre, hall, doors)
        for sx in (-1, 1):
            for sy in (-1, 1):
                off = rng.uniform(4.0, h - 3.0, size=2)
                segs.append(box(centre[0] + sx * off[0], centre[1] + sy * off[1], 0.6, 0.6))

    for a_node, b_node in sorted(edges):
        a, b = xy(a_node), xy(b_node)
        d = (b - a) / spacing
        start, end = a + d * h, b - d * h
        if (a_node, b_node) in plazas:
            mid = (a + b) / 2
            p = plaza / 2
            corridor_walls(start, mid - d * p)
            corridor_walls(mid + d * p, end)
            axis = (int(d[0]), int(d[1]))
            square_with_doors(mid, plaza, {axis, (-axis[0], -axis[1])})
            n = np.array([-d[1], d[0]])
            for _ in range(24):  # trees, at least 3 m off the route
                along, across = rng.uniform(-p + 3, p - 3), rng.choice([-1, 1]) * rng.uniform(3.0, p - 3)
                t = mid + d * along + n * across
                segs.append(box(t[0], t[1], 0.5, 0.5))
        else:
            corridor_walls(start, end)

    route = np.array([xy(n) for n in CAMPUS_ROUTE])
    size = 3 * spacing + hall
    return World(merge(*segs), route=route, closed=False, name="campus",
                 meta={"area_km2": size * size / 1e6, "spacing": spacing, "corridor_width": c})
