"""Files in and out: recording sources, the map file, map images, trajectories, recording writers; every
write atomic."""
