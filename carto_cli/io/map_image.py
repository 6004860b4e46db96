"""The map as ROS map_server / nav2 load it (PGM + YAML), and a PNG for people with the trajectory drawn on."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from carto_cli.core.errors import CartoError
from carto_cli.grid.occupancy_image import AssembledImage, OccupancyImage, coarsened, image_rows
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
    return np.ascontiguousarray(_pgm_rows(image.probability, trinary)[::-1])


def _pgm_rows(p: np.ndarray, trinary: bool) -> np.ndarray:
    """``to_pgm_pixels`` of rows of probabilities, in their own order."""
    known = ~np.isnan(p)
    pixels = np.full(p.shape, UNKNOWN, dtype=np.uint8)
    if trinary:
        pixels[known & (p > 0.5)] = 0
        pixels[known & (p < 0.5)] = 254
    else:
        # map_server reads occupancy as (255 - value) / 255 with negate 0.
        values = np.clip(np.rint(255.0 * (1.0 - np.where(known, p, 0.5))), 0, 254).astype(np.uint8)
        pixels[known] = values[known]
    return pixels


def _pgm_header(h: int, w: int) -> bytes:
    return f"P5\n# carto map\n{w} {h}\n255\n".encode()


def map_yaml(image_name: str, image: OccupancyImage | AssembledImage, mode: str = "trinary",
             occupied_thresh: float = OCCUPIED_THRESH, free_thresh: float = FREE_THRESH) -> str:
    ox, oy = image.origin
    return (
        f"image: {image_name}\n"
        f"mode: {mode}\n"
        f"resolution: {image.resolution:.6g}\n"
        f"origin: [{ox:.6f}, {oy:.6f}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {float(occupied_thresh)}\n"
        f"free_thresh: {float(free_thresh)}\n"
    )


def _checked_thresholds(occupied_thresh: float | None, free_thresh: float | None) -> tuple[float, float]:
    occ = OCCUPIED_THRESH if occupied_thresh is None else float(occupied_thresh)
    free = FREE_THRESH if free_thresh is None else float(free_thresh)
    if not 0.0 <= free < occ <= 1.0:
        raise CartoError(f"need 0 <= --free-thresh ({free:g}) < --occupied-thresh ({occ:g}) <= 1")
    return occ, free


def _unknown_grey(occupied_thresh: float, free_thresh: float) -> int:
    """The grey of a trinary image's unknown cells: 205, map_server's own, unless the thresholds read it as free
    or occupied (map_server: occupancy (255 - grey) / 255, free below ``free_thresh``, occupied above
    ``occupied_thresh``); then the grey nearest the middle of the two that map_server reads as unknown."""
    def unknown(grey: int) -> bool:
        return free_thresh <= (255 - grey) / 255 <= occupied_thresh

    if unknown(UNKNOWN):
        return UNKNOWN
    middle = 255.0 * (1.0 - 0.5 * (occupied_thresh + free_thresh))
    greys = sorted((g for g in range(1, 254) if unknown(g)), key=lambda g: abs(g - middle))
    if not greys:
        raise CartoError(f"--free-thresh ({free_thresh:g}) and --occupied-thresh ({occupied_thresh:g}) are closer "
                         "than one grey level: map_server would read no pixel as unknown")
    return greys[0]


def _thresholded_rows(p: np.ndarray, occupied_thresh: float, free_thresh: float, unknown: int) -> np.ndarray:
    known = ~np.isnan(p)
    pixels = np.full(p.shape, unknown, dtype=np.uint8)
    pixels[known & (p >= occupied_thresh)] = 0
    pixels[known & (p <= free_thresh)] = 254
    return pixels


def _scale_bgra(image: OccupancyImage | AssembledImage) -> np.ndarray:
    """map_server 'scale' mode keeps the probability: grey 255 (1 - p); never-seen cells transparent, which is
    the only way scale mode reads a cell as unknown."""
    p = image.probability
    known = ~np.isnan(p)
    grey = np.clip(np.rint(255.0 * (1.0 - np.where(known, p, 0.5))), 0, 255).astype(np.uint8)
    bgra = np.dstack([grey, grey, grey, np.where(known, 255, 0).astype(np.uint8)])
    return np.ascontiguousarray(bgra[::-1])


def write_map(outdir: Path, image: OccupancyImage | AssembledImage, stem: str = "map", *, mode: str = "trinary",
              occupied_thresh: float | None = None, free_thresh: float | None = None) -> tuple[Path, Path]:
    """Write the map_server image and ``stem.yaml``; the YAML goes last so a reader never sees it without its image.

    ``trinary`` (``stem.pgm``): without thresholds a cell is occupied or free by the balance of its evidence
    (``to_pgm_pixels``); with ``occupied_thresh`` / ``free_thresh`` by its probability, cells in between unknown.
    ``scale`` (``stem.scale.png``, grey and alpha): the probability itself, which map_server cuts at the YAML's
    thresholds (occupied above ``occupied_thresh``, free below ``free_thresh``, 1..99 between).
    The YAML carries the thresholds given (default 0.65 / 0.196).
    """
    if 0 in image.shape:
        raise CartoError("the map is empty: no scan was inserted", outdir)
    if mode not in ("trinary", "scale"):
        raise CartoError(f"--mode must be trinary or scale, got {mode!r}")
    occ, free = _checked_thresholds(occupied_thresh, free_thresh)
    outdir.mkdir(parents=True, exist_ok=True)
    yml = outdir / f"{stem}.yaml"
    if mode == "scale":
        img = outdir / f"{stem}.scale.png"
        ok, buf = cv2.imencode(".png", _scale_bgra(image))
        if not ok:
            raise CartoError("could not encode the PNG", img)
        with atomic_output(img) as tmp:
            tmp.write_bytes(buf.tobytes())
    else:
        img = outdir / f"{stem}.pgm"
        if occupied_thresh is None and free_thresh is None:
            def pixels(rows: np.ndarray) -> np.ndarray:
                return _pgm_rows(rows, True)
        else:
            grey = _unknown_grey(occ, free)

            def pixels(rows: np.ndarray) -> np.ndarray:
                return _thresholded_rows(rows, occ, free, grey)
        # Strip by strip, top first: a campus-sized map is never held whole (grid.occupancy_image.AssembledImage).
        with atomic_output(img) as tmp, open(tmp, "wb") as f:
            f.write(_pgm_header(*image.shape))
            for rows in image_rows(image):
                f.write(np.ascontiguousarray(pixels(rows)).tobytes())
    write_text_atomic(yml, map_yaml(img.name, image, mode, occ, free))
    return img, yml


# What a person reads (map.png): free white, walls black, never seen a mid grey that is neither; in between,
# evidence shades the free side towards light grey and the wall side towards dark grey.
PNG_UNKNOWN = 160
PNG_FREE = 255  # p = 0.1 (certainly free) ... PNG_FREE_EDGE at p = 0.5
PNG_FREE_EDGE = 215
PNG_WALL_EDGE = 110  # p just above 0.5 ... 0 at p = 0.9
PNG_TARGET_PX = 900  # the longer side of map.png is scaled up towards this (whole multiples, at most 8x)
PNG_MAX_PX = 4096  # a map longer than this (cells) is drawn with whole blocks of cells per pixel to fit
_FOOTER_PX = 34
# map.png's colours (BGR). The start is blue, not a green like the loop closures': on a map dense with closures
# (aces) a green start dot was lost among them.
PATH_BGR = (40, 40, 220)
START_BGR = (200, 90, 10)
LOOP_CLOSURE_BGR = (60, 170, 60)
REMOVED_BGR = (0, 140, 255)  # orange: what cleaning drew free (--show-removed)


def to_png_pixels(image: OccupancyImage | AssembledImage) -> np.ndarray:
    """uint8 grey levels for people (PNG_* above), row 0 at the top."""
    p = image.probability
    known = ~np.isnan(p)
    q = np.where(known, p, 0.5)
    free = PNG_FREE - (np.clip(q, 0.1, 0.5) - 0.1) / 0.4 * (PNG_FREE - PNG_FREE_EDGE)
    wall = PNG_WALL_EDGE * (0.9 - np.clip(q, 0.5, 0.9)) / 0.4
    grey = np.where(q <= 0.5, free, wall)
    pixels = np.full(p.shape, PNG_UNKNOWN, dtype=np.uint8)
    pixels[known] = np.clip(np.rint(grey[known]), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(pixels[::-1])


def png_scale_for(image: OccupancyImage | AssembledImage) -> int:
    """The default upscaling of map.png: a whole factor bringing the longer side towards PNG_TARGET_PX."""
    longest = max(image.shape) if 0 not in image.shape else 1
    return int(min(8, max(1, PNG_TARGET_PX // max(longest, 1))))


def _nice_length(metres: float) -> float:
    """The largest 1 / 2 / 5 x 10^k not above ``metres``."""
    if metres <= 0:
        return 1.0
    k = math.floor(math.log10(metres))
    for m in (5.0, 2.0, 1.0):
        if m * 10 ** k <= metres:
            return m * 10 ** k
    return 10 ** k


def render_png(
    image: OccupancyImage | AssembledImage,
    trajectory_xy: np.ndarray | None = None,
    constraints_xy: np.ndarray | None = None,
    scale: int | None = None,
    legend: bool = True,
    removed_xy: np.ndarray | None = None,
) -> np.ndarray:
    """BGR image for people: the map (``to_png_pixels``) scaled by ``scale`` (default ``png_scale_for``),
    loop-closure constraints in green, the trajectory in red with its start (blue dot, drawn last so nothing hides
    it) and end (red square), and below it a footer with a scale bar and a legend. ``removed_xy``: the centres of
    cells cleaning drew free (``mapping.cleaning``), marked in orange."""
    longest = max(image.shape) if 0 not in image.shape else 1
    if longest > PNG_MAX_PX:
        # A campus at 5 cm is 20,000 cells across: drawn whole it would take gigabytes, and no screen shows it.
        image = coarsened(image, math.ceil(longest / PNG_MAX_PX))
    scale = png_scale_for(image) if scale is None else int(scale)
    if scale < 1:
        raise CartoError(f"--png-scale must be a whole number >= 1, got {scale}")
    grey = to_png_pixels(image)
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    if scale > 1:
        bgr = cv2.resize(bgr, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    if removed_xy is not None and len(removed_xy):
        _mark_cells(bgr, image, removed_xy, scale)
    shift = 4  # cv2 draws with fixed-point sub-pixel coordinates
    one = 1 << shift

    def px(xy: np.ndarray) -> np.ndarray:
        # world_to_pixel is continuous (pixel i spans [i, i + 1)); cv2 puts pixel i's centre at i.
        return np.rint((image.world_to_pixel(xy) * scale - 0.5) * one).astype(np.int32)

    if constraints_xy is not None and len(constraints_xy):
        a, b = px(constraints_xy[:, :2]), px(constraints_xy[:, 2:4])
        for p, q in zip(a, b):
            cv2.line(bgr, tuple(p), tuple(q), LOOP_CLOSURE_BGR, 1, cv2.LINE_AA, shift)
    if trajectory_xy is not None and len(trajectory_xy) > 1:
        pts = px(trajectory_xy[:, :2])
        cv2.polylines(bgr, [pts.reshape(-1, 1, 2)], False, PATH_BGR, 1, cv2.LINE_AA, shift)
        r = max(3, scale + 2) * one
        e = pts[-1]
        cv2.rectangle(bgr, tuple(e - r), tuple(e + r), PATH_BGR, -1, cv2.LINE_AA, shift)
        # A white ring sets the dot off from the lines under it; a loop ends where it began, so the end square
        # would cover the start if drawn after it.
        cv2.circle(bgr, tuple(pts[0]), r + one, (255, 255, 255), -1, cv2.LINE_AA, shift)
        cv2.circle(bgr, tuple(pts[0]), r, START_BGR, -1, cv2.LINE_AA, shift)
    if not legend:
        return bgr
    return _with_footer(bgr, image.resolution / scale, removed=removed_xy is not None and len(removed_xy) > 0)


def _mark_cells(bgr: np.ndarray, image, xy: np.ndarray, scale: int) -> None:
    """Paint the cells holding the points ``xy`` (map frame) in ``REMOVED_BGR``, each as its scale x scale block."""
    at = np.floor(image.world_to_pixel(np.asarray(xy, np.float64).reshape(-1, 2))).astype(np.int64)
    h, w = bgr.shape[0] // scale, bgr.shape[1] // scale
    at = at[(at[:, 0] >= 0) & (at[:, 1] >= 0) & (at[:, 0] < w) & (at[:, 1] < h)]
    for dy in range(scale):
        for dx in range(scale):
            bgr[at[:, 1] * scale + dy, at[:, 0] * scale + dx] = REMOVED_BGR


def _with_footer(bgr: np.ndarray, metres_per_px: float, removed: bool = False) -> np.ndarray:
    """The map above a white strip holding a scale bar (1 / 2 / 5 x 10^k m, about a quarter of the width) and the
    legend: free, wall, unknown, trajectory, start, end, loop closure."""
    h, w = bgr.shape[:2]
    width = max(w, 420)
    row = 18  # the legend wraps onto further rows of this height where the map is narrow
    out = np.full((h + _FOOTER_PX + 3 * row, width, 3), 255, dtype=np.uint8)
    out[:h, :w] = bgr
    font, size, ink = cv2.FONT_HERSHEY_SIMPLEX, 0.38, (30, 30, 30)
    y = h + 22
    bar_m = _nice_length(0.25 * w * metres_per_px)
    bar_px = max(1, int(round(bar_m / metres_per_px)))
    cv2.rectangle(out, (8, y - 6), (8 + bar_px, y - 2), (0, 0, 0), -1)
    label = f"{bar_m:g} m"
    cv2.putText(out, label, (12 + bar_px, y), font, size, ink, 1, cv2.LINE_AA)
    x = 12 + bar_px + cv2.getTextSize(label, font, size, 1)[0][0] + 14
    items = [("free", (PNG_FREE,) * 3, "box"), ("wall", (0, 0, 0), "box"), ("unknown", (PNG_UNKNOWN,) * 3, "box"),
             ("path", PATH_BGR, "line"), ("start", START_BGR, "dot"), ("end", PATH_BGR, "square"),
             ("loop closure", LOOP_CLOSURE_BGR, "line")] + ([("removed", REMOVED_BGR, "box")] if removed else [])
    for text, colour, kind in items:
        if x + 27 + cv2.getTextSize(text, font, size, 1)[0][0] > width:
            x, y = 8, y + row
        if kind == "box":
            cv2.rectangle(out, (x, y - 9), (x + 10, y + 1), colour, -1)
            cv2.rectangle(out, (x, y - 9), (x + 10, y + 1), (90, 90, 90), 1)
        elif kind == "line":
            cv2.line(out, (x, y - 4), (x + 12, y - 4), colour, 2, cv2.LINE_AA)
        elif kind == "dot":
            cv2.circle(out, (x + 5, y - 4), 4, colour, -1, cv2.LINE_AA)
        else:
            cv2.rectangle(out, (x + 1, y - 8), (x + 9, y), colour, -1)
        cv2.putText(out, text, (x + 15, y), font, size, ink, 1, cv2.LINE_AA)
        x += 15 + cv2.getTextSize(text, font, size, 1)[0][0] + 12
    return np.ascontiguousarray(out[:y + _FOOTER_PX - 22])


def write_png(path: Path, bgr: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise CartoError("could not encode the PNG", path)
    with atomic_output(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return path
