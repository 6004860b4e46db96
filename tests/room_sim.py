"""A tiny 2D ray caster for the local-SLAM tests: walls as segments, exact ranges (+ optional noise).

Kept independent of carto_cli.sim on purpose: these tests must not break when the simulator changes.
"""
import math

import numpy as np

from carto_cli.sensor.range_filter import crop_polar

# An 8 m x 6 m room with a pillar and an L-shaped cabinet, so that no pose is ambiguous.
ROOM = np.array([
    [0.0, 0.0, 8.0, 0.0], [8.0, 0.0, 8.0, 6.0], [8.0, 6.0, 0.0, 6.0], [0.0, 6.0, 0.0, 0.0],
    [5.0, 1.5, 5.6, 1.5], [5.6, 1.5, 5.6, 2.1], [5.6, 2.1, 5.0, 2.1], [5.0, 2.1, 5.0, 1.5],
    [1.0, 4.0, 2.5, 4.0], [2.5, 4.0, 2.5, 4.4], [1.0, 4.0, 1.0, 5.0],
    [6.5, 4.5, 7.2, 5.2],
])


def beam_angles(n=360):
    return -math.pi + np.arange(n) * (2 * math.pi / n)


def cast(pose, angles, segments=ROOM, max_range=math.inf, noise=0.0, rng=None):
    """Ranges from the sensor at ``pose`` (x, y, theta) along ``angles`` (sensor frame); inf = no hit."""
    x, y, th = pose
    a = np.asarray(angles) + th
    d = np.stack([np.cos(a), np.sin(a)], axis=1)[:, None, :]  # (n, 1, 2)
    p0 = segments[None, :, :2]
    e = segments[None, :, 2:] - p0  # (1, m, 2)
    w = p0 - np.array([x, y])
    denom = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / denom
        u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / denom
    valid = (np.abs(denom) > 1e-12) & (t > 1e-9) & (u >= 0.0) & (u <= 1.0)
    r = np.where(valid, t, np.inf).min(axis=1)
    if noise and rng is not None:
        r = r + rng.normal(0.0, noise, r.shape)
    r[r > max_range] = np.inf
    return r


def scan_points(pose, n=360, noise=0.0, rng=None):
    """Returns of one scan in the sensor frame, (k, 2)."""
    return crop_polar(cast(pose, beam_angles(n), noise=noise, rng=rng), beam_angles(n)).returns


def build_room_grid(poses, resolution=0.05, noise=0.01, seed=0, n=360):
    """A probability grid of the room built by inserting one scan from each pose."""
    from carto_cli.grid.probability_grid import ProbabilityGrid
    from carto_cli.grid.range_inserter import ProbabilityGridRangeDataInserter

    rng = np.random.default_rng(seed)
    # Walls on cell centres: the grid's own half-cell quantisation then puts no bias into matching tests.
    grid = ProbabilityGrid(resolution, (-1.0 - 0.5 * resolution, -1.0 - 0.5 * resolution),
                           (int(round(10.0 / resolution)), int(round(8.0 / resolution))))
    inserter = ProbabilityGridRangeDataInserter()
    for pose in poses:
        rd = crop_polar(cast(pose, beam_angles(n), noise=noise, rng=rng), beam_angles(n))
        inserter.insert(rd.transformed(pose), grid)
    return grid
