"""The map_server image written strip by strip, and map.png of a map too large to draw cell by cell."""
import numpy as np

from carto_cli.grid.occupancy_image import AssembledImage, assemble
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.io import map_image


def _grids():
    rng = np.random.default_rng(4)
    grids, corrections = [], []
    for k in range(2):
        g = ProbabilityGrid(0.05, (2.0 * k, 0.0), (400, 300))
        g.set_probability(rng.integers(0, 300, size=(900, 2)), 0.9)
        g.set_probability(rng.integers(0, 300, size=(900, 2)), 0.2)
        grids.append(g)
        corrections.append(np.array([0.5 * k, 0.2, 0.3 * k]))
    return grids, corrections


def test_the_pgm_written_in_strips_is_the_whole_images(tmp_path):
    grids, corrections = _grids()
    whole = assemble(grids, corrections)
    lazy = AssembledImage(grids, corrections)
    for kwargs in ({}, {"occupied_thresh": 0.7, "free_thresh": 0.3}):
        a, _ = map_image.write_map(tmp_path / "a", whole, **kwargs)
        b, _ = map_image.write_map(tmp_path / "b", lazy, **kwargs)
        assert a.read_bytes() == b.read_bytes()
    pixels = map_image.to_pgm_pixels(whole, trinary=True)  # the whole image at once, as before strips
    h, w = pixels.shape
    expected = f"P5\n# carto map\n{w} {h}\n255\n".encode() + pixels.tobytes()
    assert map_image.write_map(tmp_path / "c", whole)[0].read_bytes() == expected


def test_a_map_longer_than_png_max_px_is_drawn_with_blocks_of_cells(monkeypatch):
    grids, corrections = _grids()
    lazy = AssembledImage(grids, corrections)
    monkeypatch.setattr(map_image, "PNG_MAX_PX", 100)
    bgr = map_image.render_png(lazy, legend=False)
    factor = -(-max(lazy.shape) // 100)
    coarse = (-(-lazy.shape[0] // factor), -(-lazy.shape[1] // factor))
    assert max(coarse) <= 100
    up = min(8, map_image.PNG_TARGET_PX // max(coarse))  # then scaled up for people as any small map
    assert bgr.shape[:2] == (coarse[0] * up, coarse[1] * up)


def test_start_marker_and_loop_closures_have_distinct_colours():
    """Issue 42, item 10: the start dot and the loop-closure lines were two nearly equal greens, so on a map dense
    with loop closures (aces) the start was lost among them; in the legend too."""
    from carto_cli.grid.occupancy_image import OccupancyImage

    image = OccupancyImage(np.full((100, 100), 0.1, np.float32), 0.1, (0.0, 0.0))  # 10 m of free space
    trajectory = np.array([[2.0, 2.0, 0.0], [8.0, 2.0, 0.0], [8.0, 8.0, 0.0]])
    closures = np.array([[2.0, 2.0, 8.0, 8.0], [2.0, 8.0, 8.0, 2.0]])  # one of them from the start
    bgr = map_image.render_png(image, trajectory, closures, scale=4)

    def at(xy):
        col, row = (image.world_to_pixel(np.array([xy])) * 4 - 0.5)[0]
        return bgr[int(round(row)), int(round(col))].astype(int)

    start, closure = at((2.0, 2.0)), at((5.0, 5.0))  # the start dot; the closures' crossing, far from any path
    assert np.abs(start - closure).max() >= 100, (start, closure)
    assert closure[1] > closure[0] + 60 and closure[1] > closure[2] + 60  # the closures stay green
    # The legend's swatches show the same two colours.
    footer = bgr[400:].reshape(-1, 3).astype(int)
    for colour in (start, closure):
        assert (np.abs(footer - colour).max(axis=1) <= 2).any(), colour
