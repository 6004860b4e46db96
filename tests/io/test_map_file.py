"""The map file: exact round trip of a real (simulated) map, and FormatError for every kind of damage."""
import hashlib
import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from carto_cli import __version__
from carto_cli.core.errors import CartoError, FormatError
from carto_cli.io.container import decode
from carto_cli.io.loaded_map import LoadedMap
from carto_cli.io.map_file import FORMAT_VERSION, MAGIC, MAP_FORMAT, load_map, save_map
from carto_cli.io.trajectory import Trajectory
from carto_cli.mapping.constraints import ConstraintKind
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options, apply_overrides, load_options

DATA = Path(__file__).parent / "data"

# Small submaps so a 40 s loop gives several finished submaps and loop closures in a few seconds.
OVERRIDES = ["pose_graph.optimize_every_n_nodes=0", "trajectory_builder_2d.submaps.num_range_data=10"]


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    from carto_cli.pipeline import build
    from carto_cli.sim.recording import simulate
    from carto_cli.sim.trajectory import loop_trajectory
    from carto_cli.sim.world import loop_building

    world = loop_building()
    recording = simulate(world, loop_trajectory(world), duration=40.0).recording()
    options = load_options(None, OVERRIDES)
    result = build(recording, options)
    path = save_map(tmp_path_factory.mktemp("map") / "map.carto", result, options, recordings=["sim.bag"])
    return result, options, path


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    """A hand-built graph: quick to save, for damage tests that load the file hundreds of times."""
    graph = _hand_graph()
    path = save_map(tmp_path_factory.mktemp("small") / "small.carto", graph, Options(),
                    trajectory=(np.arange(3.0), np.zeros((3, 3))))
    return graph, path.read_bytes()


def _hand_graph() -> PoseGraph:
    options = Options()
    graph = PoseGraph(options, loop_closure=False)
    a = Submap((0.0, 0.0), index=0, initial_size=20)
    a.grid.set_probability([[3, 4], [5, 6], [10, 2]], [0.9, 0.2, 0.6])
    a.num_range_data = 2
    a.finish()
    b = Submap((1.0, 0.5), index=1, initial_size=20)  # never observed: empty known box
    rng = np.random.default_rng(3)
    graph.add_node(1.0, (0.0, 0.0, 0.0), rng.normal(size=(40, 2)), [a, b], odometry_pose=(0, 0, 0))
    graph.add_node(2.0, (0.3, 0.1, 0.2), np.zeros((0, 2)), [a, b])
    graph.add_node(3.0, (0.6, 0.1, 0.3), rng.normal(size=(7, 2)), [b], trajectory=0)
    graph.constraints.add(1, 0, (0.1, 0.2, 0.3), 7.0, 8.0, ConstraintKind.INTER_SUBMAP)
    return graph


# ------------------------------------------------------------------------------------------- round trip


def assert_graph_state_equal(graph: PoseGraph, loaded: LoadedMap):
    assert np.array_equal(loaded.node_times, np.asarray(graph.node_times))
    assert np.array_equal(loaded.node_trajectories, np.asarray(graph.node_trajectory))
    assert np.array_equal(loaded.node_local_poses, graph.local_poses)
    assert np.array_equal(loaded.node_global_poses, graph.global_poses)
    assert np.array_equal(loaded.node_odometry, graph.node_odometry(), equal_nan=True)
    assert len(loaded.node_points) == graph.num_nodes
    for a, b in zip(loaded.node_points, graph.node_points):
        assert a.dtype == b.dtype and np.array_equal(a, b)

    assert loaded.num_submaps == len(graph.submaps)
    for i, entry in enumerate(graph.submaps):
        got, want = loaded.submaps[i], entry.submap
        assert got.index == want.index and got.finished == want.finished
        assert got.num_range_data == want.num_range_data
        assert np.array_equal(got.local_pose, want.local_pose)
        assert got.grid.resolution == want.grid.resolution
        assert np.array_equal(got.grid.origin, want.grid.origin)
        assert np.array_equal(got.grid.known_box, want.grid.known_box)
        assert got.grid.cells.dtype == np.uint16 and got.grid.cells.shape == want.grid.cells.shape
        assert got.grid.cells.tobytes() == want.grid.cells.tobytes()
        assert got.grid.version == want.grid.version
        assert loaded.submap_trajectories[i] == entry.trajectory
        assert np.array_equal(loaded.submap_global_poses[i], entry.global_pose)
        assert loaded.submap_nodes[i].tolist() == entry.nodes

    got, want = loaded.constraints, graph.constraints
    assert len(got) == len(want)
    for column in ("submap", "node", "relative", "translation_weight", "rotation_weight", "is_loop_closure"):
        assert np.array_equal(getattr(got, column), getattr(want, column)), column


def test_round_trip_of_a_real_map_is_exact(mapped):
    result, options, path = mapped
    graph = result.graph
    assert len(graph.submaps) >= 4 and any(e.finished for e in graph.submaps)
    assert not all(e.finished for e in graph.submaps)
    assert graph.constraints.num_loop_closures > 0

    loaded = load_map(path)
    assert loaded.options == options
    assert loaded.ignored_options == ()
    assert_graph_state_equal(graph, loaded)
    assert np.array_equal(loaded.trajectory.t, result.times)
    assert np.array_equal(loaded.trajectory.poses, result.poses)
    assert np.array_equal(loaded.node_scans, result.node_scans)
    assert np.array_equal(loaded.laser_pose, result.laser_pose)
    meta = loaded.metadata
    assert meta.format_version == FORMAT_VERSION and meta.carto_version == __version__
    assert meta.recordings == ("sim.bag",)
    assert meta.created == ""  # no wall-clock time unless SOURCE_DATE_EPOCH says one
    assert meta.laser_pose_source == result.laser_pose_source
    assert meta.stats["nodes"] == graph.num_nodes


def test_grids_are_cropped_in_the_file(mapped):
    result, _, path = mapped
    full = sum(e.submap.grid.cells.nbytes for e in result.graph.submaps)
    points = sum(p.nbytes for p in result.graph.node_points)
    assert path.stat().st_size < (full + points) / 2


def test_to_pose_graph_restores_the_graph_and_mapping_can_continue(mapped):
    result, options, path = mapped
    loaded = load_map(path)
    graph = loaded.to_pose_graph()
    assert graph.options == options
    assert [(e.trajectory, e.submap.index) for e in graph.submaps] == \
        [(e.trajectory, e.submap.index) for e in result.graph.submaps]
    assert [e.searched for e in graph.submaps] == [e.finished for e in graph.submaps]
    assert_graph_state_equal(graph, loaded)
    # A graph saved from the restored graph loads to the same state.
    assert_graph_state_equal(graph, load_map(save_map(path.with_name("again.carto"), graph, options)))

    # The restored graph owns copies.
    graph.submaps[0].submap.grid.cells[:] = 7
    graph.global_poses[:] = 0
    assert_graph_state_equal(result.graph, loaded)

    # A new trajectory is added, searched against the old map and optimized with it.
    graph = loaded.to_pose_graph()
    t = loaded.next_trajectory_id
    assert t == 1
    n = graph.num_nodes
    node = loaded.node_local_poses[5]
    new = Submap(node[:2], index=0, resolution=options.trajectory_builder_2d.submaps.grid_options_2d.resolution)
    graph.add_node(loaded.node_times[-1] + 1, node, loaded.node_points[5], [new], trajectory=t)
    assert graph.num_nodes == n + 1 and graph.node_trajectory[-1] == t
    assert (graph.submaps[-1].trajectory, graph.submaps[-1].submap.index) == (t, 0)
    assert len(graph.submaps) == loaded.num_submaps + 1
    summary = graph.optimize(final=True)
    assert summary is not None
    assert np.allclose(graph.global_poses[:n], loaded.node_global_poses, atol=0.05)


def test_hand_built_graph_with_empty_submap_round_trips(tmp_path):
    graph = _hand_graph()
    # A known cell outside the known box must not be lost to cropping.
    graph.submaps[1].submap.grid.cells[0, 0] = 123
    traj = Trajectory.from_poses([1.0, 2.0], [[0, 0, 0], [1, 2, 3]])
    path = save_map(tmp_path / "m.carto", graph, apply_overrides(Options(), {"pose_graph.optimize_every_n_nodes": 3}),
                    trajectory=traj, recordings=[tmp_path / "a.bag", "b.mcap"])
    loaded = load_map(path)
    assert_graph_state_equal(graph, loaded)
    assert loaded.options.pose_graph.optimize_every_n_nodes == 3
    assert loaded.metadata.recordings == (str(tmp_path / "a.bag"), "b.mcap")
    assert np.array_equal(loaded.trajectory.poses, traj.poses)
    assert loaded.node_scans is None and loaded.laser_pose is None
    assert loaded.to_pose_graph().builder.connected == set()


def test_a_map_written_by_format_version_1_still_loads():
    """tests/io/data/hand_graph_v1.carto: ``_hand_graph()`` saved by the version-1 writer of commit 64a97d6
    (with ``trajectory=(arange(3), zeros((3, 3)))`` and ``recordings=["hand.bag"]``)."""
    loaded = load_map(DATA / "hand_graph_v1.carto")
    assert_graph_state_equal(_hand_graph(), loaded)
    meta = loaded.metadata
    assert meta.format_version == 1 and meta.carto_version == "0.1.0"
    assert meta.created == "2024-01-01T00:00:00Z" and meta.recordings == ("hand.bag",)
    assert np.array_equal(loaded.trajectory.t, np.arange(3.0))
    assert loaded.to_pose_graph().num_nodes == 3


def test_the_writer_still_writes_format_version_1(tmp_path):
    """The same graph saved today gives the version-1 file's arrays, codecs and header, byte for byte
    (all but the creation time, the carto version and the options, which may grow, and the compressed arrays'
    lengths and offsets, which follow the compression level: 9 then, 3 since)."""
    path = save_map(tmp_path / "again.carto", _hand_graph(), Options(),
                    trajectory=(np.arange(3.0), np.zeros((3, 3))), recordings=["hand.bag"])
    old_header, old_arrays = decode((DATA / "hand_graph_v1.carto").read_bytes(), path, MAP_FORMAT)
    new_header, new_arrays = decode(path.read_bytes(), path, MAP_FORMAT)
    for header in (old_header, new_header):
        for key in ("created", "carto_version", "options", "data_length"):
            header.pop(key, None)
        for spec in header["arrays"].values():
            del spec["offset"], spec["length"]
    assert json.dumps(new_header) == json.dumps(old_header)  # key order too
    assert list(new_arrays) == list(old_arrays)
    for name, array in old_arrays.items():
        assert new_arrays[name].dtype == array.dtype and new_arrays[name].tobytes() == array.tobytes(), name


def test_graph_without_trajectory_or_nodes(tmp_path):
    graph = PoseGraph(Options())
    loaded = load_map(save_map(tmp_path / "empty.carto", graph, Options()))
    assert loaded.num_nodes == 0 and loaded.num_submaps == 0 and len(loaded.constraints) == 0
    assert loaded.trajectory is None and loaded.next_trajectory_id == 0
    assert loaded.to_pose_graph().num_nodes == 0


def test_save_is_atomic(tmp_path):
    path = tmp_path / "map.carto"
    path.write_bytes(b"old")
    with pytest.raises(TypeError):
        save_map(path, object(), Options())
    assert path.read_bytes() == b"old"
    save_map(path, _hand_graph(), Options())
    assert [p.name for p in tmp_path.iterdir()] == ["map.carto"]


# ------------------------------------------------------------------------------------------- damage


def expect_format_error(tmp_path, data: bytes, match: str):
    p = tmp_path / "bad.carto"
    p.write_bytes(data)
    with pytest.raises(FormatError, match=match) as info:
        load_map(p)
    assert info.value.path == str(p)
    return info.value


def test_not_a_map(tmp_path):
    expect_format_error(tmp_path, b"", "empty file")
    expect_format_error(tmp_path, b"P5\n10 10\n255\n" + bytes(100), "not a carto map file")
    expect_format_error(tmp_path, b"CART", "truncated")


def test_missing_file(tmp_path):
    with pytest.raises(CartoError, match="no such map file"):
        load_map(tmp_path / "nope.carto")


def test_wrong_version(tmp_path, small_map):
    _, data = small_map
    bad = bytearray(data)
    struct.pack_into("<I", bad, 8, FORMAT_VERSION + 1)
    expect_format_error(tmp_path, bytes(bad),
                        f"map file version {FORMAT_VERSION + 1}, this carto reads {FORMAT_VERSION}")


def test_flipped_byte_in_the_middle(tmp_path, mapped):
    data = mapped[2].read_bytes()
    bad = bytearray(data)
    bad[len(bad) // 2] ^= 0x10
    expect_format_error(tmp_path, bytes(bad), "corrupt: checksum mismatch")


@pytest.mark.parametrize("keep", [10, 27, 100, -1, -33])
def test_truncated(tmp_path, small_map, keep):
    _, data = small_map
    expect_format_error(tmp_path, data[:keep], "truncated")


def test_trailing_bytes_and_damaged_preamble(tmp_path, small_map):
    _, data = small_map
    expect_format_error(tmp_path, data + b"\0", "unexpected bytes")
    bad = bytearray(data)
    bad[17] ^= 1  # inside the file length
    expect_format_error(tmp_path, bytes(bad), "preamble")


def _forge(data: bytes, edit) -> bytes:
    """Re-encode a map file with ``edit(header)`` applied and valid checksums: damage a checksum can't see."""
    _, _, hlen, _ = struct.unpack_from("<8sIIQ", data, 0)
    header = json.loads(data[28:28 + hlen])
    payload = data[28 + hlen:-32]
    edited = edit(header)
    hb = edited if isinstance(edited, bytes) else json.dumps(header).encode()
    pre = struct.pack("<8sIIQ", MAGIC, FORMAT_VERSION, len(hb), 28 + len(hb) + len(payload) + 32)
    body = pre + struct.pack("<I", zlib.crc32(pre)) + hb + payload
    return body + hashlib.sha256(body).digest()


def test_forge_helper_is_faithful(tmp_path, small_map):
    graph, data = small_map
    p = tmp_path / "same.carto"
    p.write_bytes(_forge(data, lambda h: None))
    assert_graph_state_equal(graph, load_map(p))


@pytest.mark.parametrize("edit, match", [
    (lambda h: b"{not json", "malformed header"),
    (lambda h: b"\xff\xfe", "malformed header"),
    (lambda h: b"[]", "malformed header"),
    (lambda h: h["arrays"]["node_time"].update(dtype="|O8"), "not allowed"),
    (lambda h: h["arrays"]["node_time"].update(dtype="<U4"), "not allowed"),
    (lambda h: h["arrays"]["node_time"].update(offset=10**9), "past the data"),
    (lambda h: h["arrays"]["node_time"].update(shape=[4]), "bytes for shape"),
    (lambda h: h["arrays"]["node_time"].update(shape=[-3]), "bad shape"),
    (lambda h: h["arrays"]["submap_cells"].update(raw_length=h["arrays"]["submap_cells"]["raw_length"] + 2,
                                                   shape=[h["arrays"]["submap_cells"]["shape"][0] + 1]),
     "stored length"),
    (lambda h: h["arrays"]["node_time"].update(codec="lzma"), "unknown codec"),
    (lambda h: h["arrays"].pop("constraint_node"), "missing"),
    (lambda h: h["arrays"].__setitem__("node_trajectory", h["arrays"]["node_time"]), "dtype"),
    (lambda h: h["arrays"].__setitem__("submap_index", h["arrays"]["submap_trajectory"]), "same trajectory and index"),
    (lambda h: h["arrays"].__setitem__("constraint_node", h["arrays"]["constraint_submap"]) or
     h["arrays"].__setitem__("constraint_submap", h["arrays"]["submap_index"]), "rows|out of range"),
    (lambda h: h.update(data_length=1), "data length"),
    (lambda h: h.update(format_version=7), "format version"),
    (lambda h: h.update(options=[1]), "no options"),
    (lambda h: h["options"]["pose_graph"].update(optimize_every_n_nodes=-1), "optimize_every_n_nodes"),
    (lambda h: h["options"].update(pose_graph=3), "not a section"),
    (lambda h: h.update(recordings="x"), "recordings"),
])
def test_malformed_header_behind_a_valid_checksum(tmp_path, small_map, edit, match):
    _, data = small_map
    expect_format_error(tmp_path, _forge(data, edit), match)


def test_compressed_array_of_the_wrong_size(tmp_path, mapped):
    data = mapped[2].read_bytes()
    codecs = {}

    def edit(h):
        for name, spec in h["arrays"].items():
            codecs[name] = spec["codec"]
        spec = h["arrays"]["submap_cells"]
        spec.update(raw_length=spec["raw_length"] + 2, shape=[spec["shape"][0] + 1])

    expect_format_error(tmp_path, _forge(data, edit), "declared size")
    assert codecs["submap_cells"] == "zstd"
    assert "shuffle+zstd" in codecs.values()


def test_unknown_options_from_another_version_are_ignored(tmp_path, small_map):
    _, data = small_map

    def edit(h):
        h["options"]["pose_graph"]["some_future_option"] = 1
        h["options"]["new_section"] = {"x": 2}
        del h["options"]["trajectory_builder_2d"]["min_range"]  # a missing key takes its default

    p = tmp_path / "future.carto"
    p.write_bytes(_forge(data, edit))
    loaded = load_map(p)
    assert loaded.ignored_options == ("pose_graph.some_future_option", "new_section")
    assert loaded.options == Options()


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(0, 2**31), flips=st.lists(st.tuples(st.integers(0, 2**31), st.integers(1, 255)),
                                                 max_size=6),
       insert=st.binary(max_size=8), mode=st.sampled_from(["truncate", "flip", "insert", "all"]))
def test_random_damage_gives_only_format_errors(tmp_path, small_map, cut, flips, insert, mode):
    _, data = small_map
    bad = bytearray(data)
    if mode in ("flip", "all"):
        for pos, xor in flips:
            bad[pos % len(bad)] ^= xor
    if mode in ("insert", "all") and insert:
        pos = cut % len(bad)
        bad[pos:pos] = insert
    if mode in ("truncate", "all"):
        bad = bad[: cut % len(data)]
    if bytes(bad) == data:
        return
    p = tmp_path / "damaged.carto"
    p.write_bytes(bytes(bad))
    with pytest.raises(FormatError) as info:
        load_map(p)
    assert info.value.path == str(p)


def test_source_date_epoch_stamps_the_map_and_nothing_else_does(mapped, tmp_path, monkeypatch):
    result, options, path = mapped
    again = save_map(tmp_path / "again.carto", result, options, recordings=["sim.bag"])
    assert again.read_bytes() == path.read_bytes()  # the same map, the same bytes
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1704067200")
    stamped = save_map(tmp_path / "stamped.carto", result, options, recordings=["sim.bag"])
    assert load_map(stamped).metadata.created == "2024-01-01T00:00:00Z"


def test_the_bytes_do_not_depend_on_the_threads_that_compress_them(tmp_path, mapped):
    result, options, _ = mapped
    one = save_map(tmp_path / "one.carto", result, options, jobs=1).read_bytes()
    three = save_map(tmp_path / "three.carto", result, options, jobs=3).read_bytes()
    assert one == three
    _, _, header_length, _ = struct.unpack("<8sIIQ", one[:24])
    header = json.loads(one[28:28 + header_length])  # after the preamble and its CRC-32
    codecs = {entry["codec"] for entry in header["arrays"].values()}
    assert {"zstd", "shuffle+zstd"} <= codecs  # several arrays compressed at once, each kept at its smallest
