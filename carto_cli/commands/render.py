"""`carto render` as a library call: a saved map re-exported without its recording (Cartographer's
pbstream_to_ros_map): map_server PGM + YAML at any resolution or thresholds, and the PNG for people."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.grid.occupancy_image import AssembledImage, OccupancyImage
from carto_cli.io.atomic import existing_outputs, output_set
from carto_cli.io.loaded_map import LoadedMap
from carto_cli.io.map_file import load_map
from carto_cli.io.map_image import render_png, write_map, write_png
from carto_cli.io.pbstream import save_pbstream
from carto_cli.mapping.cleaning import cleaned_image

__all__ = ["RENDER_OUTPUTS", "Rendered", "map_image_of", "run_render"]

RENDER_OUTPUTS = ("map.pgm", "map.scale.png", "map.yaml", "map.png", "map.pbstream")


@dataclass
class Rendered:
    image_file: Path  # map.pgm (trinary) or map.scale.png (scale)
    yaml: Path
    png: Path
    image: OccupancyImage | AssembledImage
    pbstream: Path | None = None  # Cartographer's state of the same map, when asked for


def map_image_of(loaded: LoadedMap, resolution: float | None = None) -> AssembledImage:
    """The occupancy image of a saved map's submaps at their optimized poses (at ``resolution``, default the
    submaps' own), as `carto map` assembles it."""
    corrections = [transform.compose(g, transform.inverse(s.local_pose))
                   for s, g in zip(loaded.submaps, loaded.submap_global_poses)]
    return AssembledImage([s.grid for s in loaded.submaps], corrections, resolution)


def run_render(map_file: Path, outdir: Path, *, resolution: float | None = None, mode: str = "trinary",
               occupied_thresh: float | None = None, free_thresh: float | None = None,
               png_scale: int | None = None, force: bool = False, pbstream: bool = False,
               keep_transient: bool = False, show_removed: bool = False) -> Rendered:
    """Write map.pgm (or map.scale.png with ``mode`` 'scale') + map.yaml and map.png of ``map_file`` into
    ``outdir`` as one set; an earlier set there is replaced only with ``force``. Thresholds are probabilities;
    without them a cell is occupied or free by the balance of its evidence, as `carto map` writes it. ``map_file``
    is a map.carto or Cartographer's .pbstream; ``pbstream`` also writes the map as Cartographer's state
    (map.pbstream: Cartographer's tools and ``--load_state_filename`` read it). What cleaning drew free when the
    map was made (``LoadedMap.transients``) is drawn free again unless ``keep_transient``; ``show_removed`` marks it
    in map.png."""
    if resolution is not None and not resolution > 0:
        raise CartoError(f"--resolution must be > 0 m, got {resolution:g}")
    if png_scale is not None and png_scale < 1:
        raise CartoError(f"--png-scale must be >= 1, got {png_scale}")
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise CartoError("exists and is not a directory; the outputs go into a directory (give another -o)", outdir)
    taken = existing_outputs(outdir, RENDER_OUTPUTS)
    if taken and not force:
        raise CartoError(f"already holds a map ({', '.join(taken)}); --force replaces it, or give another -o", outdir)
    loaded = load_map(map_file)
    image: OccupancyImage | AssembledImage = map_image_of(loaded, resolution)
    if 0 in image.shape:
        raise CartoError("the map has no known cell to render", map_file)
    removed = loaded.transients
    if removed is not None and len(removed) and not keep_transient:
        image = cleaned_image(image, removed)
    trajectory = None if loaded.trajectory is None else loaded.trajectory.poses
    if trajectory is None and loaded.num_nodes:
        trajectory = np.asarray(loaded.node_global_poses)
    mask = loaded.constraints.is_loop_closure
    closures = np.concatenate([np.asarray(loaded.node_global_poses)[loaded.constraints.node[mask], :2],
                               np.asarray(loaded.submap_global_poses)[loaded.constraints.submap[mask], :2]], axis=1)
    with output_set(outdir, RENDER_OUTPUTS) as staging:
        img, yml = write_map(staging, image, mode=mode, occupied_thresh=occupied_thresh, free_thresh=free_thresh)
        marked = removed.centres() if show_removed and removed is not None else None
        write_png(staging / "map.png", render_png(image, trajectory, closures, scale=png_scale, removed_xy=marked))
        if pbstream:
            save_pbstream(staging / "map.pbstream", loaded)
    return Rendered(outdir / img.name, outdir / yml.name, outdir / "map.png", image,
                    outdir / "map.pbstream" if pbstream else None)
