"""GMapping (Grisetti et al.'s Rao-Blackwellized particle filter), carto's second mapping system.

``filter.GMappingSlam`` is the core object; ``maps`` holds the particles' copy-on-write maps,
``matcher`` the scan matcher and improved proposal, ``motion`` the odometry motion model and
``resampling`` the weights and selective resampling. The package itself imports nothing heavy, so that
naming the algorithms costs nothing (the CLI checks ``--algorithm`` against ``ALGORITHMS``).
"""

ALGORITHMS = ("cartographer", "gmapping", "scan-to-map")
# The systems that run GMapping's processed-scan pipeline and take its options (``gmapping.*``): the particle
# filter, and one pose matched on a distance map (``front_end.ScanToMapSlam``).
GMAPPING_PIPELINE = frozenset({"gmapping", "scan-to-map"})

__all__ = ["ALGORITHMS", "GMAPPING_PIPELINE"]
