"""GMapping as a core object: scans and odometry in, the best particle's trajectory and map out. No files.

The same shape as :class:`carto_cli.mapping.slam.Slam` (``add_scan``, ``add_odometry``, ``finish``), so the
pipeline drives either system and writes the same outputs.

One processed scan: every particle moves by the odometry since the last processed scan with the motion
model's noise, tries headings within a few sigma of that noise and climbs to the best match of the scan on
its own map, draws its pose from the improved
proposal around that match and adds the proposal's normaliser to its weight; when the effective sample
size falls below the threshold the particles are resampled (low variance); then every surviving
particle's map takes the scan. A scan is processed once odometry has moved ``linearUpdate`` or turned
``angularUpdate`` since the last one (every scan without odometry); the others get the best particle's
pose at the last processed scan moved on by odometry. At the end the best particle's trajectory is made
consistent where it revisits a place (``loops``, a pose graph of loop closures between passes), its processed
scans are re-matched against the map of all of them (``refine``, ``refineIterations`` rounds), and its map is
drawn again from the moved scans.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass

import numpy as np

from carto_cli.core import kernels, transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.core.timing import NullTimer
from carto_cli.gmapping import Algorithm, loops, matcher, motion, refine, resampling
from carto_cli.gmapping.maps import CELL_BYTES, TILE, TiledMaps
from carto_cli.grid.occupancy_image import OccupancyImage
from carto_cli.mapping.cleaning import compact_returns
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.slam import RunStats, SlamResult
from carto_cli.mapping.submaps import ActiveSubmaps
from carto_cli.matching import correlative
from carto_cli.options import Options
from carto_cli.sensor.range_filter import RangeData, crop_scan
from carto_cli.sensor.voxel_filter import adaptive_voxel_filter

ODOMETRY_EXTRAPOLATION_S = 0.5  # a scan this far past the newest odometry still gets it extrapolated
ENTROPY_EVERY = 10  # processed scans between two computations of the map's entropy
GMAPPING_OCC_THRESH = 0.25  # slam_gmapping's occ_thresh
# map.yaml's occupied_thresh (io.map_image.OCCUPIED_THRESH; the core does not import io, a test keeps them equal)
OCCUPIED_THRESH = 0.65
MAX_SWEEP = math.radians(45.0)  # beyond this a scan's own symmetries compete with its true heading


@register_warm_up(system="gmapping")
def warm_up() -> None:
    """The final refinement's pruned correlative search (loops, refine) on a toy scan. The particles' kernels
    warm up in their own modules (maps, matcher): on a fresh install each warm-up is compiled by whichever
    process claims it first (core.kernels), and they took 84 s as one."""
    angles = np.linspace(-1.5, 1.5, 32)
    ends = np.stack([2.0 * np.cos(angles), 2.0 * np.sin(angles)], axis=1)
    grid = refine.map_of(np.zeros((1, 3)), [RangeData(np.zeros(2), ends, np.empty((0, 2)))], 0.05)
    correlative.match_pruned(grid, correlative.coarse_grid(grid), ends, np.zeros(3), linear_search_window=0.1,
                             angular_search_window=0.05)


@dataclass
class Beams:
    """One scan's rays in the tracking frame."""

    origin: np.ndarray  # (2,) the sensor
    ends: np.ndarray  # (n, 2) where each ray stops (a wall, or the usable range)
    hit: np.ndarray  # (n,) the ray ends in a wall
    points: np.ndarray  # (m, 2) endpoints within the usable range: what is matched
    data: RangeData  # the cropped scan: the refinement and the submaps at the end


class GMappingSlam:
    """The Rao-Blackwellized particle filter of GMapping, options from ``options.gmapping``."""

    def __init__(self, options: Options, *, laser_pose=(0.0, 0.0, 0.0), timer=None, started: float | None = None,
                 jobs: int | None = None):
        """``jobs``: threads for the particles' kernels and the final refinement's searches (None: every core);
        the result is the same for any number."""
        self.options = options
        self.jobs = jobs
        import numba

        # numba's thread count is the process's: set it either way, so that an earlier filter run with fewer
        # jobs (the survey's one-particle odometry check) does not leave this one on fewer cores
        most = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]  # set at import from the cores
        numba.set_num_threads(min(max(1, int(jobs)), most) if jobs is not None else most)
        self.g = options.gmapping
        self._climb = matcher.ClimbSettings.of(self.g)
        self.timer = timer or NullTimer()
        kernels.warm_up(self.timer, systems=("gmapping",))
        self.laser_pose = transform.as_pose(laser_pose)
        self._started = _time.perf_counter() if started is None else started
        self.rng = np.random.Generator(np.random.PCG64(self.g.seed))
        n = self.g.particles
        self.maps = TiledMaps(n, self.g.delta)
        self.poses = np.zeros((n, 3))
        self.log_weights = np.zeros(n)  # since the last resampling: what resampling weighs
        self.lineage = np.zeros(n)  # over each particle's whole history: what picks the best one
        # Processed scans: every particle's pose and the index of its parent at the step before.
        self._step_poses: list[np.ndarray] = []
        self._step_parents: list[np.ndarray] = []
        self._step_odometry: list[np.ndarray | None] = []
        self._step_times: list[float] = []
        self._step_beams: list[Beams] = []  # for the submaps, the refinement and redrawing the map at the end
        # Every scan: its time, odometry, and the processed step at or before it.
        self._scan_times: list[float] = []
        self._scan_odometry: list[np.ndarray | None] = []
        self._scan_step: list[int] = []
        self._odometry: list[tuple[float, np.ndarray]] = []
        self._odometry_samples: list[tuple[float, np.ndarray]] = []
        self._last_odometry: np.ndarray | None = None  # at the previous scan
        self._moved = 0.0
        self._turned = 0.0
        self.num_scans = 0
        self.resamplings = 0
        self.empty_scans = 0
        self.neff_history: list[float] = []
        self._entropy_cache: tuple[int, float] | None = None
        # GMapping charges an endpoint in never-observed space like one in free space; unknownIsNoEvidence
        # charges it like a wall at the edge of the search kernel (measured worse: docs/gmapping.md).
        g = self.g
        self._unknown_ll = (-((g.kernelSize + 0.5) * g.delta) ** 2 / g.lsigma if g.unknownIsNoEvidence
                            else matcher.NULL_LIKELIHOOD / g.lsigma)

    @property
    def num_poses(self) -> int:
        return len(self._scan_times)

    @property
    def num_steps(self) -> int:
        """Scans processed so far."""
        return len(self._step_poses)

    @property
    def step_odometry(self) -> list[np.ndarray | None]:
        """The odometry at each processed scan (None where there was none)."""
        return self._step_odometry

    # ------------------------------------------------------------------ input

    def add_odometry(self, odometry: Odometry) -> None:
        pose = np.array([odometry.x, odometry.y, odometry.yaw], dtype=np.float64)
        self._odometry.append((odometry.time, pose))
        self._odometry_samples.append((odometry.time, pose))
        if len(self._odometry) > 8:
            del self._odometry[:-4]

    def add_imu(self, imu: Imu) -> None:
        """GMapping uses no IMU."""

    def _odometry_at(self, t: float) -> np.ndarray | None:
        samples = self._odometry
        if not samples:
            return None
        for (t0, p0), (t1, p1) in zip(samples[-2::-1], samples[:0:-1]):
            if t0 <= t <= t1:
                return _interpolate(t0, p0, t1, p1, t)
        t1, p1 = samples[-1]
        if t >= t1 and len(samples) > 1 and t - t1 <= ODOMETRY_EXTRAPOLATION_S:
            t0, p0 = samples[-2]
            if t1 > t0:
                return _interpolate(t0, p0, t1, p1, t)
        return p1.copy()

    def _beams(self, scan: Scan) -> Beams:
        g = self.g
        max_range = g.maxRange
        if math.isfinite(scan.range_max) and scan.range_max > 0:
            # slam_gmapping takes the laser's own range_max: a reading at it is no return.
            max_range = min(max_range, scan.range_max - 0.01)
        data = crop_scan(scan, mount=self.laser_pose, min_range=0.0, max_range=max_range,
                         missing_data_ray_length=g.maxUrange)
        origin = data.origin
        rel = data.returns - origin[None, :]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        usable = dist <= g.maxUrange
        clipped = origin[None, :] + rel[~usable] * (g.maxUrange / dist[~usable])[:, None]
        # A beam with no return (beyond maxRange) is skipped, as GMapping does: it says nothing reliable about
        # where the free space ends, and casting it to maxUrange would touch tiles far beyond any wall.
        ends = np.vstack([data.returns[usable], clipped])
        hit = np.zeros(ends.shape[0], bool)
        hit[:int(usable.sum())] = True
        # The refinement's grids and the submaps skip those beams too: as free rays to maxUrange (80 m) they made
        # every chunk and submap grid about 170 m across (intel: 26 submaps of 23 MB, packed and unpacked on the
        # way out; loop step and re-matching on grids ten times the returns' area), for free space GMapping's own
        # map does not have. Relation errors moved by -0.9 to +2.3 mm a run, means by -0.3 to +0.8 (docs/gmapping.md).
        data = RangeData(data.origin, data.returns, np.empty((0, 2)))
        return Beams(origin, np.ascontiguousarray(ends), hit, np.ascontiguousarray(data.returns[usable]), data)

    def add_scan(self, scan: Scan) -> bool:
        """Feed one scan; True when it was processed, i.e. became a node (the others are placed by odometry at the
        end)."""
        self.num_scans += 1
        timer = self.timer
        with timer.scan():
            odometry = self._odometry_at(scan.time)
            if odometry is not None and self._last_odometry is not None:
                step = motion.increment(self._last_odometry, odometry)
                self._moved += float(np.hypot(step[0], step[1]))
                self._turned += abs(float(step[2]))
            self._last_odometry = odometry
            g = self.g
            due = (not self._step_poses or odometry is None or self._moved >= g.linearUpdate
                   or self._turned >= g.angularUpdate
                   or (g.temporalUpdate >= 0 and scan.time - self._step_times[-1] >= g.temporalUpdate))
            if due:
                with timer.stage("preprocess"):
                    beams = self._beams(scan)
                if beams.points.shape[0] == 0:
                    self.empty_scans += 1
                    due = False
            if due:
                self._process(scan.time, odometry, beams)
                self._moved = self._turned = 0.0
            if self._step_poses:
                self._scan_times.append(scan.time)
                self._scan_odometry.append(odometry)
                self._scan_step.append(len(self._step_poses) - 1)
        return due

    # ------------------------------------------------------------------ the filter

    def _process(self, t: float, odometry: np.ndarray | None, beams: Beams) -> None:
        g, timer, maps = self.g, self.timer, self.maps
        n = self.poses.shape[0]
        parents = np.arange(n)
        lx, ly = float(beams.origin[0]), float(beams.origin[1])
        if not self._step_poses:
            # The first scan goes into one map that every particle then shares.
            with timer.stage("map update"):
                maps.insert(self.poses[:1], beams.origin, beams.ends, beams.hit)
                maps.reindex(np.zeros(n, np.int64))
            self._record(t, odometry, beams, parents)
            return
        with timer.stage("motion model"):
            previous = self._step_odometry[-1]
            delta = (motion.increment(previous, odometry) if previous is not None and odometry is not None
                     else np.zeros(3))
            sigma = motion.sigmas(delta, g.srr, g.srt, g.str, g.stt)
            means = motion.predict(self.poses, delta, np.zeros((n, 3)))
            # The noise is drawn in the frame of the pose each particle moves from, so that frame turns it.
            world_sigma = motion.world_sigmas(self.poses, sigma)
            self.poses = motion.sample(self.poses, delta, sigma, self.rng)
        ox, oy = maps.tile_origin
        # Headings within sweepSigmas of the motion model's rotational noise are tried before climbing: a key
        # scan's turn leaves most particles tens of degrees off, beyond the climb's reach (orebro: 0.07 m
        # instead of metres; docs/gmapping.md).
        sweeps = np.minimum(g.sweepSigmas * world_sigma[:, 2], MAX_SWEEP)
        with timer.stage("scan matching"):
            modes, scores = matcher.climb(maps, g.delta, beams.points, lx, ly, self.poses, sweeps, self._climb)
            if g.minimumScore > 0:
                weak = scores < g.minimumScore
                modes[weak] = self.poses[weak]
        with timer.stage("weighting"):
            normals = self.rng.standard_normal((n, 3))
            self.poses, log_eta, _ = matcher.propose(
                maps.table, maps.state, maps.mean, ox, oy, g.delta, beams.points, lx, ly, modes, means,
                world_sigma, normals, g.kernelSize, g.lsigma, g.lskip + 1, self._unknown_ll, g.llsamplerange,
                g.llsamplestep, g.lasamplerange, g.lasamplestep)
            self.poses[:, 2] = transform.wrap_angle(self.poses[:, 2])
            self.log_weights += log_eta
            self.lineage += log_eta
        with timer.stage("resampling"):
            weights = resampling.normalized(self.log_weights, g.ogain, g.gainParticles)
            neff = resampling.neff(weights)
            self.neff_history.append(neff)
            limit = resampling.threshold(n, g.resampleThreshold)
            if neff < limit and g.adaptiveResampling:
                limit = resampling.threshold(n, g.resampleThreshold, self._entropy())
            if neff < limit:
                parents = resampling.low_variance(weights, self.rng)
                self.poses = self.poses[parents]
                self.lineage = self.lineage[parents]
                self.log_weights = np.zeros(n)
                maps.reindex(parents)
                self.resamplings += 1
        with timer.stage("map update"):
            maps.insert(self.poses, beams.origin, beams.ends, beams.hit)
        self._record(t, odometry, beams, parents)

    def _entropy(self) -> float:
        """The best particle's map entropy, recomputed every ENTROPY_EVERY processed scans (it moves slowly
        and costs a pass over the whole map)."""
        step = len(self._step_poses)
        if self._entropy_cache is None or step - self._entropy_cache[0] >= ENTROPY_EVERY:
            self._entropy_cache = (step, self.maps.entropy(self.best_particle()))
        return self._entropy_cache[1]

    def _record(self, t, odometry, beams: Beams, parents: np.ndarray) -> None:
        self._step_poses.append(self.poses.copy())
        self._step_parents.append(np.asarray(parents, np.int32))
        self._step_odometry.append(odometry)
        self._step_times.append(t)
        self._step_beams.append(beams)

    # ------------------------------------------------------------------ output

    def best_particle(self) -> int:
        return int(np.argmax(self.lineage))

    def best_trajectory(self) -> np.ndarray:
        """(steps, 3) the best particle's pose at every processed scan, followed back through its ancestors."""
        j = self.best_particle()
        out = np.empty((len(self._step_poses), 3))
        for k in range(len(self._step_poses) - 1, -1, -1):
            out[k] = self._step_poses[k][j]
            j = int(self._step_parents[k][j])
        return out

    def close(self, abandon: bool = False) -> None:
        """Nothing runs between scans (the particles' threads are numba's), so there is nothing to stop."""

    def finish(self) -> SlamResult:
        """The best particle's trajectory (a pose for every scan), its map, and the same map as submaps
        (the processed scans inserted at its poses) so map.carto and ``carto relocalize`` work as for
        Cartographer maps. Call once, with at least one processed scan."""
        if not self._step_poses:
            raise ValueError("no scan was processed")
        timer = self.timer
        steps = unrefined = self.best_trajectory()
        scans = [b.data for b in self._step_beams]
        refined = self.g.refineLoops or self.g.refineIterations > 0
        closed = loops.LoopRefinement(steps, 0, 0)  # what "no loop step" reports
        peak_tiles = self.maps.peak_tiles
        if refined:
            # The refined map is drawn again from the scans: the particles' maps are done with, and released here
            # they are not held beside the refinement's grids (edmonton at 100 particles: peak RSS 1055 -> 861 MB).
            self.maps = TiledMaps(1, self.g.delta)
            with timer.stage("refine"):
                if self.g.refineLoops:
                    with timer.stage("loop closure"):
                        closed = loops.close_loops(steps, scans, resolution=self.g.delta, jobs=self.jobs)
                    steps = closed.poses
                if self.g.refineIterations > 0:
                    with timer.stage("re-match"):
                        steps = refine.refine_poses(steps, scans, resolution=self.g.delta,
                                                    iterations=self.g.refineIterations, jobs=self.jobs)
        with timer.stage("assemble map"):
            step_of = np.asarray(self._scan_step, dtype=np.int64)
            poses = steps[step_of]
            # Scans between processed ones: the processed scan's pose moved on by odometry, where there is some.
            moved = [i for i, (k, odo) in enumerate(zip(step_of, self._scan_odometry))
                     if odo is not None and self._step_odometry[k] is not None]
            if moved:
                base = np.array([self._step_odometry[step_of[i]] for i in moved])
                odo = np.array([self._scan_odometry[i] for i in moved])
                poses[moved] = transform.compose(poses[moved], motion.increment(base, odo))
            prob, origin = self._map(steps) if refined else self.maps.occupancy(self.best_particle())
            # A GMapping cell holds how often rays ending near it stopped there, not a probability: slam_gmapping
            # calls it occupied above 0.25. Scaled so that 0.25 lands on map.yaml's occupied_thresh, the walls
            # nav2 sees are the ones slam_gmapping would publish (unscaled, grazed walls read as unknown).
            image = OccupancyImage(np.minimum(prob * np.float32(OCCUPIED_THRESH / GMAPPING_OCC_THRESH), 1.0),
                                   self.g.delta, origin)
            graph, submaps, node_scans = self._submaps(steps)
        wall = _time.perf_counter() - self._started
        stats: RunStats = {
            "algorithm": Algorithm.GMAPPING,
            "scans": self.num_scans,
            "poses": len(self._scan_times),
            "nodes": len(self._step_poses),
            "processed_scans": len(self._step_poses),
            "submaps": len(submaps),
            "particles": int(self.g.particles),
            "resamplings": self.resamplings,
            "mean_neff": float(np.mean(self.neff_history)) if self.neff_history else None,
            "map_tiles_peak": int(peak_tiles),
            "map_memory_peak_bytes": int(peak_tiles * TILE * TILE * CELL_BYTES),
            "wall_time_s": wall,
            "scans_per_s": self.num_scans / wall if wall > 0 else float("nan"),
            "empty_scans": self.empty_scans,
            "constraints": len(graph.constraints),
            "loop_closures": closed.accepted,
            "loop_closure_candidates": closed.candidates,
        }
        return SlamResult(
            times=np.array(self._scan_times), poses=poses, local_poses=poses.copy(), node_scans=node_scans,
            submaps=submaps, submap_poses=graph.submap_global_poses, image=image, laser_pose=self.laser_pose,
            stats=stats, graph=graph, unrefined_node_poses=unrefined if refined else None,
            node_returns=[compact_returns(b.data.returns) for b in self._step_beams])

    def _map(self, steps: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
        """The map drawn again from the processed scans at ``steps`` (one particle's worth of tiles)."""
        drawn = TiledMaps(1, self.g.delta)
        for pose, b in zip(steps, self._step_beams):
            drawn.insert(pose[None, :], b.origin, b.ends, b.hit)
        return drawn.occupancy(0)

    def _submaps(self, steps: np.ndarray):
        """The processed scans inserted into Cartographer submaps at the best particle's poses, as nodes of a
        pose graph without loop closure (its frame is the map frame)."""
        o = self.options
        tb = o.trajectory_builder_2d
        ri = tb.submaps.range_data_inserter
        active = ActiveSubmaps(num_range_data=tb.submaps.num_range_data,
                               resolution=tb.submaps.grid_options_2d.resolution, hit_probability=ri.hit_probability,
                               miss_probability=ri.miss_probability, insert_free_space=ri.insert_free_space)
        graph = PoseGraph(o, timer=self.timer, loop_closure=False)
        for t, pose in self._odometry_samples:
            graph.add_odometry(t, pose)
        lc = tb.loop_closure_adaptive_voxel_filter
        submaps = {}
        for k, (beams, pose) in enumerate(zip(self._step_beams, steps)):
            data = beams.data
            inserted = active.insert(data.transformed(pose))
            for sm in inserted:
                submaps[sm.index] = sm
            points = adaptive_voxel_filter(data.returns, max_length=lc.max_length, min_num_points=lc.min_num_points,
                                           max_range=lc.max_range)
            graph.add_node(self._step_times[k], pose, points, inserted)
        first_scan: dict[int, int] = {}
        for i, k in enumerate(self._scan_step):
            first_scan.setdefault(k, i)
        node_scans = np.array([first_scan[k] for k in range(len(steps))], dtype=np.int64)
        return graph, [submaps[i] for i in sorted(submaps)], node_scans


def _interpolate(t0, p0, t1, p1, t) -> np.ndarray:
    if t1 <= t0:
        return p1.copy()
    f = (t - t0) / (t1 - t0)
    d = transform.wrap_angle_scalar(p1[2] - p0[2])
    return np.array([p0[0] + f * (p1[0] - p0[0]), p0[1] + f * (p1[1] - p0[1]), p0[2] + f * d])
