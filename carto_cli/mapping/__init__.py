"""Grids, submaps, local SLAM, the pose graph and map assembly."""
