"""Worlds for the simulator: walls as line segments, plus a route through free space.

A world is a ``(k, 4)`` float64 array of segments ``x1 y1 x2 y2`` (metres) and,
for the builders that have an obvious one, a route: waypoints ``(m, 2)`` along
which a robot can drive without touching a wall (see ``trajectory.follow``).

A segment may be partly transparent to the laser (``World.materials``, one ``Material`` row per
segment; the lidar lets the rays it does not return pass on): glass, returning some of the rays that
meet it near its normal; a hedge, a bush or a parked car's body, returning some rays and, being lower
than a scan plane tilted a little up, none from afar. ``glass_office`` and ``courtyard`` are built of
such things on purpose, with walls one line thick seen from both sides and doors, for judging a map's
walls (``mapping/see_through.py``); the other builders have opaque walls only (``materials`` None), and their
recordings are what they always were.
"""
from __future__ import annotations

import math
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
    materials: np.ndarray | None = None  # (k, 3) ``Material.row`` per segment; None: every one opaque

    def __post_init__(self):
        seg = np.ascontiguousarray(self.segments, dtype=np.float64).reshape(-1, 4)
        object.__setattr__(self, "segments", seg)
        if self.route is not None:
            object.__setattr__(self, "route", np.asarray(self.route, dtype=np.float64).reshape(-1, 2))
        if self.materials is not None:
            rows = np.ascontiguousarray(self.materials, dtype=np.float64).reshape(-1, 3)
            if len(rows) != len(seg) or not np.all((rows[:, 0] > 0) & (rows[:, 0] <= 1)):
                raise ValueError("materials need one row per segment, with an opacity in (0, 1]")
            object.__setattr__(self, "materials", rows)

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


@dataclass(frozen=True)
class Material:
    """How a segment returns a laser ray that crosses it: with probability ``opacity``, and only if the ray
    meets it within ``incidence`` degrees of its normal and at most ``reach`` metres from the scanner."""

    opacity: float = 1.0
    incidence: float = 90.0
    reach: float = math.inf

    @property
    def row(self) -> tuple[float, float, float]:
        """(opacity, least |cos| of the incidence, reach): the lidar's row for it."""
        return (float(self.opacity), math.cos(math.radians(self.incidence)) if self.incidence < 90 else 0.0,
                float(self.reach))


OPAQUE = Material()


def merge_partial(parts: Iterable[tuple[np.ndarray, Material]]) -> tuple[np.ndarray, np.ndarray]:
    """Segments and their materials' rows (for ``World``) from ``(segments, material)`` pairs."""
    parts = [(np.asarray(p, float).reshape(-1, 4), m) for p, m in parts]
    rows = np.concatenate([np.tile(np.array(m.row), (len(p), 1)) for p, m in parts]) if parts else np.zeros((0, 3))
    return merge(*(p for p, _ in parts)), rows


def blob(cx: float, cy: float, w: float, h: float, rng: np.random.Generator, leaves: int = 3,
         sides: int = 8) -> np.ndarray:
    """A bush or a stretch of hedge: a ragged ellipse ``w`` x ``h`` around (cx, cy) (``sides`` segments,
    radii jittered by up to 20 %) and ``leaves`` short segments inside it. Give it an opacity below 1."""
    a = np.sort(rng.uniform(0, 2 * np.pi, sides))
    r = rng.uniform(0.8, 1.0, sides)
    outline = polyline(np.column_stack([cx + r * w / 2 * np.cos(a), cy + r * h / 2 * np.sin(a)]).tolist(), closed=True)
    centre = np.column_stack([cx + rng.uniform(-0.35, 0.35, leaves) * w, cy + rng.uniform(-0.35, 0.35, leaves) * h])
    turn = rng.uniform(0, np.pi, leaves)
    half = 0.25 * min(w, h) * np.column_stack([np.cos(turn), np.sin(turn)])
    return merge(outline, np.hstack([centre - half, centre + half]))


def car(cx: float, cy: float, along_x: bool = True, length: float = 4.4, width: float = 1.8
        ) -> tuple[np.ndarray, np.ndarray]:
    """A parked car at scanner height: (its four wheels, its body's outline). The laser sees the wheels and
    only partly the body (the gap under the sills, the bumpers): give the outline an opacity below 1."""
    lx, ly = (length, width) if along_x else (width, length)
    wx, wy = (0.6, 0.25) if along_x else (0.25, 0.6)
    ox, oy = (lx / 2 - 0.8, ly / 2 - 0.2) if along_x else (lx / 2 - 0.2, ly / 2 - 0.8)
    wheels = merge(*(box(cx + sx * ox, cy + sy * oy, wx, wy) for sx in (-1, 1) for sy in (-1, 1)))
    return wheels, box(cx, cy, lx, ly)


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


def glass_office(width: float = 20.0, height: float = 14.0, corridor_width: float = 2.0, door_width: float = 1.0,
                 glass: Material = Material(0.3), plants: Material = Material(0.5), seed: int = 0) -> World:
    """A ring corridor around six rooms with glass fronts, walls one line thick, doors and plants.

    The core (inside the ring) is split by partitions into three rooms along the bottom and three along the
    top, at different widths; each room has a door onto the corridor, the middle rooms a door between them.
    Every wall is a single line, so a partition is seen from both its rooms and a core wall from the corridor
    and its room. A room's front onto the corridor is glass (``glass``) but for a door and a post at each end;
    the core's left wall and one partition hold a pane, and a glass panel in the outer wall opens onto a yard
    fenced 4 m out. Potted plants (``plants``) stand in the corridor's corners and in two rooms, a desk in two.
    The route drives the ring counter-clockwise, in and out of four rooms on the way; drive it twice (``laps``)
    to revisit everything."""
    rng = np.random.default_rng(seed)
    W, H, c = width, height, corridor_width
    mid = H / 2
    x0, x1 = c, W - c
    cw = x1 - x0
    bottom_cuts = [x0 + f * cw for f in (0.3, 0.62)]
    top_cuts = [x0 + f * cw for f in (0.4, 0.75)]
    parts: list[tuple[np.ndarray, Material]] = []

    def rooms(cuts):
        edges = [x0, *cuts, x1]
        return [(a, b) for a, b in zip(edges[:-1], edges[1:])]

    bottom_rooms, top_rooms = rooms(bottom_cuts), rooms(top_cuts)
    bottom_doors = [a + 0.3 * (b - a) + 0.4 for a, b in bottom_rooms]
    top_doors = [a + 0.7 * (b - a) - 0.4 for a, b in top_rooms]

    def front(y, room_list, doors):
        """The core's wall at height y: per room a door, a 0.4 m post at each end and by the door, glass between."""
        for (a, b), d in zip(room_list, doors):
            da, db = d - door_width / 2, d + door_width / 2
            for p, q in ((a, a + 0.4), (da - 0.3, da), (db, db + 0.3), (b - 0.4, b)):
                parts.append((polyline([(p, y), (q, y)]), OPAQUE))
            for p, q in ((a + 0.4, da - 0.3), (db + 0.3, b - 0.4)):
                if q - p > 0.2:
                    parts.append((polyline([(p, y), (q, y)]), glass))

    # Outer walls: a glass panel in the right one, onto a yard closed by a fence 4 m out.
    pane = (0.35 * H, 0.65 * H)
    parts.append((polyline([(W, pane[1]), (W, H), (0, H), (0, 0), (W, 0), (W, pane[0])]), OPAQUE))
    parts.append((polyline([(W, pane[0]), (W, pane[1])]), glass))
    parts.append((polyline([(W, pane[0] - 1.0), (W + 4.0, pane[0] - 1.0), (W + 4.0, pane[1] + 1.0),
                            (W, pane[1] + 1.0)]), OPAQUE))
    front(c, bottom_rooms, bottom_doors)
    front(H - c, top_rooms, top_doors)
    # The core's left wall (a pane in it) and right wall.
    parts.append((wall((x0, c), (x0, H - c), [(mid - c + 2.0, 1.2)]), OPAQUE))
    parts.append((polyline([(x0, mid + 1.4), (x0, mid + 2.6)]), glass))
    parts.append((polyline([(x1, c), (x1, H - c)]), OPAQUE))
    # Partitions: between the two rows (a door between the middle rooms), and between rooms of a row.
    (b0, _), (m0, m1), _ = bottom_rooms
    (t0, _), _, (_, r1) = top_rooms
    parts.append((wall((x0, mid), (x1, mid), [(0.5 * (m0 + m1) - x0, door_width)]), OPAQUE))
    parts.append((wall((bottom_cuts[0], c), (bottom_cuts[0], mid), [(0.7 * (mid - c), 1.6)]), OPAQUE))
    parts.append((polyline([(bottom_cuts[0], c + 0.7 * (mid - c) - 0.8),
                            (bottom_cuts[0], c + 0.7 * (mid - c) + 0.8)]), glass))
    parts.append((polyline([(bottom_cuts[1], c), (bottom_cuts[1], mid)]), OPAQUE))
    for x in top_cuts:
        parts.append((polyline([(x, mid), (x, H - c)]), OPAQUE))
    # Plants: one in three corridor corners, two in rooms; a desk in two rooms.
    for x, y, size in ((0.4, 0.4, 0.5), (W - 0.4, H - 0.4, 0.5), (0.4, H - 0.4, 0.5), (b0 + 0.7, mid - 0.7, 0.7),
                       (r1 - 0.7, H - c - 0.7, 0.7)):
        parts.append((blob(x, y, size, size, rng), plants))
    parts.append((box(0.5 * (m0 + m1) + 1.0, c + 1.0, 1.2, 0.6), OPAQUE))
    parts.append((box(t0 + 1.2, H - c - 0.5, 1.4, 0.6), OPAQUE))

    h = c / 2
    route = [(h, h)]
    for x in bottom_doors[:2]:
        route += [(x, h), (x, (c + mid) / 2), (x, h)]
    route += [(W - h, h), (W - h, H - h)]
    for x in top_doors[::-1][:2]:
        route += [(x, H - h), (x, (H - c + mid) / 2), (x, H - h)]
    route += [(h, H - h)]
    segments, materials = merge_partial(parts)
    return World(segments, route=np.array(route), closed=True, name="glass office", materials=materials,
                 meta={"corridor_width": c, "glass": glass, "plants": plants})


def courtyard(width: float = 40.0, height: float = 30.0, hedges: Material = Material(0.7, reach=6.0),
              glass: Material = Material(0.6, incidence=25.0), cars: Material = Material(0.7, reach=8.0),
              seed: int = 0) -> World:
    """An outdoor yard between buildings: two lawns edged with hedges, bushes and tree trunks on them,
    cars parked along two facades, glass in the facades.

    Hedges are rows of ragged blobs (``blob``) of ``hedges``, with a gap in each row; bushes are of the same;
    trunks are opaque. A car's wheels are opaque, its body is of ``cars``. Facades are single lines with
    glass windows (``glass``) onto rooms 3-5 m deep. By default a hedge returns 70 % of the rays within 6 m
    and none from further (a scan plane tilted up by 2 degrees is 20 cm higher 6 m out: it passes over it),
    a car's body 70 % within 8 m, glass 60 % of the rays within 25 degrees of its normal. The route (not
    closed) drives round the yard, along the path between the lawns, back along the bottom, up the left, along
    the top and back through the middle: each hedge is seen from both sides, from two passes."""
    if width < 26.0 or height < 22.0:
        raise ValueError("a courtyard needs at least 26 m x 22 m for its paths and lawns")
    rng = np.random.default_rng(seed)
    W, H = width, height
    parts: list[tuple[np.ndarray, Material]] = []
    # Facades: windows at random along each, with a room behind each window.
    corners = [(0.0, 0.0), (W, 0.0), (W, H), (0.0, H)]
    for k in range(4):
        p0, p1 = np.array(corners[k]), np.array(corners[(k + 1) % 4])
        length = float(np.hypot(*(p1 - p0)))
        d = (p1 - p0) / length
        n = np.array([d[1], -d[0]])  # outward
        windows, s = [], rng.uniform(2.0, 5.0)
        while s < length - 4.0:
            w = rng.uniform(1.5, 3.0)
            windows.append((s + w / 2, w))
            s += w + rng.uniform(3.0, 7.0)
        parts.append((wall(tuple(p0), tuple(p1), windows), OPAQUE))
        for centre, w in windows:
            a, b = p0 + (centre - w / 2) * d, p0 + (centre + w / 2) * d
            parts.append((polyline([a, b]), glass))
            depth = rng.uniform(3.0, 5.0)
            parts.append((polyline([a, a + n * depth, b + n * depth, b]), OPAQUE))
    # Lawns, one above the other, between the paths at y = 3.5, H / 2 and H - 3.5 and x = 4 and W - 4.
    lawns = [(8.0, W - 8.0, 6.5, H / 2 - 2.5), (8.0, W - 8.0, H / 2 + 2.5, H - 6.5)]
    for xa, xb, ya, yb in lawns:
        # Hedges along the long sides (a gap in each), bushes along the short ones.
        for y in (ya, yb):
            gap = rng.uniform(xa + 4.0, xb - 4.0)
            x = xa
            while x < xb:
                if abs(x - gap) > 1.0:
                    parts.append((blob(x, y + rng.uniform(-0.1, 0.1), rng.uniform(0.6, 0.9), rng.uniform(0.7, 0.9),
                                       rng), hedges))
                x += rng.uniform(0.6, 0.8)
        for x in (xa, xb):
            for y in np.arange(ya + 1.5, yb - 1.0, rng.uniform(1.8, 2.6)):
                size = rng.uniform(0.6, 1.2)
                parts.append((blob(x, y, size, size, rng), hedges))
        # Trees on the lawn: opaque trunks, a bush here and there.
        for _ in range(5):
            x, y = rng.uniform(xa + 2.0, xb - 2.0), rng.uniform(ya + 1.0, yb - 1.0)
            r = rng.uniform(0.2, 0.4)
            parts.append((box(x, y, r, r), OPAQUE))
            if rng.random() < 0.5:
                parts.append((blob(x + rng.uniform(-1.5, 1.5), y + rng.uniform(-0.8, 0.8), 1.0, 1.0, rng), hedges))
    # Cars parked along the top facade, nose to tail with gaps, and two along the right one.
    spots = []
    x = 6.0
    while x < W - 8.0:
        if rng.random() < 0.75:
            spots.append((x, H - 1.3, True))
        x += rng.uniform(5.0, 6.5)
    spots += [(W - 1.3, 8.0, False), (W - 1.3, 20.0, False)]
    for x, y, along_x in spots:
        wheels, body = car(x, y, along_x)
        parts += [(wheels, OPAQUE), (body, cars)]

    lo, mid, hi, left, right = 3.5, H / 2, H - 3.6, 4.0, W - 4.0
    route = [(left, mid), (left, lo), (right, lo), (right, hi), (left, hi), (left, mid), (right, mid),
             (right, lo), (left, lo), (left, hi), (right, hi), (right, mid), (left, mid)]
    segments, materials = merge_partial(parts)
    return World(segments, route=np.array(route), closed=False, name="courtyard", materials=materials,
                 meta={"hedges": hedges, "glass": glass, "cars": cars})


# ---------------------------------------------------------------- a building that changes between sessions

def altered(world: World, *, remove: Iterable[np.ndarray] = (), add: Iterable[np.ndarray] = (),
            name: str | None = None) -> World:
    """``world`` as a later session finds it: the segments of ``remove`` (each (k, 4); matched to the world's
    within 1 mm, either way round) taken out, those of ``add`` put in, the route kept. Opaque worlds only."""
    if world.materials is not None:
        raise ValueError("altered() changes opaque worlds only")
    segments = world.segments
    gone = np.zeros(len(segments), bool)
    for seg in (np.asarray(s, float).reshape(-1, 4) for s in remove):
        for row in seg:
            same = (np.abs(segments - row).max(axis=1) < 1e-3) | (np.abs(segments - row[[2, 3, 0, 1]]).max(axis=1)
                                                                 < 1e-3)
            if not same.any():
                raise ValueError(f"no segment {row.tolist()} in world '{world.name}'")
            gone |= same
    added = [np.asarray(s, float).reshape(-1, 4) for s in add]
    return World(merge(segments[~gone], *added), route=world.route, closed=world.closed,
                 name=name or f"{world.name}, altered", meta=dict(world.meta))


def rearranged_loop_building() -> tuple[World, World]:
    """``loop_building()`` and the same building as a later session finds it: the door in the bottom wall at
    13.2 m closed, the back wall of the room behind the left door moved 1.5 m closer (its side walls shortened),
    and the cabinet (a 0.4 m pillar) against the bottom wall at 8.4 m taken away."""
    before = loop_building()
    # The left room: door centred at (0, 6.4) in the wall x = 0, 2.88 m wide, 3.5 m deep (loop_building's layout)
    a, b = (0.0, 7.84), (0.0, 4.96)
    old_room = polyline([a, (-3.5, a[1]), (-3.5, b[1]), b])
    new_room = polyline([a, (-2.0, a[1]), (-2.0, b[1]), b])
    after = altered(before, remove=[old_room, box(8.4, 0.5, 0.4, 0.4)],
                    add=[new_room, polyline([(12.7, 0.0), (13.7, 0.0)])], name="loop building, rearranged")
    return before, after


def wall_cells(world: World, origin: Sequence[float], resolution: float, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the cells of a grid (row = y, lower-left corner ``origin``) that a wall of ``world`` crosses."""
    out = np.zeros(shape, bool)
    for x1, y1, x2, y2 in world.segments:
        n = max(int(math.ceil(math.hypot(x2 - x1, y2 - y1) / (resolution / 4))), 1) + 1
        t = np.linspace(0.0, 1.0, n)
        ix = np.floor((x1 + t * (x2 - x1) - origin[0]) / resolution).astype(np.int64)
        iy = np.floor((y1 + t * (y2 - y1) - origin[1]) / resolution).astype(np.int64)
        inside = (ix >= 0) & (iy >= 0) & (ix < shape[1]) & (iy < shape[0])
        out[iy[inside], ix[inside]] = True
    return out


def grown(cells: np.ndarray, by: int) -> np.ndarray:
    """``cells`` with every cell within ``by`` cells (a square) of one set."""
    out = cells.copy()
    for _ in range(by):
        step = out.copy()
        step[1:] |= out[:-1]
        step[:-1] |= out[1:]
        step[:, 1:] |= step[:, :-1].copy()
        step[:, :-1] |= step[:, 1:].copy()
        out = step
    return out


def changed_cells(before: World, after: World, origin: Sequence[float], resolution: float, shape: tuple[int, int],
                  margin: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth of what changed between two worlds on a grid: (appeared, vanished, unchanged) bool rasters,
    the cells a wall of ``after`` crosses with no wall of ``before`` within ``margin`` cells, the reverse, and
    the cells both worlds' walls cross. The margin keeps the ends of a changed wall, where it meets one that
    stayed, out of both (a map's wall is a cell or two thick)."""
    a = wall_cells(before, origin, resolution, shape)
    b = wall_cells(after, origin, resolution, shape)
    return b & ~grown(a, margin), a & ~grown(b, margin), a & b
