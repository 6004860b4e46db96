"""A 2D laser scanner: ray casting against wall segments, then a noise model.

Invalid returns follow ROS REP 117, which is what carto's readers see from
real drivers: nothing within ``max_range`` -> ``+inf``; a dropout (no echo
from a dark or glancing surface) is also "no return" -> ``+inf`` by default
(``dropout_value`` can make it ``nan`` or ``max_range``, as some drivers do);
a hit closer than ``min_range`` -> ``-inf``.

Segments may be partly transparent (``World.material``, one row per segment): a ray crossing one is
returned by it with probability ``opacity``, and only if it meets it within ``incidence`` of its normal
(glass reflects near the normal only) and within ``reach`` of the scanner (a hedge or a car body lower
than the scan plane, which a plane tilted a little up passes over from afar); otherwise the ray passes on
to the next segment. The draw is a hash of (a key drawn from the scan's generator, scan, beam, segment),
so it does not depend on the order the segments are tested in; a world whose segments are all opaque
draws nothing more than before.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from carto_cli.sim.world import Material

CULL_ABOVE = 256  # segments; beyond this, walls out of every pose's reach are left out before casting


@numba.njit(cache=True, nogil=True)
def _uniform(key, p, b, s):
    """A uniform draw in [0, 1) from (key, scan, beam, segment): splitmix64 of their mix."""
    z = np.uint64(key) ^ (np.uint64(p) * np.uint64(0x9E3779B97F4A7C15))
    z = z ^ (np.uint64(b) * np.uint64(0xC2B2AE3D27D4EB4F)) ^ (np.uint64(s) * np.uint64(0x165667B19E3779F9))
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) / 9007199254740992.0


@numba.njit(cache=True, nogil=True)
def _cast(poses, angles, segments, material, ids, max_range, key):
    """(m, n) distance along each beam to the nearest segment that returns it, inf beyond ``max_range``.

    Ray o + t d against segment a + u e: with r = a - o, t = (r x e) / (d x e) and u = (r x d) / (d x e).
    Segment ``s`` returns a crossing ray met at |cos(incidence)| >= ``material[s, 1]`` and at most
    ``material[s, 2]`` away with probability ``material[s, 0]`` (drawn by ``_uniform(key, scan, beam, ids[s])``
    unless it is 1: an opaque wall draws nothing), and lets it pass otherwise."""
    m, n, k = poses.shape[0], angles.shape[0], segments.shape[0]
    out = np.empty((m, n), dtype=np.float64)
    for p in range(m):
        ox, oy, oyaw = poses[p, 0], poses[p, 1], poses[p, 2]
        for b in range(n):
            a = oyaw + angles[b]
            dx, dy = math.cos(a), math.sin(a)
            best = np.inf
            for s in range(k):
                ax, ay = segments[s, 0], segments[s, 1]
                ex, ey = segments[s, 2] - ax, segments[s, 3] - ay
                den = dx * ey - dy * ex
                if den == 0.0:
                    continue  # parallel: a grazing ray does not hit
                rx, ry = ax - ox, ay - oy
                t = (rx * ey - ry * ex) / den
                if t < 0.0 or t >= best:
                    continue
                u = (rx * dy - ry * dx) / den
                if u < 0.0 or u > 1.0 or t > material[s, 2]:
                    continue
                if material[s, 1] > 0.0 and abs(den) < material[s, 1] * math.sqrt(ex * ex + ey * ey):
                    continue  # met too far from its normal: |d x e| / |e| is the cosine of the incidence
                if material[s, 0] >= 1.0 or _uniform(key, p, b, ids[s]) < material[s, 0]:
                    best = t
            out[p, b] = best if best <= max_range else np.inf
    return out


def cast(poses, angles, segments, max_range: float = np.inf, *, material=None, key: int = 0) -> np.ndarray:
    """Exact ranges from sensor ``poses`` ((m, 3) x y yaw, or one (3,)) along ``angles`` (sensor frame).

    Returns (m, n) float64 (or (n,) for one pose); ``inf`` where no wall lies within ``max_range``.
    ``material`` (k, 3), per segment: the probability that it returns a ray crossing it, the least
    |cos| of the angle between ray and normal at which it can, and the most range at which it can (None:
    every segment returns every ray); ``key`` seeds the draws.
    """
    p = np.ascontiguousarray(poses, dtype=np.float64)
    single = p.ndim == 1
    seg = np.ascontiguousarray(segments, dtype=np.float64).reshape(-1, 4)
    ids = np.arange(len(seg), dtype=np.int64)
    if material is None:
        material = np.tile(Material().row, (len(seg), 1))  # every wall opaque
    material = np.asarray(material, np.float64).reshape(-1, 3)
    if len(material) != len(seg):
        raise ValueError(f"material has {len(material)} rows for {len(seg)} segments")
    if math.isfinite(max_range) and len(seg) > CULL_ABOVE:
        # A large world (a campus): only walls within max_range of some pose can be hit. Keeping their order
        # keeps every range exactly what the whole list gives.
        xy = p.reshape(-1, 3)[:, :2]
        lo, hi = xy.min(axis=0) - max_range, xy.max(axis=0) + max_range
        near = ((np.minimum(seg[:, 0], seg[:, 2]) <= hi[0]) & (np.maximum(seg[:, 0], seg[:, 2]) >= lo[0])
                & (np.minimum(seg[:, 1], seg[:, 3]) <= hi[1]) & (np.maximum(seg[:, 1], seg[:, 3]) >= lo[1]))
        seg = np.ascontiguousarray(seg[near])
        ids = ids[near]
    out = _cast(p.reshape(-1, 3), np.ascontiguousarray(angles, dtype=np.float64), seg,
                np.ascontiguousarray(material[ids]), ids, float(max_range), int(key))
    return out[0] if single else out


@dataclass(frozen=True)
class Lidar:
    beams: int = 360
    fov: float = 2 * math.pi * 0.75
    max_range: float = 30.0
    min_range: float = 0.05
    noise: float = 0.01  # m, gaussian sigma
    noise_per_metre: float = 0.0  # extra sigma per metre of range
    dropout: float = 0.01  # probability that a beam returns nothing
    dropout_value: float = math.inf

    @property
    def angle_increment(self) -> float:
        # A full circle must not repeat its first beam; a partial fan includes both ends.
        if self.fov >= 2 * math.pi - 1e-9:
            return 2 * math.pi / self.beams
        return self.fov / max(self.beams - 1, 1)

    @property
    def angle_min(self) -> float:
        return -math.pi if self.fov >= 2 * math.pi - 1e-9 else -self.fov / 2

    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(self.beams)

    def measure(self, poses, segments, rng: np.random.Generator, material=None) -> np.ndarray:
        """Noisy float32 ranges (m, n) from sensor ``poses`` (m, 3); ``material`` as for ``cast`` (its
        draws take one key from ``rng`` first; without it ``rng`` is used exactly as before)."""
        return self.noisy(self.true_ranges(poses, segments, rng, material), rng)

    def true_ranges(self, poses, segments, rng: np.random.Generator, material=None) -> np.ndarray:
        """Exact ranges (m, n), inf beyond ``max_range`` (the first half of ``measure``)."""
        if material is None:
            return cast(np.atleast_2d(poses), self.angles(), segments, self.max_range)
        key = int(rng.integers(0, 2**62))
        return cast(np.atleast_2d(poses), self.angles(), segments, self.max_range, material=material, key=key)

    def noisy(self, true: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``true`` ranges with the noise model's noise, limits and dropouts, as float32."""
        sigma = self.noise + self.noise_per_metre * np.where(np.isfinite(true), true, 0.0)
        noisy = true + sigma * rng.standard_normal(true.shape)
        noisy[noisy > self.max_range] = np.inf
        noisy[noisy < self.min_range] = -np.inf
        noisy[rng.random(true.shape) < self.dropout] = self.dropout_value
        return noisy.astype(np.float32)
