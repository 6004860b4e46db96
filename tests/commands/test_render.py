"""`carto render`: a saved map re-exported without its recording, read back by map_server's rules cell by cell,
and the PNG people read (free white, walls black, unknown grey, scale bar and legend below)."""
import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.commands.render import run_render
from carto_cli.core.errors import CartoError
from carto_cli.io.map_image import PNG_FREE, PNG_UNKNOWN
from carto_cli.io.map_server import occupancy_from_pixels
from carto_cli.pipeline import MapRequest


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """A map of the simulated loop building written by `carto map` (map.carto, map.pgm, ...) from a bag."""
    from carto_cli.commands.map import run_map
    from carto_cli.io.recording_writers import write_recording
    from carto_cli.options import load_options
    from carto_cli.sim import loop_building, loop_trajectory, simulate

    base = tmp_path_factory.mktemp("render")
    w = loop_building()
    sim = simulate(w, loop_trajectory(w), duration=30.0, scan_rate=10.0)
    bag = base / "sim.bag"
    write_recording(iter(list(sim.records(["/scan", "/odom"]))), bag, "ros1")
    result, _ = run_map(MapRequest(bag, load_options("wheeled")), base / "map")
    return base / "map", result


def _map_server(yaml_path):
    """(occupancy rows bottom-up, YAML) as map_server would load the pair."""
    meta = yaml.safe_load(yaml_path.read_text())
    pixels = cv2.imread(str(yaml_path.parent / meta["image"]), cv2.IMREAD_UNCHANGED)
    occ = occupancy_from_pixels(pixels, mode=meta["mode"], negate=bool(meta["negate"]),
                                occupied_thresh=meta["occupied_thresh"], free_thresh=meta["free_thresh"])
    return occ[::-1], meta


def test_render_at_the_maps_resolution_is_what_map_wrote(mapped, tmp_path):
    out, _ = mapped
    done = run_render(out / "map.carto", tmp_path / "r")
    assert done.image_file.read_bytes() == (out / "map.pgm").read_bytes()
    assert (tmp_path / "r" / "map.yaml").read_text() == (out / "map.yaml").read_text()


@pytest.mark.parametrize("kwargs", [{}, {"occupied_thresh": 0.7, "free_thresh": 0.3}, {"mode": "scale"},
                                    {"resolution": 0.1}])
def test_map_server_reads_the_export_cell_by_cell(mapped, tmp_path, kwargs):
    out, _ = mapped
    done = run_render(out / "map.carto", tmp_path / "r", **kwargs)
    occ, meta = _map_server(done.yaml)
    p = done.image.probability
    assert occ.shape == p.shape and meta["resolution"] == pytest.approx(done.image.resolution)
    assert meta["origin"][:2] == pytest.approx(list(done.image.origin), abs=1e-6)
    known = ~np.isnan(p)
    if kwargs.get("mode") == "scale":
        assert (occ[~known] == -1).all()
        # the probability survives to within a grey level, and map_server's thresholds apply to it
        assert (occ[known & (p > 0.66)] == 100).all() and (occ[known & (p < 0.19)] == 0).all()
        mid = known & (p > 0.21) & (p < 0.64)
        expect = np.rint(1 + 98 * (p[mid] - 0.196) / (0.65 - 0.196))
        assert np.abs(occ[mid] - expect).max() <= 2
        return
    if "occupied_thresh" in kwargs:
        assert (occ[known & (p >= 0.7)] == 100).all() and (occ[known & (p <= 0.3)] == 0).all()
        assert (occ[known & (p > 0.3) & (p < 0.7)] == -1).all()
    else:
        assert (occ[known & (p > 0.5)] == 100).all() and (occ[known & (p < 0.5)] == 0).all()
    assert (occ[~known] == -1).all()


def test_render_thresholds_in_scale_mode_reach_map_yaml_and_map_server(mapped, tmp_path):
    """Issue 42 item 3: --occupied-thresh / --free-thresh are what map_server applies. map.yaml carries them in
    both modes; scale mode keeps the probabilities and map_server cuts them there (occupied above, free below,
    1..99 between); trinary cuts the image there, with the unknown grey still unknown under them."""
    out, _ = mapped
    for mode, occ_t, free_t in (("scale", 0.8, 0.1), ("scale", 0.75, 0.3), ("trinary", 0.8, 0.3)):
        done = run_render(out / "map.carto", tmp_path / f"{mode}{free_t}", mode=mode, occupied_thresh=occ_t,
                          free_thresh=free_t)
        occ, meta = _map_server(done.yaml)
        assert (meta["occupied_thresh"], meta["free_thresh"]) == (occ_t, free_t)
        p = done.image.probability
        known = ~np.isnan(p)
        assert (occ[~known] == -1).all()
        walls, free = known & (p > occ_t + 0.01), known & (p < free_t - 0.01)
        assert (occ[walls] == 100).all() and (occ[free] == 0).all()
        if mode == "trinary":
            assert (occ[known & (p > free_t) & (p < occ_t)] == -1).all()
            continue
        mid = known & (p > free_t + 0.01) & (p < occ_t - 0.01)
        assert walls.sum() > 100 and mid.sum() > 100  # the map has cells on both sides of the new wall cut
        assert np.abs(occ[mid] - np.rint(1 + 98 * (p[mid] - free_t) / (occ_t - free_t))).max() <= 2
        # what the defaults read differently: cells between 0.65 and the new cut are no longer walls
        assert (occ[known & (p > 0.66) & (p < occ_t - 0.01)] < 100).all()


def test_the_png_is_readable_by_people(mapped, tmp_path):
    out, _ = mapped
    done = run_render(out / "map.carto", tmp_path / "r", png_scale=2)
    png = cv2.imread(str(done.png), cv2.IMREAD_GRAYSCALE)
    p = done.image.probability
    h, w = p.shape
    assert png.shape[0] > 2 * h and png.shape[1] >= 2 * w  # the map at 2 px a cell, and a footer below
    body = png[:2 * h:2, :2 * w:2][::-1]  # one pixel per cell, bottom-up like the grid
    free, wall, unknown = p < 0.15, p > 0.85, np.isnan(p)
    # away from the drawn trajectory most cells show their class's grey
    assert np.mean(body[free] >= PNG_FREE - 5) > 0.95
    assert np.mean(body[wall] <= 10) > 0.95
    assert np.mean(body[unknown] == PNG_UNKNOWN) > 0.95
    footer = png[2 * h:]
    assert footer.min() < 60 and footer.max() == 255  # a scale bar and legend text on white


def test_bad_requests_are_one_line_errors(mapped, tmp_path):
    out, _ = mapped
    with pytest.raises(CartoError, match="--resolution must be > 0"):
        run_render(out / "map.carto", tmp_path / "a", resolution=0)
    with pytest.raises(CartoError, match="--free-thresh"):
        run_render(out / "map.carto", tmp_path / "b", occupied_thresh=0.3, free_thresh=0.6)
    with pytest.raises(CartoError, match="closer than one grey level"):
        run_render(out / "map.carto", tmp_path / "b", occupied_thresh=0.501, free_thresh=0.5)
    assert not (tmp_path / "b").exists()
    run_render(out / "map.carto", tmp_path / "c")
    r = CliRunner().invoke(app, ["render", str(out / "map.carto"), "-o", str(tmp_path / "c")])
    assert r.exit_code == 2 and "--force" in r.output
    r = CliRunner().invoke(app, ["render", str(out / "map.carto"), "-o", str(tmp_path / "c"), "--force",
                                 "--mode", "scale"])
    assert r.exit_code == 0 and not (tmp_path / "c" / "map.pgm").exists()  # the set is this run's, not mixed
    assert (tmp_path / "c" / "map.scale.png").exists()


def test_a_map_handed_to_cartographer_and_back(mapped, tmp_path):
    """--pbstream writes the map as Cartographer's state; carto renders, relocalizes in and continues that file
    as it does the map.carto it came from."""
    from carto_cli.commands.relocalize import RelocalizeRequest, RelocalizeScans, run_relocalize

    mapdir, _ = mapped
    done = run_render(mapdir / "map.carto", tmp_path / "out", pbstream=True)
    assert done.pbstream == tmp_path / "out" / "map.pbstream" and done.pbstream.read_bytes()[:2] == b"\xdb\x01"
    again = run_render(done.pbstream, tmp_path / "again")
    assert again.image_file.read_bytes() == (mapdir / "map.pgm").read_bytes()
    bag = mapdir.parent / "sim.bag"
    poses = [run_relocalize(RelocalizeScans(RelocalizeRequest(m, bag), scan_index=150, global_search=True)).result.pose
             for m in (mapdir / "map.carto", done.pbstream)]
    assert np.allclose(poses[0], poses[1], atol=1e-6)
    runner = CliRunner()
    r = runner.invoke(app, ["map", str(bag), "-o", str(tmp_path / "more"), "--profile", "wheeled",
                            "--load-state", str(done.pbstream)])
    assert r.exit_code == 0, r.output
