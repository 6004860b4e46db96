"""Probability grids, inserting range data into them, and the occupancy image assembled from many grids."""
