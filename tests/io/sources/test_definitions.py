"""carto_cli.io.sources.definitions: a recording's message definitions checked before a typestore is built."""
import pytest
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore

from carto_cli.core.errors import FormatError
from carto_cli.io.sources import definitions
from carto_cli.io.sources.definitions import DefinitionFormat, check_type_name, checked_types

MSG = DefinitionFormat.MSG


@pytest.mark.parametrize("store, ros_version", [(Stores.ROS1_NOETIC, 1), (Stores.ROS2_HUMBLE, 2),
                                                (Stores.LATEST, 2)])
def test_every_definition_rosbags_knows_passes(store, ros_version):
    """What recorders write (each type with the types it uses) is never refused."""
    typestore = get_typestore(store)
    for name in typestore.fielddefs:
        text = typestore.generate_msgdef(name, ros_version=ros_version)[0]
        assert name in checked_types(text, MSG, name, "/t")


@pytest.mark.parametrize("line", [
    "# a comment with code in it: __import__('os')", "", "   ", "Header header", "float32[] ranges  # metres",
    "uint8 TYPE_A = 1  # a constant", "string NAME=a string constant # its comment is part of it",
    "int32 A=-3", "float64 PI=3.14159", "bool FLAG=True", "int8[4] fixed", "string<=10 bounded",
    "int32[<=5] bounded_sequence", "geometry_msgs/Point p", "geometry_msgs/msg/Point q", "int32 x 5",
    "string s \"a default\"", "int32[] xs [1, 2, 3]",
])
def test_lines_of_a_definition_that_pass(line):
    checked_types(line + "\nfloat32 y\n", MSG, "pkg/Name", "/t")


@pytest.mark.parametrize("line, why", [
    ("string __qualname__;__import__('os').system('touch x');X=abc", "not a field"),  # genpy's hole
    ("int32 __qualname__;__import__('os').system('touch x');X=1", "not a field"),
    ("float32 x;__import__('os')", "not a field"),
    ("int32 X ;__import__('os')", "not a field"),
    ("int32 Y=abc", "not a field"),
    ("int32 Y=1 ;x", "not a field"),
    ("_private int32", "not a field"),
    ("float32 _x", "not a field"),
])
def test_lines_that_are_refused_with_their_number(line, why):
    with pytest.raises(FormatError) as info:
        checked_types(f"# first\nfloat32 y\n{line}\n", MSG, "pkg/Name", "/scan")
    message = str(info.value)
    assert message.startswith("topic /scan: the message definition of 'pkg/Name', line 3: ") and why in message


@pytest.mark.parametrize("name", ["x", "pkg/Name'", "pkg/msg/X;__import__('os')", "1pkg/Name", "a/b/c/d", ""])
def test_type_names_that_are_refused(name):
    with pytest.raises(FormatError, match="is not pkg/Name or pkg/msg/Name"):
        checked_types("float32 x\n", MSG, name, "/t")
    with pytest.raises(FormatError, match="topic /t: the type name"):
        check_type_name(name, "/t")


def test_a_parse_tree_with_code_for_a_name_is_refused(monkeypatch):
    """Whatever a parser lets through, no name that is not a ROS name reaches a typestore (a second wall behind
    the line check, and the only one for IDL)."""
    import rosbags.typesys

    base = (Nodetype.BASE, ("int32", 0))
    trees = [
        {"pkg/msg/Name": ([], [("x;__import__('os')", base)])},
        {"pkg/msg/Name": ([("X;__import__('os')", "int32", 1)], [("x", base)])},
        {"pkg/msg/Name": ([("X", "int32", "__import__('os')")], [("x", base)])},
        {"pkg/msg/Name": ([], [("x", (Nodetype.NAME, "pkg/msg/T;__import__('os')"))])},
        {"pkg/msg/Name": ([], [("x", (Nodetype.SEQUENCE, ((Nodetype.BASE, ("int32;x", 0)), 0)))])},
        {"pkg/msg/Name'];__import__('os')#": ([], [("x", base)])},
    ]
    for i, tree in enumerate(trees):
        monkeypatch.setattr(rosbags.typesys, "get_types_from_idl", lambda text, tree=tree: tree)
        with pytest.raises(FormatError, match="not a valid ROS message definition"):  # a text of its own: not cached
            checked_types(f"module pkg {{ }};  // {i}\n", DefinitionFormat.IDL, "pkg/msg/Name", "/t")


def test_the_typestore_decodes_what_was_checked():
    noetic = get_typestore(Stores.ROS1_NOETIC)
    text = noetic.generate_msgdef("std_msgs/msg/String")[0]
    store = definitions.typestore_of(checked_types(text, MSG, "std_msgs/String", "/chatter"))
    msg = noetic.types["std_msgs/msg/String"](data="hi")
    assert store.deserialize_ros1(noetic.serialize_ros1(msg, "std_msgs/msg/String"), "std_msgs/msg/String").data == "hi"
