"""The map as ROS map_server / nav2 load it (PGM + YAML), and a PNG for people with the trajectory drawn on."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from carto_cli.core.errors import CartoError
from carto_cli.grid.occupancy_image import OccupancyImage
from carto_cli.io.atomic import atomic_output, write_text_atomic

UNKNOWN = 205  # map_server's "unknown" grey; (255-205)/255 = 0.196 sits exactly on free_thresh, so it stays unknown
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196


def to_pgm_pixels(image: OccupancyImage, trinary: bool = False) -> np.ndarray:
    """uint8 image, row 0 at the top; unknown 205.

    Continuous (for people): grey levels 255·(1 − p), as Cartographer paints submaps.
    Trinary (for navigation): a cell with more hit than miss evidence is occupied (0),
    one with more miss evidence free (254). With hit 0.55 / miss 0.49 a corridor seen
    a handful of times stays near p = 0.4, which map_server's free_thresh (0.196) would
    call unknown, leaving a planner nothing to drive on; the evidence balance is what
    the grid actually knows.
    """
    p = image.probability
    known = ~np.isnan(p)
    pixels = np.full(p.shape, UNKNOWN, dtype=np.uint8)
    if trinary:
        pixels[known & (p > 0.5)] = 0
        pixels[known & (p < 0.5)] = 254
    else:
        # map_server reads occupancy as (255 - value) / 255 with negate 0.
        values = np.clip(np.rint(255.0 * (1.0 - np.where(known, p, 0.5))), 0, 254).astype(np.uint8)
        pixels[known] = values[known]
    return np.ascontiguousarray(pixels[::-1])


def _pgm_bytes(pixels: np.ndarray) -> bytes:
    h, w = pixels.shape
    return f"P5\n# carto map\n{w} {h}\n255\n".encode() + pixels.tobytes()


def map_yaml(image_name: str, image: OccupancyImage) -> str:
    ox, oy = image.origin
    return (
        f"image: {image_name}\n"
        f"mode: trinary\n"
        f"resolution: {image.resolution:.6g}\n"
        f"origin: [{ox:.6f}, {oy:.6f}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
    )


def write_map(outdir: Path, image: OccupancyImage, stem: str = "map") -> tuple[Path, Path]:
    """Write ``stem.pgm`` and ``stem.yaml``; the YAML goes last so a reader never sees it without its image."""
    if image.probability.size == 0:
        raise CartoError("the map is empty: no scan was inserted", outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    pgm = outdir / f"{stem}.pgm"
    yml = outdir / f"{stem}.yaml"
    with atomic_output(pgm) as tmp:
        tmp.write_bytes(_pgm_bytes(to_pgm_pixels(image, trinary=True)))
    write_text_atomic(yml, map_yaml(pgm.name, image))
    return pgm, yml


def render_png(
    image: OccupancyImage,
    trajectory_xy: np.ndarray | None = None,
    constraints_xy: np.ndarray | None = None,
    scale: int = 1,
) -> np.ndarray:
    """BGR image: the map in grey, loop-closure constraints in green, the trajectory in red."""
    grey = to_pgm_pixels(image)
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    if scale > 1:
        bgr = cv2.resize(bgr, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    shift = 4  # cv2 draws with fixed-point sub-pixel coordinates
    if constraints_xy is not None and len(constraints_xy):
        a = np.rint(image.world_to_pixel(constraints_xy[:, :2]) * scale * (1 << shift)).astype(np.int32)
        b = np.rint(image.world_to_pixel(constraints_xy[:, 2:4]) * scale * (1 << shift)).astype(np.int32)
        for p, q in zip(a, b):
            cv2.line(bgr, tuple(p), tuple(q), (60, 170, 60), 1, cv2.LINE_AA, shift)
    if trajectory_xy is not None and len(trajectory_xy) > 1:
        pts = np.rint(image.world_to_pixel(trajectory_xy[:, :2]) * scale * (1 << shift)).astype(np.int32)
        cv2.polylines(bgr, [pts.reshape(-1, 1, 2)], False, (40, 40, 220), 1, cv2.LINE_AA, shift)
    return bgr


def write_png(path: Path, bgr: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise CartoError("could not encode the PNG", path)
    with atomic_output(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return path
