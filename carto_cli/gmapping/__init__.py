"""GMapping (Grisetti et al.'s Rao-Blackwellized particle filter), carto's second mapping system.

``filter.GMappingSlam`` is the core object; ``maps`` holds the particles' copy-on-write maps,
``matcher`` the scan matcher and improved proposal, ``motion`` the odometry motion model and
``resampling`` the weights and selective resampling. The package itself imports nothing heavy, so that
naming the algorithms costs nothing (the CLI checks ``--algorithm`` against ``ALGORITHMS``).
"""

ALGORITHMS = ("cartographer", "gmapping")

__all__ = ["ALGORITHMS"]
