"""No recording, map or configuration runs code (SECURITY.md): a crafted file for every reader tries to create a
canary file, through the commands that read it, and the canary must never appear.

Files that carry code where a name belongs (a message definition's field or constant name, a type name) are
refused with one line naming the file, the topic and the line, exit 2; the others are read as the data they are
(their code is a string, never run) or refused for what they are (a tag YAML must not build, a dtype not
allowed). Each builder writes its file by code into the test's directory.
"""
import gzip
import hashlib
import json
import pickle
import sqlite3
import struct
import zlib

import numpy as np
import pytest
from mcap.writer import Writer as McapWriter
from rosbags.typesys import Stores, get_typestore
from support import SAMPLE_BAG, laser_scan_idl
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.io import container, pbstream
from carto_cli.io.map_file import MAP_FORMAT

NOETIC = get_typestore(Stores.ROS1_NOETIC)
HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
LASER = "sensor_msgs/msg/LaserScan"


def code(canary):
    """A Python statement creating the canary: what a crafted file hopes some reader will run."""
    return f"__import__('os').system('touch {canary}')"


def laser(typestore, ns=10**9):
    T = typestore.types
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    header = (T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="laser") if typestore is NOETIC
              else T["std_msgs/msg/Header"](stamp=stamp, frame_id="laser"))
    return T[LASER](header=header, angle_min=-1.0, angle_max=1.0, angle_increment=0.1, time_increment=0.0,
                    scan_time=0.1, range_min=0.1, range_max=10.0, ranges=np.full(21, 2.0, dtype=np.float32),
                    intensities=np.empty(0, dtype=np.float32))


def ros1_definition():
    return NOETIC.generate_msgdef(LASER)[0]


def ros2_definition():
    return HUMBLE.generate_msgdef(LASER, ros_version=2)[0]


def string_constant(canary):
    """The line genpy copied into its source unchecked (a constant's name)."""
    return f"string __qualname__;{code(canary)};X=abc\n"


def int_constant(canary):
    return f"int32 __qualname__;{code(canary)};X=1\n"


def idl_definition(canary):
    """LaserScan as rosbag2 writes a ros2idl definition, with a statement where a member's name belongs."""
    return laser_scan_idl(f"      float x; {code(canary)};\n")


# --- recordings -----------------------------------------------------------------------------------------------

def standalone_mcap(path, schema_encoding, definition, schema_name=LASER):
    ros1 = schema_encoding == "ros1msg"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="ros1" if ros1 else "ros2", library="test")
        sid = w.register_schema(schema_name, schema_encoding, definition.encode())
        cid = w.register_channel("/scan", "ros1" if ros1 else "cdr", sid)
        for i in range(3):
            ns = 10**9 + i * 10**8
            data = (NOETIC.serialize_ros1(laser(NOETIC, ns), LASER) if ros1
                    else HUMBLE.serialize_cdr(laser(HUMBLE, ns), LASER))
            w.add_message(cid, log_time=ns, publish_time=ns, data=bytes(data))
        w.finish()
    return path


def ros1_bag(path, definition, msgtype=LASER):
    from rosbags.rosbag1 import Writer

    with Writer(path) as w:
        conn = w.add_connection("/scan", msgtype, msgdef=definition, md5sum="0" * 32)
        for i in range(3):
            w.write(conn, 10**9 + i * 10**8, NOETIC.serialize_ros1(laser(NOETIC, 10**9 + i * 10**8), LASER))
    return path


def ros2_bag(path, definition, storage, msgtype=LASER, idl=False):
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin) as w:
        conn = w.add_connection("/scan", msgtype, msgdef=definition, rihs01="RIHS01_" + "0" * 64)
        for i in range(3):
            w.write(conn, 10**9 + i * 10**8, HUMBLE.serialize_cdr(laser(HUMBLE, 10**9 + i * 10**8), LASER))
    if idl:
        (db,) = path.glob("*.db3")
        with sqlite3.connect(db) as con:
            con.execute("UPDATE message_definitions SET encoding = 'ros2idl'")
    return path


def carmen_log(path, canary):
    ranges = " ".join(["2.0"] * 180)
    lines = [f"# {code(canary)}", f"PARAM robot_{code(canary)} 1"]
    for i in range(5):
        t = 1.0 + 0.1 * i
        lines.append(f"ODOM {0.1 * i} 0 0 0 0 0 {t} host {t}")
        lines.append(f"FLASER 180 {ranges} {0.1 * i} 0 0 {0.1 * i} 0 0 {t} host {t}")
    lines.append(f"FLASER 180 {code(canary)} 0 0 0 0 0 0 2.0 host 2.0")
    path.write_text("\n".join(lines) + "\n")
    return path


# --- maps and configurations --------------------------------------------------------------------------------

def pickled_map(path, canary):
    """A map.carto whose array directory declares an object array holding a pickle that runs the payload."""
    class Payload:
        def __reduce__(self):
            import os

            return os.system, (f"touch {canary}",)

    data = bytearray(container.encode(MAP_FORMAT, {}, {"grid": np.zeros(4)}))
    (header_length,) = struct.unpack_from("<I", data, 12)
    header = json.loads(data[28:28 + header_length])  # after the 24-byte preamble and its CRC
    blob = pickle.dumps(np.array([Payload()], dtype=object))
    header["arrays"]["grid"].update(dtype="|O", shape=[1], codec="none", offset=0, length=len(blob),
                                    raw_length=len(blob))
    header["data_length"] = len(blob)
    head = json.dumps(header).encode()
    total = 28 + len(head) + len(blob) + 32
    preamble = struct.pack("<8sIIQ", MAP_FORMAT.magic, MAP_FORMAT.version, len(head), total)
    body = preamble + struct.pack("<I", zlib.crc32(preamble)) + head + blob
    path.write_bytes(body + hashlib.sha256(body).digest())
    return path


def crafted_pbstream(path, canary):
    """A Cartographer state whose strings (sensor ids) hold the payload."""
    M = pbstream.messages()
    out = bytearray(pbstream.MAGIC_BYTES)
    header = M["SerializationHeader"](format_version=2)
    graph = M["SerializedData"]()
    graph.pose_graph.trajectory.add(trajectory_id=0)
    options = M["SerializedData"]()
    sensor = options.all_trajectory_builder_options.options_with_sensor_ids.add()
    sensor.sensor_id.add(id=code(canary))
    for msg in (header, graph, options):
        blob = gzip.compress(msg.SerializeToString())
        out.extend(struct.pack("<Q", len(blob)) + blob)
    path.write_bytes(bytes(out))
    return path


def map_server_yaml(path, canary):
    path.write_text(f'image: !!python/object/apply:os.system ["touch {canary}"]\nresolution: 0.05\n'
                    "origin: [0.0, 0.0, 0.0]\n")
    return path


def plain_map_server(directory):
    """A small map_server map (a walled room) to relocalize a crafted recording in."""
    import cv2

    pixels = np.full((60, 60), 254, np.uint8)
    pixels[[0, -1], :] = pixels[:, [0, -1]] = 0
    cv2.imwrite(str(directory / "room.pgm"), pixels)
    (directory / "room.yaml").write_text("image: room.pgm\nresolution: 0.05\norigin: [-1.5, -1.5, 0.0]\n")
    return directory / "room.yaml"


def profile_yaml(path, canary):
    path.write_text(f'trajectory_builder_2d:\n  min_range: !!python/object/apply:os.system ["touch {canary}"]\n')
    return path


def lua_config(path, canary):
    path.write_text(f'include "map_builder.lua"\nos.execute("touch {canary}")\nreturn {{}}\n')
    return path


# --- the corpus ------------------------------------------------------------------------------------------------

def recording_commands(rec, tmp_path):
    """Every command that reads a recording: info, map, convert (to ROS1, and to ROS2: rosbags' own converter
    for a ROS1 bag), relocalize --track."""
    room = plain_map_server(tmp_path)
    return [["info", rec], ["map", rec, "--no-loop-closure", "-o", tmp_path / "out_map"],
            ["convert", rec, tmp_path / "out.bag"], ["convert", rec, tmp_path / "out_ros2"],
            ["relocalize", room, rec, "--track", "--initial-pose", "0,0,0", "-o", tmp_path / "out_track"]]


# name -> build(directory, canary): a recording carrying code where a definition has a name.
CASES = {
    "mcap-ros1msg-string-constant": lambda d, c: standalone_mcap(
        d / "s.mcap", "ros1msg", string_constant(c) + ros1_definition(), "sensor_msgs/LaserScan"),
    "mcap-ros1msg-int-constant": lambda d, c: standalone_mcap(
        d / "i.mcap", "ros1msg", int_constant(c) + ros1_definition(), "sensor_msgs/LaserScan"),
    "mcap-ros2msg-string-constant": lambda d, c: standalone_mcap(
        d / "r2.mcap", "ros2msg", string_constant(c) + ros2_definition()),
    "mcap-ros2msg-field-name": lambda d, c: standalone_mcap(
        d / "f.mcap", "ros2msg", f"float32 x;{code(c)}\n" + ros2_definition()),
    "mcap-ros2idl-member-name": lambda d, c: standalone_mcap(d / "idl.mcap", "ros2idl", idl_definition(c)),
    "ros1-bag-constant": lambda d, c: ros1_bag(d / "c.bag", string_constant(c) + ros1_definition()),
    "ros1-bag-type-name": lambda d, c: ros1_bag(d / "t.bag", ros1_definition(), f"sensor_msgs/msg/X';{code(c)};'"),
    "ros2-sqlite3-constant": lambda d, c: ros2_bag(d / "db3", string_constant(c) + ros2_definition(), "sqlite3"),
    "ros2-sqlite3-idl": lambda d, c: ros2_bag(d / "idl_db3", idl_definition(c), "sqlite3", idl=True),
    "ros2-mcap-constant": lambda d, c: ros2_bag(d / "mcap_bag", string_constant(c) + ros2_definition(), "mcap"),
}


def run(args):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_line(result):
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.output
    assert lines[0].startswith("carto: error: ") and "Traceback" not in result.output
    return lines[0]


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_definition_carrying_code_is_refused_by_every_command(tmp_path, case):
    canary = tmp_path / "PWNED"
    rec = CASES[case](tmp_path, canary)
    for args in recording_commands(rec, tmp_path):
        result = run(args)
        assert not canary.exists(), (case, args[0])
        assert result.exit_code == 2, (case, args[0], result.output)
        line = one_line(result)
        assert rec.name in line and "topic /scan" in line, line
        if "type-name" not in case:
            assert "line " in line, line
        assert not any((tmp_path / out).exists() for out in ("out_map", "out.bag", "out_ros2", "out_track"))


def test_the_definition_error_names_the_line_it_found(tmp_path):
    rec = standalone_mcap(tmp_path / "s.mcap", "ros1msg", "# a comment\n" + string_constant(tmp_path / "C")
                          + ros1_definition(), "sensor_msgs/LaserScan")
    line = one_line(run(["info", rec]))
    assert f"{rec}: topic /scan: the message definition of 'sensor_msgs/LaserScan', line 2: " in line


def test_a_carmen_log_is_data(tmp_path):
    canary = tmp_path / "PWNED"
    log = carmen_log(tmp_path / "evil.log", canary)
    result = run(["info", log])
    assert not canary.exists()
    assert result.exit_code in (0, 2), result.output
    if result.exit_code:
        assert str(log.name) in one_line(result)


@pytest.mark.parametrize("build, command", [
    (pickled_map, lambda path, d: ["render", path, "-o", d / "out"]),
    (crafted_pbstream, lambda path, d: ["render", path, "-o", d / "out"]),
    (map_server_yaml, lambda path, d: ["relocalize", path, SAMPLE_BAG, "--initial-pose", "0,0,0"]),
    (profile_yaml, lambda path, d: ["map", SAMPLE_BAG, "--profile", path, "-o", d / "out"]),
    (profile_yaml, lambda path, d: ["profile", SAMPLE_BAG, "--profile", path]),
    (lua_config, lambda path, d: ["options", "import", path]),
    (lua_config, lambda path, d: ["map", SAMPLE_BAG, "--profile", path, "-o", d / "out"]),
], ids=["map.carto-pickle", "pbstream-strings", "map_server-yaml-tag", "profile-yaml-tag-map",
        "profile-yaml-tag-profile", "lua-os-execute-import", "lua-os-execute-profile"])
def test_maps_and_configurations_run_nothing(tmp_path, build, command):
    canary = tmp_path / "PWNED"
    suffix = {"pickled_map": ".carto", "crafted_pbstream": ".pbstream", "lua_config": ".lua"}.get(build.__name__,
                                                                                                  ".yaml")
    path = build(tmp_path / f"evil{suffix}", canary)
    result = run(command(path, tmp_path))
    assert not canary.exists()
    assert result.exit_code == 2, result.output
    assert path.name in one_line(result)


def test_a_set_value_is_never_built_as_an_object(tmp_path):
    canary = tmp_path / "PWNED"
    result = run(["map", SAMPLE_BAG, "-o", tmp_path / "out", "--set",
                  f'trajectory_builder_2d.min_range=!!python/object/apply:os.system ["touch {canary}"]'])
    assert not canary.exists()
    assert result.exit_code == 2, result.output
    one_line(result)


def test_a_ros2_metadata_yaml_tag_is_not_built(tmp_path):
    canary = tmp_path / "PWNED"
    bag = ros2_bag(tmp_path / "meta", ros2_definition(), "sqlite3")
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text() + f'  custom_data: !!python/object/apply:os.system ["touch {canary}"]\n')
    result = run(["info", bag])
    assert not canary.exists()
    assert result.exit_code == 2, result.output
    assert bag.name in one_line(result)
