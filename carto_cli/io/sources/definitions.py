"""The message definitions a recording carries, checked before anything is built from them.

A ROS1 bag, a ROS2 bag and an MCAP file each carry the text of their message definitions, and a decoder is made
from that text. rosbags (which decodes every format here) writes Python source from a definition's type, field
and constant names and runs it, as genpy does; a name copied into that source unchecked is code, run by opening
the file. So no definition reaches a typestore without passing here: first line by line as ROS ``.msg`` text (so a
refusal names its line), then its parse tree name by name, whatever the format, before the typestore is built.
Parsing itself runs nothing: rosbags' parsers are pure Python grammars.
"""
from __future__ import annotations

import enum
import functools
import re
from typing import Any

from carto_cli.core.errors import FormatError

__all__ = ["DefinitionFormat", "check_type_name", "checked_types", "typestore_of"]

# ROS's own rule for package, message, field and constant names (genmsg, rosidl): a letter, then letters, digits
# and underscores. Every name that reaches generated source is held to it.
NAME = r"[a-zA-Z][a-zA-Z0-9_]*"
_NAME = re.compile(NAME)
_TYPE_NAME = re.compile(rf"{NAME}(?:/{NAME}){{1,2}}")  # pkg/Name or pkg/msg/Name
_BASE_TYPE = re.compile(r"[a-z][a-z0-9_]*")  # bool, int32, float64, string, octet...

# One line of .msg text (ROS1, and ROS2's additions: bounded strings and sequences, default values, annotations):
# a field (a default value and a comment may follow its name), a constant (NAME=VALUE: a string constant's value is
# the rest of the line, any other's a literal), a comment, a blank line, or the separator and 'MSG: pkg/Name'
# header between a type and each type it uses.
_FIELD_TYPE = rf"{NAME}(?:/{NAME}){{0,2}}(?:<=\d+)?(?:\[(?:<=)?\d*\])?"
_LITERAL = (r"(?:[-+]?(?:[0-9.][0-9a-fA-FxX_.eE+-]*|inf|nan)|true|false|True|False"
            r"|\"(?:\\.|[^\"\\])*\"|'(?:\\.|[^'\\])*'|\[[^\]]*\])")
_END = r"(?:[ \t]+#.*|#.*)?[ \t]*"
_FIELD = rf"{_FIELD_TYPE}[ \t]+{NAME}(?:[ \t]+{_LITERAL})?{_END}"
_CONSTANT = rf"(?:w?string(?:<=\d+)?[ \t]+{NAME}[ \t]*=.*|{_FIELD_TYPE}[ \t]+{NAME}[ \t]*=[ \t]*{_LITERAL}{_END})"
_MSG_LINE = re.compile(rf"[ \t]*(?:(?:@[a-z]+[ \t]+)?(?:{_CONSTANT}|{_FIELD})|@[a-z]+[ \t]*|#.*|=+)?"
                       rf"|MSG: {NAME}(?:/{NAME}){{1,2}}[ \t]*")
_CONSTANT_TYPES = {"bool": (bool,), "string": (str,), "wstring": (str,), "float32": (float, int),
                   "float64": (float, int)}  # every other base type holds an int

_IDL_SEPARATOR = "=" * 80 + "\n"
_IDL_HEADER = re.compile(r"^={80}\nIDL: [^\n]*(?:\n|$)", re.MULTILINE)


class DefinitionFormat(enum.Enum):
    """How a definition is written: ROS ``.msg`` text (ROS1 and ROS2) or ROS2's IDL."""

    MSG = "msg"
    IDL = "idl"


class _Invalid(Exception):
    def __init__(self, reason: str, line: int | None = None):
        super().__init__(reason)
        self.reason, self.line = reason, line


def checked_types(text: str, fmt: DefinitionFormat, msgtype: str, topic: str) -> dict[str, Any]:
    """The types ``text`` defines (rosbags' parse tree, a ``Typesdict``), every name in it checked.

    Raises FormatError naming the topic, the type and the line for text that is not a valid definition.
    """
    try:
        return dict(_checked(text, fmt, msgtype))  # a copy: the cached tree stays as checked
    except _Invalid as e:
        where = f", line {e.line}" if e.line is not None else ""
        raise FormatError(f"topic {topic}: the message definition of {_shown(msgtype)}{where}: {e.reason}: "
                          "not a valid ROS message definition, nothing decoded") from None


def check_type_name(msgtype: str, topic: str) -> None:
    """Refuse a type name that is not ``pkg/Name`` or ``pkg/msg/Name`` (it becomes a class name in source)."""
    if not _TYPE_NAME.fullmatch(msgtype):
        raise FormatError(f"topic {topic}: the type name {_shown(msgtype)} is not pkg/Name or pkg/msg/Name: "
                          "not a valid ROS message type, nothing decoded")


def typestore_of(types: dict[str, Any]) -> Any:
    """A rosbags typestore of ``types`` alone (checked by :func:`checked_types`)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


@functools.lru_cache(maxsize=256)  # a bag repeats one definition on every connection of its type
def _checked(text: str, fmt: DefinitionFormat, msgtype: str) -> dict[str, Any]:
    if not _TYPE_NAME.fullmatch(msgtype):
        raise _Invalid(f"the type name {_shown(msgtype)} is not pkg/Name or pkg/msg/Name")
    if fmt is DefinitionFormat.MSG:
        _check_msg_lines(text)
    types = _parsed(text, fmt, msgtype)
    _check_tree(types, text)
    return types


def _check_msg_lines(text: str) -> None:
    for number, line in enumerate(text.split("\n"), 1):
        if not _MSG_LINE.fullmatch(line):
            raise _Invalid(f"{_shown(line)} is not a field (TYPE NAME), a constant (TYPE NAME=VALUE) or a comment "
                           f"(names are {NAME}, values literals)", number)


def _parsed(text: str, fmt: DefinitionFormat, msgtype: str) -> dict[str, Any]:
    from rosbags.typesys import get_types_from_idl, get_types_from_msg

    if fmt is DefinitionFormat.MSG:
        # rosbags parses 'MSG: name' and the text: its offsets count that header line.
        return _parse(lambda: get_types_from_msg(text, msgtype), f"MSG: {msgtype}\n{text}", -1, "it does not parse")
    types: dict[str, Any] = {}
    for start, part in _idl_parts(text):
        # The IDL parser backtracks to the declaration that failed: its offset is where that declaration begins.
        types.update(_parse(lambda part=part: get_types_from_idl(part), part, text.count("\n", 0, start),
                            "the declaration beginning on this line does not parse"))
    return types


def _idl_parts(text: str) -> list[tuple[int, str]]:
    """(offset, IDL) of each type: rosbag2 and MCAP writers join a type's IDL with its dependencies', each after
    a separator and an 'IDL: pkg/msg/Name' header."""
    heads = list(_IDL_HEADER.finditer(text)) if text.startswith(_IDL_SEPARATOR + "IDL: ") else []
    if not heads:
        return [(0, text)]
    ends = [h.start() for h in heads[1:]] + [len(text)]
    return [(h.end(), text[h.end():end]) for h, end in zip(heads, ends)]


def _parse(parse: Any, parsed: str, shift: int, failure: str) -> dict[str, Any]:
    """``parse()``'s types; a failure names the line its offset into ``parsed`` falls on (moved by ``shift``)."""
    try:
        return dict(parse())
    except Exception as e:  # rosbags' parse failures: TypesysError, and asserts on malformed trees
        # Its message: 'Could not parse:', the text's repr, the offset it stopped at.
        lines = str(e).split("\n")
        line = None
        if len(lines) > 2 and lines[2].isdigit():
            line = parsed.count("\n", 0, int(lines[2])) + 1 + shift
        why = _first_line(e)
        raise _Invalid(failure + ("" if why == "Could not parse" else f" ({why})"), line) from None


def _check_tree(types: dict[str, Any], text: str) -> None:
    """Every name in the parse tree is a ROS name and every constant a plain value: what rosbags writes into
    source is then identifiers and literals only."""
    for name, (constants, fields) in types.items():
        if not isinstance(name, str) or not _TYPE_NAME.fullmatch(name):
            raise _bad_name(name, text)
        for constant in constants:
            cname, ctype, value = constant
            _check_name(cname, _NAME, text)
            _check_name(ctype, _BASE_TYPE, text)
            if type(value) not in _CONSTANT_TYPES.get(ctype, (int,)):
                raise _Invalid(f"the {ctype} constant {_shown(cname)} has the value {_shown(value)}",
                               _line_of(cname, text))
        for fname, desc in fields:
            _check_name(fname, _NAME, text)
            _check_field(desc, text)


def _check_field(desc: Any, text: str) -> None:
    from rosbags.interfaces import Nodetype

    kind, payload = desc
    if kind == Nodetype.BASE:  # (name, string bound); a bare name in rosbags before 0.10
        _check_name(payload[0] if isinstance(payload, tuple) else payload, _BASE_TYPE, text)
    elif kind == Nodetype.NAME:
        _check_name(payload, _TYPE_NAME, text)
    elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        _check_field(payload[0], text)
        if type(payload[1]) is not int:
            raise _Invalid(f"an array of size {_shown(payload[1])}")
    else:
        raise _Invalid(f"a field of unknown kind {_shown(kind)}")


def _check_name(name: Any, rule: re.Pattern, text: str) -> None:
    if not isinstance(name, str) or not rule.fullmatch(name):
        raise _bad_name(name, text)


def _bad_name(name: Any, text: str) -> _Invalid:
    return _Invalid(f"the name {_shown(name)} is not a ROS name ({NAME})", _line_of(name, text))


def _line_of(name: Any, text: str) -> int | None:
    at = text.find(str(name))
    return None if at < 0 else text.count("\n", 0, at) + 1


def _first_line(e: Exception) -> str:
    text = str(e).strip()
    return text.split("\n", 1)[0].rstrip(":") if text else type(e).__name__


def _shown(value: Any, limit: int = 60) -> str:
    if isinstance(value, str) and len(value) > limit:
        return repr(value[:limit - 3] + "...")
    return repr(value)
