"""Local SLAM stages that touch points: range cropping and voxel filters."""
