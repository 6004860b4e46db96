"""The SLAM core: local SLAM (extrapolator, motion filter, submaps), the pose graph with its loop-closure
search and optimization, and the Slam object tying them together. It knows no file."""
