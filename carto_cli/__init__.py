"""carto: 2D LiDAR SLAM from recorded data, in the tradition of Cartographer."""

__version__ = "0.1.0"
