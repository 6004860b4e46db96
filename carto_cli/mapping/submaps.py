"""Submaps and Cartographer's two-active-submaps life cycle.

Every scan goes into both active submaps. A new submap starts each
``num_range_data`` insertions and the older one is finished after
``2 × num_range_data``: consecutive submaps overlap by half, so a scan always
has a submap that already holds ``num_range_data`` scans of context to be
matched against (the older, "front" one), and loop closure always finds a
finished submap covering any place the robot has been.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.grid.range_inserter import ProbabilityGridRangeDataInserter
from carto_cli.sensor.range_filter import RangeData

INITIAL_SUBMAP_SIZE = 100  # cells; the grid grows as scans leave it


class Submap:
    """A local occupancy grid. ``local_pose`` is its origin in the local SLAM frame.

    As in Cartographer the pose is a pure translation (the sensor position of
    the first scan inserted) and the grid is axis-aligned with the local frame.
    Unlike Cartographer's, the grid's cells are snapped to the lattice of whole
    multiples of ``resolution``, so the two active submaps share their cell
    boundaries and one ray casting serves both (see ``ActiveSubmaps.insert``).
    """

    def __init__(self, origin: ArrayLike, *, resolution: float = 0.05, index: int = 0,
                 initial_size: int = INITIAL_SUBMAP_SIZE) -> None:
        origin = np.asarray(origin, dtype=np.float64)[:2]
        self.index = index
        self.local_pose = np.array([origin[0], origin[1], 0.0])
        corner = np.floor(origin / resolution - 0.5 * initial_size) * resolution
        self.grid = ProbabilityGrid(resolution, corner, (initial_size, initial_size))
        self.num_range_data = 0
        self.finished = False

    @classmethod
    def stand_in(cls, index: int, local_pose: ArrayLike) -> Submap:
        """A submap known by its index and pose alone until it is given its finished grid: the pose graph's
        copy in a process of its own, which reads a submap's grid only once it is finished."""
        submap = cls.__new__(cls)
        submap.index = int(index)
        submap.local_pose = np.array(local_pose, dtype=np.float64)
        submap.grid = None  # type: ignore[assignment]  # read only once finished, when the grid comes
        submap.num_range_data = 0
        submap.finished = False
        return submap

    def insert(self, range_data: RangeData, inserter: ProbabilityGridRangeDataInserter) -> None:
        """Insert range data expressed in the local SLAM frame."""
        if self.finished:
            raise RuntimeError(f"submap {self.index} is finished; it takes no more range data")
        inserter.insert(range_data, self.grid)
        self.num_range_data += 1

    def finish(self) -> None:
        # Cropping to the known cells is free memory: a finished grid never grows again, nor changes.
        self.grid = self.grid.cropped()
        self.finished = True

    def retire(self) -> None:
        """Local SLAM is done with this finished submap: keep its grid packed (a corridor's submap is mostly
        unknown cells: 5-10x smaller), unpacked when read. Not at ``finish``: the next scan is still matched
        against it, and unpacking it for that one match kept a copy in the shared cache of unpacked cells."""
        if not self.grid.is_packed:
            self.grid.pack()

    def __repr__(self) -> str:
        state = "finished" if self.finished else "active"
        return f"Submap(index={self.index}, num_range_data={self.num_range_data}, {state})"


class ActiveSubmaps:
    """The (at most) two submaps currently receiving range data, oldest first."""

    def __init__(self, *, num_range_data: int = 90, resolution: float = 0.05, hit_probability: float = 0.55,
                 miss_probability: float = 0.49, insert_free_space: bool = True,
                 initial_size: int = INITIAL_SUBMAP_SIZE):
        if num_range_data < 1:
            raise ValueError("num_range_data must be at least 1")
        self.num_range_data = int(num_range_data)
        self.resolution = float(resolution)
        self.initial_size = int(initial_size)
        self.inserter = ProbabilityGridRangeDataInserter(
            hit_probability=hit_probability, miss_probability=miss_probability,
            insert_free_space=insert_free_space)
        self.submaps: list[Submap] = []
        self.num_submaps_created = 0

    @property
    def matching_submap(self) -> Submap | None:
        """The submap scans are matched against: the older active one."""
        return self.submaps[0] if self.submaps else None

    def insert(self, range_data: RangeData, timer: StageTimer | NullTimer | None = None) -> list[Submap]:
        """Insert range data (local frame) into every active submap; returns those submaps.

        The front submap of the returned list may have just been finished:
        callers hand it to the pose graph when ``finished`` is set. Rays are
        cast once for both submaps; ``timer`` gets the ``ray casting`` and
        ``update`` stages.
        """
        if not self.submaps or self.submaps[-1].num_range_data == self.num_range_data:
            self._add_submap(range_data.origin)
        self.inserter.insert_many(range_data, [submap.grid for submap in self.submaps], timer)
        for submap in self.submaps:
            submap.num_range_data += 1
        inserted = list(self.submaps)
        if self.submaps[0].num_range_data == 2 * self.num_range_data:
            self.submaps[0].finish()
        return inserted

    def _add_submap(self, origin: ArrayLike) -> None:
        if len(self.submaps) >= 2:
            # The front one was finished on the previous insertion; only the pose graph keeps it now.
            assert self.submaps[0].finished
            self.submaps.pop(0).retire()
        self.submaps.append(Submap(origin, resolution=self.resolution, index=self.num_submaps_created,
                                   initial_size=self.initial_size))
        self.num_submaps_created += 1
