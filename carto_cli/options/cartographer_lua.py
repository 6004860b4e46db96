"""Cartographer's Lua configurations as carto options (``--profile robot.lua``, ``carto options import``).

A team's tuned ``robot.lua`` is a Lua program: it includes the stock files (``map_builder.lua``,
``trajectory_builder.lua``, ...), builds an ``options`` table and changes ``TRAJECTORY_BUILDER_2D`` and
``POSE_GRAPH`` in place, often with arithmetic (``math.rad(20.)``) and variables. It is run here by a real Lua
interpreter (lupa), never parsed: the stock files it includes are carto's own defaults written as the Lua tables
Cartographer's stock files define, so what the file changes is exactly what differs from carto's defaults.

The trajectory builder and pose graph are read from the ``options`` table the file returns (as Cartographer's
node does), else from the globals. Their keys map onto carto's by name (carto's options carry Cartographer's
names); the few whose nesting differs are in :data:`RENAMED`. Keys carto has no use for (3D, TSDF, ROS node
options, solver threads...) are reported, not silently dropped. The Lua runs sandboxed (``options.lua_sandbox``).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from carto_cli.core.errors import CartoError
from carto_cli.options.layering import Layer, apply_values, packaged_defaults, validate_options
from carto_cli.options.lua_sandbox import Sandbox, source
from carto_cli.options.schema import Options, hints, is_section, options_to_dict

__all__ = ["LuaImport", "import_lua", "stock_lua"]

# Cartographer's dotted key (under trajectory_builder_2d / pose_graph) -> carto's, where they differ.
RENAMED = {
    "trajectory_builder_2d.submaps.range_data_inserter.probability_grid_range_data_inserter.insert_free_space":
        "trajectory_builder_2d.submaps.range_data_inserter.insert_free_space",
    "trajectory_builder_2d.submaps.range_data_inserter.probability_grid_range_data_inserter.hit_probability":
        "trajectory_builder_2d.submaps.range_data_inserter.hit_probability",
    "trajectory_builder_2d.submaps.range_data_inserter.probability_grid_range_data_inserter.miss_probability":
        "trajectory_builder_2d.submaps.range_data_inserter.miss_probability",
}
# Selector strings carto follows (its only kind); any other value is reported as not used.
SELECTORS = {
    "trajectory_builder_2d.submaps.grid_options_2d.grid_type": "PROBABILITY_GRID",
    "trajectory_builder_2d.submaps.range_data_inserter.range_data_inserter_type": "PROBABILITY_GRID_INSERTER_2D",
}
SECTIONS = ("trajectory_builder_2d", "pose_graph")
_CARTO_TO_LUA = {v: k for k, v in RENAMED.items()}


@dataclass
class LuaImport:
    """What a Lua configuration sets: carto options that differ from carto's defaults, and what carto leaves."""

    path: Path
    overrides: dict[str, Any]  # carto's dotted key -> value (only those differing from carto's defaults)
    unused: dict[str, Any] = field(default_factory=dict)  # Cartographer's dotted key -> value, not used by carto

    def nested(self) -> dict:
        """The overrides as a nested mapping (a profile's YAML layout)."""
        return _nest(self.overrides.items())

    def note(self) -> str | None:
        """One line naming what carto does not use (None when it uses everything)."""
        if not self.unused:
            return None
        node = sorted(k for k in self.unused if "." not in k)
        keys = sorted(k for k in self.unused if "." in k)
        parts = []
        if keys:
            shown = ", ".join(keys[:6]) + (f" and {len(keys) - 6} more" if len(keys) > 6 else "")
            parts.append(f"{len(keys)} setting(s) carto does not use: {shown}")
        if node:
            parts.append(f"{len(node)} ROS node option(s) ({', '.join(node[:3])}{', ...' if len(node) > 3 else ''}): "
                         "carto takes frames and topics from the recording")
        return f"{self.path.name}: " + "; ".join(parts) + " (carto options import lists them)"

    def to_yaml(self) -> str:
        """A carto profile with the same options (``carto options import``), what was left out as comments."""
        import yaml

        lines = [f"# carto profile imported from {self.path.name} (carto options import): Cartographer's settings",
                 "# that differ from carto's defaults, under the same names."]
        if self.unused:
            lines.append("# Not used by carto (no counterpart, or a kind carto does not build):")
            lines += [f"#   {k} = {_lua_repr(v)}" for k, v in sorted(self.unused.items())]
        body = yaml.safe_dump(self.nested(), sort_keys=False, default_flow_style=False) if self.overrides else "{}\n"
        return "\n".join(lines) + "\n" + body


def _lua_repr(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


# --------------------------------------------------------------------------- the stock files, from carto's defaults

def _lua_value(value: Any, indent: int) -> str:
    if isinstance(value, dict):
        pad = "  " * (indent + 1)
        items = "".join(f"{pad}{k} = {_lua_value(v, indent + 1)},\n" for k, v in value.items())
        return "{\n" + items + "  " * indent + "}"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else "0/0"
    return repr(value)


def _cartographer_layout(section: str, values: dict) -> dict:
    """carto's nested defaults of ``section`` laid out as Cartographer's stock file has them."""
    keys = [(_CARTO_TO_LUA.get(key, key), value) for key, value in _flatten(values, section + ".")]
    keys += [(key, value) for key, value in SELECTORS.items() if key.startswith(section + ".")]
    return _nest((key.split(".", 1)[1], value) for key, value in keys)


def _nest(items: Iterable[tuple[str, Any]]) -> dict:
    """(dotted key, value) pairs as a nested mapping."""
    out: dict = {}
    for key, value in items:
        node = out
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def stock_lua(options: Options | None = None) -> dict[str, str]:
    """The stock files a configuration includes, by name, holding ``options`` (carto's defaults): every table
    creates missing sub-tables when written to, so settings carto has no key for can still be assigned (and are
    then reported)."""
    from carto_cli.options import load_options

    values = options_to_dict(options or load_options(None))
    tb = _lua_value(_cartographer_layout("trajectory_builder_2d", values["trajectory_builder_2d"]), 0)
    pg = _lua_value(_cartographer_layout("pose_graph", values["pose_graph"]), 0)
    return {
        "trajectory_builder_2d.lua": f"TRAJECTORY_BUILDER_2D = carto_open({tb})\n",
        "trajectory_builder_3d.lua": "TRAJECTORY_BUILDER_3D = carto_open({})\n",
        "pose_graph.lua": f"POSE_GRAPH = carto_open({pg})\n",
        "sparse_pose_graph.lua": 'include "pose_graph.lua"\nSPARSE_POSE_GRAPH = POSE_GRAPH\n',
        "map_builder.lua": ('include "pose_graph.lua"\n'
                            "MAP_BUILDER = carto_open({use_trajectory_builder_2d = false, "
                            "use_trajectory_builder_3d = false, num_background_threads = 4, "
                            "pose_graph = POSE_GRAPH})\n"),
        "trajectory_builder.lua": ('include "trajectory_builder_2d.lua"\ninclude "trajectory_builder_3d.lua"\n'
                                   "TRAJECTORY_BUILDER = carto_open({trajectory_builder_2d = TRAJECTORY_BUILDER_2D, "
                                   "trajectory_builder_3d = TRAJECTORY_BUILDER_3D})\n"),
        "map_builder_server.lua": ('include "map_builder.lua"\n'
                                   "MAP_BUILDER_SERVER = carto_open({map_builder = MAP_BUILDER})\n"),
    }


# Tables that grow a sub-table on first access, so `T.a.b = 1` works where the stock table has no `a`; the
# sub-tables are marked so that an untouched one is not taken for a setting.
_PRELUDE = """
local function open(t)
  for k, v in pairs(t) do
    if type(v) == "table" and getmetatable(v) == nil then open(v) end
  end
  return setmetatable(t, {__index = function(self, key)
    local sub = open({})
    rawset(self, key, sub)
    return sub
  end})
end
carto_open = open
"""


def _flatten(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted key, leaf value) of a nested mapping."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _flatten(v, f"{prefix}{k}.")
    else:
        yield prefix[:-1], value


def _to_python(value: Any, seen: frozenset = frozenset()) -> Any:
    """A Lua value as Python: tables as dicts (arrays as lists), numbers and strings as they are."""
    from lupa import lua_type

    if lua_type(value) != "table":
        return value
    if id(value) in seen:  # a table that holds itself: nothing more to read
        return {}
    seen = seen | {id(value)}
    items = {k: _to_python(v, seen) for k, v in value.items()}
    if items and all(isinstance(k, int) for k in items) and sorted(items) == list(range(1, len(items) + 1)):
        return [items[k] for k in sorted(items)]
    return items


def _read(value: Callable[[], Any], path: Path) -> Any:
    """:func:`_to_python` of ``value()``, with what a configuration can make that Python cannot read as a CartoError."""
    try:
        return _to_python(value())
    except RecursionError:
        raise CartoError("its tables are nested too deeply to read", path) from None
    except UnicodeDecodeError as e:
        raise CartoError(f"a string among its options is not UTF-8 text ({e.reason})", path) from None


def _typed(value: Any, tp: Any) -> Any:
    """A Lua number as the option's type: Lua writes 50 and 50. alike where carto wants an int or a float."""
    if tp is int and isinstance(value, float) and value.is_integer():
        return int(value)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def _leaf_types() -> dict[str, Any]:
    out: dict[str, Any] = {}

    def walk(cls: type, prefix: str) -> None:
        for f in dataclasses.fields(cls):
            tp = hints(cls)[f.name]
            if is_section(tp):
                walk(tp, f"{prefix}{f.name}.")
            else:
                out[prefix + f.name] = tp

    walk(Options, "")
    return out


# By file and its state, so loading the options and the CLI's note run it once per command (an include changed
# meanwhile is not seen; within one command it is not).
_IMPORTED: dict[tuple, LuaImport] = {}


def import_lua(path: str | Path) -> LuaImport:
    """Run ``path`` (a Cartographer configuration) and read the options it sets. Raises CartoError naming the
    file for a Lua error, a missing include, or a value of the wrong type for carto's option."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise CartoError("no such file" if not path.exists() else "not a file", path)
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    if key not in _IMPORTED:
        _IMPORTED[key] = _import(path)
    return _IMPORTED[key]


def _import(path: Path) -> LuaImport:
    try:
        import lupa  # noqa: F401
    except ImportError as e:  # pragma: no cover - a dependency of carto
        raise CartoError("reading Lua configurations needs the 'lupa' package (pip install lupa)", path) from e

    defaults = validate_options(packaged_defaults())
    box = Sandbox(path, stock_lua(defaults))
    box.run(_PRELUDE, None, "carto's prelude")
    returned = box.run(source(path), path, path.name)
    g = box.env
    found = {"trajectory_builder_2d": None, "pose_graph": None}
    unused: dict[str, Any] = {}
    top = _read(lambda: returned, path)
    if isinstance(top, dict):
        tb = top.pop("trajectory_builder", None)
        mb = top.pop("map_builder", None)
        if isinstance(tb, dict):
            found["trajectory_builder_2d"] = tb.pop("trajectory_builder_2d", None)
            _collect(tb, "trajectory_builder.", unused)
        if isinstance(mb, dict):
            found["pose_graph"] = mb.pop("pose_graph", None) or mb.pop("sparse_pose_graph", None)
            if mb.get("use_trajectory_builder_3d"):
                unused["map_builder.use_trajectory_builder_3d"] = True
            mb.pop("use_trajectory_builder_3d", None)
            mb.pop("use_trajectory_builder_2d", None)
            mb.pop("num_background_threads", None)  # carto sizes its pools itself (--jobs)
            mb.pop("trajectory_builder_2d", None)
            mb.pop("trajectory_builder_3d", None)
            _collect(mb, "map_builder.", unused)
        _collect(top, "", unused)  # the ROS node's options (frames, topics, rates): carto reads them from the bag
    if found["trajectory_builder_2d"] is None:  # (reading a global may meet a string that is not UTF-8)
        found["trajectory_builder_2d"] = _read(lambda: g.TRAJECTORY_BUILDER_2D, path)
    if found["pose_graph"] is None:
        found["pose_graph"] = _read(lambda: g.POSE_GRAPH, path)
    if all(v is None for v in found.values()):
        raise CartoError("no TRAJECTORY_BUILDER_2D or POSE_GRAPH in it, and it returns no options table "
                         "(is it a Cartographer configuration?)", path)

    types = _leaf_types()
    base = dict(_flatten(options_to_dict(defaults)))
    overrides: dict[str, Any] = {}
    for section in SECTIONS:
        values = found[section]
        if not isinstance(values, dict):
            continue
        # (A sub-table created by reading it and never set is empty: it has no leaf, so no key.)
        for key, value in _flatten(values, section + "."):
            if key in SELECTORS:
                if value != SELECTORS[key]:
                    unused[key] = value
                continue
            carto_key = RENAMED.get(key, key)
            tp = types.get(carto_key)
            if tp is None or isinstance(value, list):
                unused[key] = value
                continue
            value = _typed(value, tp)
            if value != base[carto_key]:
                overrides[carto_key] = value
    order = {k: i for i, k in enumerate(types)}  # the schema's order, not the Lua tables' hash order
    overrides = dict(sorted(overrides.items(), key=lambda kv: order[kv[0]]))
    result = LuaImport(path, overrides, dict(sorted(unused.items())))
    options = apply_values(defaults, result.nested(), Layer(path))  # types and bounds, errors naming the key
    validate_options(options, path)
    return result


def _collect(values: dict, prefix: str, out: dict) -> None:
    out.update(_flatten(values, prefix))
