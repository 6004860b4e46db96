"""map_server YAML + image read as a relocalization map: map_server's pixel semantics, tiles, errors."""
import math

import cv2
import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.core.errors import FormatError
from carto_cli.grid.probability_grid import UNKNOWN_VALUE, VALUE_TO_PROBABILITY
from carto_cli.io import map_server
from carto_cli.io.map_server import is_map_server_yaml, load_map_server, occupancy_from_pixels


def _write(tmp_path, pixels, *, name="m", ext="pgm", **yaml_fields):
    image = tmp_path / f"{name}.{ext}"
    assert cv2.imwrite(str(image), pixels)
    fields = {"image": image.name, "resolution": 0.05, "origin": "[0.0, 0.0, 0.0]", **yaml_fields}
    (tmp_path / f"{name}.yaml").write_text("".join(f"{k}: {v}\n" for k, v in fields.items()))
    return tmp_path / f"{name}.yaml"


def test_trinary_scale_raw_and_negate_follow_map_server():
    # occupancy = (255 - v) / 255 with negate 0: 0 -> 1.0, 254 -> 0.004, 205 -> 0.196 (on free_thresh: unknown)
    # 100 -> 0.608 (between the thresholds: unknown in trinary), 80 -> 0.686 (occupied)
    px = np.array([[0, 254, 205, 100, 80]], dtype=np.uint8)
    assert occupancy_from_pixels(px).tolist() == [[100, 0, -1, -1, 100]]
    scale = occupancy_from_pixels(np.array([[0, 254, 150]], np.uint8), mode="scale")
    occ = (255 - 150) / 255
    assert scale.tolist() == [[100, 0, round(1 + 98 * (occ - 0.196) / (0.65 - 0.196))]]
    # negate: the value itself is the occupancy
    assert occupancy_from_pixels(np.array([[255, 0]], np.uint8), negate=True).tolist() == [[100, 0]]
    # raw: the value is the occupancy 0..100; anything above is unknown
    assert occupancy_from_pixels(np.array([[0, 42, 100, 101, 255]], np.uint8), mode="raw").tolist() == \
        [[0, 42, 100, -1, -1]]
    # colour: the mean of the channels; a transparent pixel is unknown in every mode
    bgra = np.array([[[0, 0, 0, 255], [0, 0, 0, 0], [254, 254, 254, 255]]], np.uint8)
    assert occupancy_from_pixels(bgra).tolist() == [[100, -1, 0]]


def test_grid_matches_the_image_with_walls_widened(tmp_path):
    px = np.full((40, 60), 254, np.uint8)  # free
    px[:, :5] = 205  # unknown strip on the left
    px[20, 10:50] = 0  # a wall along x, image row 20 (from the top)
    m = load_map_server(_write(tmp_path, px, origin="[1.0, 2.0, 0.0]"))
    assert len(m.submaps) == 1 and m.mode == "trinary"
    grid = m.submaps[0].grid
    # the wall: image row 20 from the top is grid row 40 - 1 - 20 = 19 from the bottom
    world = np.array([[1.0 + 30.5 * 0.05, 2.0 + 19.5 * 0.05]])
    grid_xy = transform.apply(transform.compose(m.submaps[0].local_pose, transform.inverse(m.submap_global_poses[0])),
                              world)
    ix, iy = grid.cell_index(grid_xy)[0]
    p = VALUE_TO_PROBABILITY[grid.cells[iy, ix]]
    assert p == pytest.approx(0.9, abs=1e-3)
    # beside the wall: raised above free, farther away: free
    assert 0.3 < VALUE_TO_PROBABILITY[grid.cells[iy + 1, ix]] < 0.9
    assert VALUE_TO_PROBABILITY[grid.cells[iy + 5, ix]] == pytest.approx(0.1, abs=1e-3)
    # the unknown strip stays unknown (cropped away entirely: the grid starts at the first known column)
    assert grid.origin[0] == pytest.approx(5 * 0.05)
    assert (grid.cells[:, :1] != UNKNOWN_VALUE).all()


def test_large_images_are_tiled_and_tiles_agree(tmp_path, monkeypatch):
    monkeypatch.setattr(map_server, "TILE_CELLS", 32)
    monkeypatch.setattr(map_server, "TILE_MARGIN_CELLS", 8)
    rng = np.random.default_rng(0)
    px = np.where(rng.random((70, 100)) < 0.1, 0, 254).astype(np.uint8)
    m = load_map_server(_write(tmp_path, px, origin="[-3.0, 4.0, 0.5]"))
    assert len(m.submaps) == 3 * 4
    # every tile says the same about a world point they share
    pt = transform.apply(m.origin, np.array([[40.5 * 0.05, 30.5 * 0.05]]))
    seen = set()
    for s, g in zip(m.submaps, m.submap_global_poses):
        local = transform.apply(transform.compose(s.local_pose, transform.inverse(g)), pt)
        cell = s.grid.cell_index(local)
        if s.grid.contains(cell)[0]:
            seen.add(int(s.grid.cells[cell[0, 1], cell[0, 0]]))
    assert len(seen) == 1


@pytest.mark.parametrize("yaml_text, expected", [
    ("image: nothere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "does not exist"),
    ("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n", "'resolution' must be > 0"),
    ("image: m.pgm\nresolution: 0.05\norigin: [0, zero]\n", "'origin' must be"),
    ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: fancy\n", "'mode' must be one of"),
    ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 2\n", "'negate' must be 0 or 1"),
    ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nfree_thresh: 0.9\n", "free_thresh"),
    ("resolution: 0.05\n", "no 'image' key"),
    ("image: [unclosed\n", "not valid YAML"),
])
def test_bad_yaml_is_one_clear_error(tmp_path, yaml_text, expected):
    cv2.imwrite(str(tmp_path / "m.pgm"), np.zeros((4, 4), np.uint8))
    path = tmp_path / "bad.yaml"
    path.write_text(yaml_text)
    with pytest.raises(FormatError) as e:
        load_map_server(path)
    assert expected in str(e.value) and "\n" not in str(e.value)


def test_unreadable_or_empty_images_are_errors(tmp_path):
    (tmp_path / "junk.pgm").write_bytes(b"not an image")
    (tmp_path / "a.yaml").write_text("image: junk.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(FormatError, match="not an image"):
        load_map_server(tmp_path / "a.yaml")
    with pytest.raises(FormatError, match="no known cell"):
        load_map_server(_write(tmp_path, np.full((5, 5), 205, np.uint8), name="u"))
    with pytest.raises(FormatError, match="no such map file"):
        load_map_server(tmp_path / "missing.yaml")
    assert is_map_server_yaml("x/map.yaml") and is_map_server_yaml("M.YML") and not is_map_server_yaml("map.carto")


def test_origin_yaw_rotates_the_image_about_its_corner(tmp_path):
    px = np.full((20, 30), 254, np.uint8)
    px[5, 7] = 0  # one occupied pixel: row 5 from the top = grid row 14, column 7
    m = load_map_server(_write(tmp_path, px, origin=f"[1.0, 2.0, {math.pi / 2}]"))
    g = m.submaps[0].grid
    iy, ix = np.argwhere(VALUE_TO_PROBABILITY[g.cells] > 0.89)[0]
    centre_grid = g.cell_center(np.array([[ix, iy]]))[0]
    to_map = transform.compose(m.submap_global_poses[0], transform.inverse(m.submaps[0].local_pose))
    world = transform.apply(to_map, centre_grid[None])[0]
    # image coordinates (7.5, 14.5) cells, rotated by +90 deg about the corner (1, 2)
    assert world == pytest.approx([1.0 - 14.5 * 0.05, 2.0 + 7.5 * 0.05])
