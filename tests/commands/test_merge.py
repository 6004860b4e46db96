"""`carto merge` end to end through the CLI: two maps made alone from parts of one recording linked and written as
`carto map A B` writes its map; a map of another building linked to nothing (exit 3); a missing or corrupt map
(one line, nothing written); a .pbstream among the maps."""
import dataclasses
import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.core import transform
from carto_cli.io.map_file import load_map
from carto_cli.io.pbstream import save_pbstream
from carto_cli.io.trajectory import read_trajectory

runner = CliRunner()


def _relative_error(out, reference) -> tuple[float, float]:
    """How far the merged map puts part 1's first scan from part 0's first scan, against the truth (m, deg)."""
    first = [read_trajectory(out / f"trajectory_{k}.tum") for k in (0, 1)]
    truth = [np.array([np.interp(tr.t[0], reference[:, 0], reference[:, i]) for i in (1, 2)]
                      + [reference[np.searchsorted(reference[:, 0], tr.t[0]), 3]]) for tr in first]
    got = transform.compose(transform.inverse(first[0].poses[0]), first[1].poses[0])
    want = transform.compose(transform.inverse(truth[0]), truth[1])
    gap = transform.relative(want, got)
    return math.hypot(gap[0], gap[1]), abs(math.degrees(gap[2]))


def test_two_maps_made_alone_are_linked_and_written_as_one(merge_parts, tmp_path):
    (a, b), reference = merge_parts
    out = tmp_path / "out"
    r = runner.invoke(app, ["merge", str(a / "map.carto"), str(b / "map.carto"), "-o", str(out), "-j", "1"])
    assert r.exit_code == 0, r.output
    assert "2 maps:" in r.stdout and "sessions: trajectories 0 and 1:" in r.stdout
    for name in ("map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto", "summary.json", "sessions.json",
                 "trajectory_0.tum", "trajectory_1.tum"):
        assert (out / name).is_file(), name
    report = json.loads((out / "sessions.json").read_text())
    assert [s["linked"] for s in report["sessions"]] == [True, True] and len(report["links"]) == 1
    assert json.loads((out / "summary.json").read_text())["sessions"] == report
    # Every scan of each part, in the merged map's frame, part 1 where the truth has it relative to part 0
    for k, d in enumerate((a, b)):
        assert len(read_trajectory(out / f"trajectory_{k}.tum")) == len(read_trajectory(d / "trajectory.tum"))
    metres, degrees = _relative_error(out, reference)
    assert metres < 0.1 and degrees < 1.0
    merged = load_map(out / "map.carto")
    parts = [load_map(d / "map.carto") for d in (a, b)]
    assert merged.num_nodes == sum(p.num_nodes for p in parts) and sorted(set(merged.node_trajectories)) == [0, 1]
    assert merged.metadata.recordings == tuple(p.metadata.recordings[0] for p in parts)


def test_the_merge_reports_its_progress_in_nodes(merge_parts, tmp_path):
    from carto_cli.commands.merge import run_merge

    (a, b), _ = merge_parts
    totals, done = [], []
    run_merge([a / "map.carto", b / "map.carto"], tmp_path / "out", jobs=1, on_total=totals.append,
              on_nodes=done.append)
    # Each appended key node twice (whole-map until linked, then windowed): the count ends at the total announced
    (total,) = totals
    searching = int(load_map(b / "map.carto").num_nodes)
    assert 0 < total <= 2 * searching and sum(done) == total and all(n >= 0 for n in done)


def test_a_map_of_another_building_is_linked_to_nothing(merge_parts, tmp_path):
    from carto_cli.commands.map import run_map
    from carto_cli.pipeline import Auto, MapRequest
    from carto_cli.sim.sessions import route_sessions
    from carto_cli.sim.world import room

    (a, _), _ = merge_parts
    (other,), _ = route_sessions(room(), 1)
    run_map(MapRequest(other, Auto()), tmp_path / "room")
    out = tmp_path / "out"
    r = runner.invoke(app, ["merge", str(a / "map.carto"), str(tmp_path / "room" / "map.carto"), "-o", str(out)])
    assert r.exit_code == 3, r.output
    assert "is linked to no other: left out of the map" in r.stdout
    report = json.loads((out / "sessions.json").read_text())
    assert [s["linked"] for s in report["sessions"]] == [True, False] and report["links"] == []
    # The room's submaps are left out of the image: the first map's size
    alone = (a / "map.pgm").read_bytes().split(b"\n", 3)[2]
    assert (out / "map.pgm").read_bytes().split(b"\n", 3)[2] == alone


@pytest.mark.parametrize("bad", ["missing", "corrupt"])
def test_a_missing_or_corrupt_map_writes_nothing(merge_parts, tmp_path, bad):
    (a, _), _ = merge_parts
    path = tmp_path / "b.carto"
    if bad == "corrupt":
        path.write_bytes(b"CARTOMAP" + b"\0" * 40)
    out = tmp_path / "out"
    r = runner.invoke(app, ["merge", str(a / "map.carto"), str(path), "-o", str(out)])
    assert r.exit_code == 2, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("carto: error:") and "b.carto" in lines[0]
    assert not out.exists()


def test_an_earlier_map_in_the_output_is_kept_without_force(merge_parts, tmp_path):
    (a, b), _ = merge_parts
    out = tmp_path / "out"
    out.mkdir()
    (out / "map.pgm").write_bytes(b"mine")
    r = runner.invoke(app, ["merge", str(a / "map.carto"), str(b / "map.carto"), "-o", str(out)])
    assert r.exit_code == 2 and "--force" in r.stderr
    assert (out / "map.pgm").read_bytes() == b"mine"


def test_a_pbstream_merges_too(merge_parts, tmp_path):
    (a, b), reference = merge_parts
    save_pbstream(tmp_path / "b.pbstream", load_map(b / "map.carto"))
    out = tmp_path / "out"
    r = runner.invoke(app, ["merge", str(a / "map.carto"), str(tmp_path / "b.pbstream"), "-o", str(out)])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "sessions.json").read_text())
    assert [s["linked"] for s in report["sessions"]] == [True, True]
    assert report["sessions"][1]["recording"] == "b.pbstream trajectory 0"
    metres, degrees = _relative_error(out, reference)
    assert metres < 0.1 and degrees < 1.0


def test_what_a_maps_cleaning_removed_stays_removed_in_the_merge(merge_parts):
    """A cell part 1's cleaning drew free (here: where one of its first node's returns ended) is carried into the
    merged frame by that node's move and drawn free there too, though the part's submaps still hold it."""
    from carto_cli.mapping.cleaning import FREE, Transients
    from carto_cli.pipeline import merge_maps

    (a, b), _ = merge_parts
    first, second = load_map(a / "map.carto"), load_map(b / "map.carto")
    point = np.asarray(second.node_points[0][0], np.float64)
    where = transform.apply(second.node_global_poses[0], point[None, :])[0]
    res = second.submaps[0].grid.resolution
    centre = (np.floor(where / res) + 0.5) * res
    removed = Transients.of_centres(res, centre[None, :], np.array([[second.node_times[0], second.node_times[0]]]),
                                    np.array([5]), np.array([20]))
    result = merge_maps([first, dataclasses.replace(second, transients=removed)], jobs=1)
    assert result.transients is not None and len(result.transients) == 1
    # The part's node 0 is node first.num_nodes of the merged graph: the cell moved with it
    node = result.graph.global_poses[first.num_nodes]
    local = transform.apply(transform.inverse(second.node_global_poses[0]), centre[None, :])
    expected = transform.apply(node, local)[0]
    assert np.linalg.norm(result.transients.centres()[0] - expected) <= res
    ix, iy = result.transients.cells_on(result.image.origin, result.image.resolution, result.image.shape)[0]
    assert result.image.probability[iy, ix] <= FREE
    # Without it, the merged map draws the wall the submaps hold there
    plain = merge_maps([first, second], jobs=1)
    assert plain.transients is None
    at = np.floor((expected - np.asarray(plain.image.origin)) / plain.image.resolution).astype(int)
    assert np.nanmax(plain.image.probability[at[1] - 1:at[1] + 2, at[0] - 1:at[0] + 2]) > 0.5
