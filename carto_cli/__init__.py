"""carto: 2D LiDAR SLAM from recorded data, in the tradition of Cartographer."""

from carto_cli.core import kernel_cache as _kernel_cache

__version__ = "0.1.0"

# Before any module defines a kernel: compiled kernels go to a per-user cache, never into the package.
_kernel_cache.choose()
