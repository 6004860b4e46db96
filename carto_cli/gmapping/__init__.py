"""GMapping (Grisetti et al.'s Rao-Blackwellized particle filter), carto's second mapping system.

``filter.GMappingSlam`` is the core object; ``maps`` holds the particles' copy-on-write maps,
``matcher`` the scan matcher and improved proposal, ``motion`` the odometry motion model and
``resampling`` the weights and selective resampling. The package itself imports nothing heavy, so that
naming the algorithms costs nothing (the CLI checks ``--algorithm`` against ``ALGORITHMS``).
"""

from carto_cli.core.enums import TextEnum


class Algorithm(TextEnum):
    """carto's mapping systems, by the names ``--algorithm`` takes."""

    CARTOGRAPHER = "cartographer"
    GMAPPING = "gmapping"
    SCAN_TO_MAP = "scan-to-map"


ALGORITHMS = tuple(a.value for a in Algorithm)  # the names, for choices and messages
# The systems that run GMapping's processed-scan pipeline and take its options (``gmapping.*``): the particle
# filter, and one pose matched on a distance map (``front_end.ScanToMapSlam``).
GMAPPING_PIPELINE = frozenset({Algorithm.GMAPPING, Algorithm.SCAN_TO_MAP})

__all__ = ["ALGORITHMS", "GMAPPING_PIPELINE", "Algorithm"]
