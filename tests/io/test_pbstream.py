"""carto_cli.io.pbstream: Cartographer's saved state, read and written."""
import gzip
import re
import struct

import numpy as np
import pytest
from support import SAMPLE_BAG

from carto_cli.core.errors import FormatError
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.io import pbstream
from carto_cli.io.map_file import load_map
from carto_cli.pipeline import MapRequest

# The messages carto reads and writes, as Cartographer's published .proto files declare them (cartographer/
# mapping/proto/{serialization,pose_graph,trajectory,submap,grid_2d,map_limits,cell_limits_2d,
# trajectory_node_data,trajectory_builder_options}.proto, transform/proto/transform.proto,
# sensor/proto/sensor.proto), nested messages given the flat names carto's schema uses. Transcribed by hand: the
# reference the schema is checked against, field by field.
PUBLISHED = """
message Vector2d { double x = 1; double y = 2; }
message Vector3d { double x = 1; double y = 2; double z = 3; }
message Quaterniond { double x = 1; double y = 2; double z = 3; double w = 4; }
message Rigid3d { Vector3d translation = 1; Quaterniond rotation = 2; }
message SubmapId { int32 trajectory_id = 1; int32 submap_index = 2; }
message NodeId { int32 trajectory_id = 1; int32 node_index = 2; }
message Constraint { SubmapId submap_id = 1; NodeId node_id = 2; Rigid3d relative_pose = 3;
  double translation_weight = 6; double rotation_weight = 7; Tag tag = 5; }
message TrajectoryNode { int32 node_index = 7; int64 timestamp = 1; Rigid3d pose = 5; }
message TrajectorySubmap { int32 submap_index = 2; Rigid3d pose = 1; }
message Trajectory { int32 trajectory_id = 3; repeated TrajectoryNode node = 1; repeated TrajectorySubmap submap = 2; }
message PoseGraph { repeated Constraint constraint = 2; repeated Trajectory trajectory = 4;
  repeated LandmarkPose landmark_poses = 5; }
message CellLimits { int32 num_x_cells = 1; int32 num_y_cells = 2; }
message MapLimits { double resolution = 1; Vector2d max = 2; CellLimits cell_limits = 3; }
message CellBox { int32 max_x = 1; int32 max_y = 2; int32 min_x = 3; int32 min_y = 4; }
message ProbabilityGrid { }
message Grid2D { MapLimits limits = 1; repeated int32 cells = 2; CellBox known_cells_box = 3;
  ProbabilityGrid probability_grid_2d = 4; TSDF2D tsdf_2d = 5; float min_correspondence_cost = 6;
  float max_correspondence_cost = 7; }
message Submap2D { Rigid3d local_pose = 1; int32 num_range_data = 2; bool finished = 3; Grid2D grid = 4; }
message Submap { SubmapId submap_id = 1; Submap2D submap_2d = 2; Submap3D submap_3d = 3; }
message CompressedPointCloud { int32 num_points = 1; repeated int32 point_data = 3; }
message TrajectoryNodeData { int64 timestamp = 1; Quaterniond gravity_alignment = 2;
  CompressedPointCloud filtered_gravity_aligned_point_cloud = 3; CompressedPointCloud high_resolution_point_cloud = 4;
  CompressedPointCloud low_resolution_point_cloud = 5; repeated float rotational_scan_matcher_histogram = 6;
  Rigid3d local_pose = 7; }
message Node { NodeId node_id = 1; TrajectoryNodeData node_data = 5; }
message TrajectoryData { int32 trajectory_id = 1; double gravity_constant = 2; Quaterniond imu_calibration = 3;
  Rigid3d fixed_frame_origin_in_map = 4; }
message SensorId { SensorType type = 1; string id = 2; }
message TrajectoryBuilderOptions { }
message TrajectoryBuilderOptionsWithSensorIds { repeated SensorId sensor_id = 1;
  TrajectoryBuilderOptions trajectory_builder_options = 2; }
message AllTrajectoryBuilderOptions { repeated TrajectoryBuilderOptionsWithSensorIds options_with_sensor_ids = 1; }
message SerializationHeader { uint32 format_version = 1; }
message SerializedData { PoseGraph pose_graph = 1; AllTrajectoryBuilderOptions all_trajectory_builder_options = 2;
  Submap submap = 3; Node node = 4; TrajectoryData trajectory_data = 5; ImuData imu_data = 6;
  OdometryData odometry_data = 7; FixedFramePoseData fixed_frame_pose_data = 8; LandmarkData landmark_data = 9; }
"""
ENUMS = {"Tag", "SensorType"}  # varints on the wire, as int32
SCALARS = {"double": "d", "float": "f", "int32": "i", "int64": "l", "uint32": "u", "bool": "b", "string": "s"}


def published_layout() -> dict[str, dict[str, tuple[int, str, str]]]:
    layout = {}
    for name, body in re.findall(r"message (\w+) \{([^}]*)\}", PUBLISHED):
        fields = {}
        for repeated, tp, fname, number in re.findall(r"(repeated )?(\w+) (\w+) = (\d+);", body):
            kind = SCALARS.get(tp, "i" if tp in ENUMS else "m")
            fields[fname] = (int(number), kind, "r" if repeated else "")
        layout[name] = fields
    return layout


def test_the_schema_is_cartographers_layout():
    """Every field carto declares has the number, wire type and label Cartographer's .proto files give it."""
    layout = published_layout()
    for message, fields in pbstream.SCHEMA.items():
        assert message in layout, message
        for fname, number, kind, label, _ in fields:
            if fname in ("tsdf_2d", "submap_3d"):  # declared as empty messages: carto only tests their presence
                assert layout[message][fname][:2] == (number, "m")
                continue
            assert layout[message].get(fname) == (number, kind, label), (message, fname)


def decode_reference(num_points, data):
    """Cartographer's CompressedPointCloud iterator, point by point (the reference for the vectorised decoder)."""
    out, it, left_in_block, block = [], iter(data), 0, (0, 0, 0)
    for _ in range(num_points):
        if left_in_block == 0:
            left_in_block = next(it)
            block = tuple(next(it) * 1024 for _ in range(3))
        left_in_block -= 1
        p = next(it)
        out.append(((block[0] + (p & 1023)) * 0.001, (block[1] + ((p >> 10) & 1023)) * 0.001,
                    (block[2] + (p >> 20)) * 0.001))
    return np.array(out)


def test_compressed_point_clouds_match_cartographers_decoding():
    rng = np.random.default_rng(3)
    points = np.concatenate([rng.uniform(-30, 30, (400, 2)), [[0.0, 0.0], [-0.0005, 0.0005], [1.024, -1.024]]])
    n, data = pbstream.compress_points(points)
    ref = decode_reference(n, data.tolist())
    assert n == len(points) and np.all(ref[:, 2] == 0)
    ours = pbstream.decompress_points(n, data)
    np.testing.assert_allclose(ours, ref[:, :2], atol=1e-12)
    # Every point within half a millimetre of one decoded (the format's precision); order is by block.
    d = np.linalg.norm(points[:, None] - ours[None], axis=2).min(axis=1)
    assert d.max() <= 0.0005 * np.sqrt(2) + 1e-9


def test_grid_axes_follow_cartographers_map_limits():
    """A wall cell at a known world position lands on the cell Cartographer's MapLimits::GetCellIndex gives."""
    M = pbstream.messages()
    grid = ProbabilityGrid(0.05, (1.0, -2.0), (40, 30))  # 2 m x 1.5 m from (1, -2)
    wall = np.array([1.62, -1.13])
    cell = grid.cell_index(wall[None])[0]
    grid.set_probability(cell[None], [0.9])
    msg = M["Grid2D"]()
    pbstream.grid_to_message(msg, grid)
    mx, my = msg.limits.max.x, msg.limits.max.y
    cx = int(np.floor((my - wall[1]) / 0.05))  # RoundToInt(v - 0.5) is floor(v) away from cell edges
    cy = int(np.floor((mx - wall[0]) / 0.05))
    nxc = msg.limits.cell_limits.num_x_cells
    cells = np.asarray(msg.cells)
    assert np.flatnonzero(cells).tolist() == [nxc * cy + cx]
    box = msg.known_cells_box
    assert (box.min_x, box.max_x, box.min_y, box.max_y) == (cx, cx, cy, cy)
    back = pbstream.grid_from_message(msg, "test")
    np.testing.assert_array_equal(back.cells, grid.cells)
    np.testing.assert_allclose(back.origin, grid.origin)
    np.testing.assert_array_equal(back.known_box, grid.known_box)


@pytest.fixture(scope="module")
def sample_map(tmp_path_factory):
    from carto_cli.commands.map import run_map
    from carto_cli.options import load_options

    out = tmp_path_factory.mktemp("pb") / "map"
    run_map(MapRequest(SAMPLE_BAG, load_options("office")), out)
    return load_map(out / "map.carto")


def same_points(a, b):
    assert len(a) == len(b)
    if len(a):
        assert np.linalg.norm(a[:, None] - b[None], axis=2).min(axis=1).max() <= 0.0008


def test_a_carto_map_written_and_read_back(tmp_path, sample_map):
    """map.carto -> .pbstream -> the same graph: grids and poses exact, times to Cartographer's 100 ns, points
    to its 1 mm; written twice, the same bytes."""
    a = sample_map
    path = pbstream.save_pbstream(tmp_path / "map.pbstream", a)
    assert path.read_bytes()[:8] == struct.pack("<Q", 0x7B1D1F7B5BF501DB)
    assert pbstream.save_pbstream(tmp_path / "again.pbstream", a).read_bytes() == path.read_bytes()
    b = load_map(path)
    assert (b.num_nodes, b.num_submaps, len(b.constraints)) == (a.num_nodes, a.num_submaps, len(a.constraints))
    for x, y in zip(a.submaps, b.submaps):
        np.testing.assert_array_equal(x.grid.cells, y.grid.cells)
        np.testing.assert_array_equal(x.grid.known_box, y.grid.known_box)
        np.testing.assert_allclose(x.grid.origin, y.grid.origin, atol=1e-9)
        assert (x.finished, x.num_range_data) == (y.finished, y.num_range_data)
    for name in ("node_global_poses", "node_local_poses", "submap_global_poses"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-12)
    np.testing.assert_allclose(a.node_times, b.node_times, atol=1e-7)
    np.testing.assert_array_equal(a.constraints.submap, b.constraints.submap)
    np.testing.assert_array_equal(a.constraints.node, b.constraints.node)
    np.testing.assert_array_equal(a.constraints.is_loop_closure, b.constraints.is_loop_closure)
    np.testing.assert_allclose(a.constraints.relative, b.constraints.relative, atol=1e-12)
    assert all(np.array_equal(x, y) for x, y in zip(a.submap_nodes, b.submap_nodes))
    for p, q in zip(a.node_points, b.node_points):
        same_points(np.asarray(p, float), q)
    # Once more through Cartographer's format: points (on the millimetre grid now) and times come back exactly,
    # poses to the last bit or two of a yaw through a quaternion.
    c = load_map(pbstream.save_pbstream(tmp_path / "twice.pbstream", b))
    assert all(np.array_equal(p, q) for p, q in zip(b.node_points, c.node_points))
    np.testing.assert_array_equal(b.node_times, c.node_times)
    np.testing.assert_allclose(b.node_global_poses, c.node_global_poses, rtol=0, atol=1e-14)


def test_the_stream_is_cartographers(tmp_path, sample_map):
    """Read with the protobuf library alone, as Cartographer's ProtoStreamDeserializer does: header (version
    2), pose graph, trajectory builder options (one per trajectory), submaps, nodes, trajectory data."""
    M = pbstream.messages()
    data = pbstream.save_pbstream(tmp_path / "m.pbstream", sample_map).read_bytes()
    pos, kinds = 8, []
    while pos < len(data):
        (size,) = struct.unpack("<Q", data[pos:pos + 8])
        raw = gzip.decompress(data[pos + 8:pos + 8 + size])
        pos += 8 + size
        if not kinds:
            assert M["SerializationHeader"].FromString(raw).format_version == 2
            kinds.append("header")
            continue
        msg = M["SerializedData"].FromString(raw)
        kinds.append(next(f.name for f, _ in msg.ListFields()))
    assert kinds[:3] == ["header", "pose_graph", "all_trajectory_builder_options"]
    body = kinds[3:]
    assert body == ["submap"] * sample_map.num_submaps + ["node"] * sample_map.num_nodes + ["trajectory_data"]


def test_a_hand_built_cartographer_state_is_read(tmp_path):
    """A state built message by message (one trajectory, one submap, two nodes, one constraint each) loads with
    its poses, grid and times; a 3D map and an older format are refused by name."""
    M = pbstream.messages()
    out = bytearray(pbstream.MAGIC_BYTES)

    def put(msg):
        blob = gzip.compress(msg.SerializeToString())
        out.extend(struct.pack("<Q", len(blob)) + blob)

    put(M["SerializationHeader"](format_version=2))
    d = M["SerializedData"]()
    tr = d.pose_graph.trajectory.add(trajectory_id=0)
    for i, x in enumerate((0.0, 1.0)):
        n = tr.node.add(node_index=i, timestamp=pbstream.to_ticks(100.0 + i))
        n.pose.translation.x, n.pose.rotation.w = x + 5.0, 1.0
        c = d.pose_graph.constraint.add(tag=0, translation_weight=1.0, rotation_weight=2.0)
        c.node_id.node_index = i
        c.relative_pose.translation.x, c.relative_pose.rotation.w = x, 1.0
    s = tr.submap.add(submap_index=0)
    s.pose.translation.x, s.pose.rotation.w = 5.0, 1.0
    put(d)
    d = M["SerializedData"]()
    d.all_trajectory_builder_options.options_with_sensor_ids.add()
    put(d)
    d = M["SerializedData"]()
    g = d.submap.submap_2d.grid
    g.limits.resolution, g.limits.max.x, g.limits.max.y = 0.1, 1.0, 1.0
    g.limits.cell_limits.num_x_cells, g.limits.cell_limits.num_y_cells = 3, 2  # 3 cells along y, 2 along x
    g.cells.extend([0, 0, 0, 0, 1000, 0])
    d.submap.submap_2d.finished = True
    d.submap.submap_2d.local_pose.rotation.w = 1.0
    put(d)
    for i in range(2):
        d = M["SerializedData"]()
        d.node.node_id.node_index = i
        d.node.node_data.timestamp = pbstream.to_ticks(100.0 + i)
        d.node.node_data.local_pose.translation.x, d.node.node_data.local_pose.rotation.w = float(i), 1.0
        put(d)
    path = tmp_path / "hand.pbstream"
    path.write_bytes(bytes(out))
    m = load_map(path)
    assert m.num_nodes == 2 and m.num_submaps == 1
    np.testing.assert_allclose(m.node_times, [100.0, 101.0])
    np.testing.assert_allclose(m.node_global_poses[:, 0], [5.0, 6.0])
    np.testing.assert_allclose(m.submap_global_poses[0], [5.0, 0.0, 0.0])
    grid = m.submaps[0].grid
    assert grid.num_cells == (2, 3) and np.count_nonzero(grid.cells) == 1
    # Cartographer's flat index 4 is cell (cx, cy) = (1, 1), centred at max - (cy + 0.5, cx + 0.5) * 0.1.
    ix, iy = grid.cell_index(np.array([[0.85, 0.85]]))[0]
    assert grid.cells[iy, ix] == 1000
    assert m.submap_nodes[0].tolist() == [0, 1]

    def stream(*messages):
        out = bytearray(pbstream.MAGIC_BYTES)
        for msg in messages:
            blob = gzip.compress(msg.SerializeToString())
            out.extend(struct.pack("<Q", len(blob)) + blob)
        return bytes(out)

    old = tmp_path / "old.pbstream"
    old.write_bytes(stream(M["SerializationHeader"](format_version=9)))
    with pytest.raises(FormatError, match="format version 9") as info:
        load_map(old)
    assert str(old) in str(info.value)
    d = M["SerializedData"]()
    d.submap.submap_3d.SetInParent()
    three_d = tmp_path / "3d.pbstream"
    three_d.write_bytes(stream(M["SerializationHeader"](format_version=2), d))
    with pytest.raises(FormatError, match="a 3D map"):
        load_map(three_d)


def test_damaged_streams_are_one_format_error(tmp_path, sample_map):
    data = pbstream.save_pbstream(tmp_path / "m.pbstream", sample_map).read_bytes()
    for i, blob in enumerate([data[:len(data) // 2], data[:12], data[:8] + b"\xff" * 40,
                              data[:200] + bytes(64) + data[264:]]):
        p = tmp_path / f"bad{i}.pbstream"
        p.write_bytes(blob)
        with pytest.raises(FormatError) as info:
            load_map(p)
        assert str(p) in str(info.value)


def test_a_node_is_placed_by_its_gravity_aligned_frame():
    """Cartographer's 2D graph relates a node by local_pose * gravity_alignment^-1 (its points' frame): a node
    whose IMU alignment holds a turn of 0.3 rad about z is read 0.3 rad less turned than its tracking frame."""
    M = pbstream.messages()
    pose = M["Rigid3d"]()
    pose.translation.x, pose.rotation.z, pose.rotation.w = 2.0, np.sin(0.5), np.cos(0.5)  # yaw 1.0
    gravity = M["Quaterniond"](z=np.sin(0.15), w=np.cos(0.15))  # yaw 0.3
    tilt = M["Quaterniond"](x=np.sin(0.05), w=np.cos(0.05))  # a roll only: no yaw to take away
    np.testing.assert_allclose(pbstream.pose_of(pose), [2.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(pbstream.pose_of(pose, gravity), [2.0, 0.0, 0.7], atol=1e-12)
    np.testing.assert_allclose(pbstream.pose_of(pose, tilt)[2], 1.0, atol=1e-3)
