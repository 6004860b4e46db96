"""GMapping (Grisetti et al.'s Rao-Blackwellized particle filter), carto's second mapping system.

``filter.GMappingSlam`` is the core object; ``maps`` holds the particles' copy-on-write maps,
``matcher`` the scan matcher and improved proposal, ``motion`` the odometry motion model and
``resampling`` the weights and selective resampling. The package itself imports nothing heavy, so that
naming the algorithms costs nothing (the CLI checks ``--algorithm`` against ``ALGORITHMS``).
"""

import enum


class Algorithm(str, enum.Enum):
    """carto's mapping systems, by the names ``--algorithm`` takes (a ``str`` with its value, as reports write it)."""

    CARTOGRAPHER = "cartographer"
    GMAPPING = "gmapping"
    SCAN_TO_MAP = "scan-to-map"

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


ALGORITHMS = tuple(a.value for a in Algorithm)  # the names, for choices and messages
# The systems that run GMapping's processed-scan pipeline and take its options (``gmapping.*``): the particle
# filter, and one pose matched on a distance map (``front_end.ScanToMapSlam``).
GMAPPING_PIPELINE = frozenset({Algorithm.GMAPPING, Algorithm.SCAN_TO_MAP})

__all__ = ["ALGORITHMS", "GMAPPING_PIPELINE", "Algorithm"]
