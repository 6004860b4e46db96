"""Values onto the options schema: YAML files and ``--set`` values read, type- and bounds-checked, layered.

Every layer (a YAML profile, a Cartographer configuration's values, ``--set``) is checked for unknown keys
(rejected with the closest valid key), types and ranges, and errors name the key and where it came from (a
:class:`Layer`). Lengths are metres, times seconds and angles radians everywhere except on the command line,
where an explicit ``deg`` suffix (``--set ...angular_search_window=20deg``) is accepted. ``loader`` stacks the
layers (the packaged defaults, a profile, ``--set``); ``cartographer_lua`` puts a Lua configuration's values
through the same checks, so neither needs the other's module.
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from carto_cli.core.errors import CartoError
from carto_cli.core.parse import height_band
from carto_cli.options import profiles
from carto_cli.options.schema import Options, bounds_text, hints, is_section, suggestion

__all__ = [
    "Layer",
    "YamlLoader",
    "apply_overrides",
    "apply_values",
    "packaged_defaults",
    "read_yaml",
    "validate_options",
]


# --------------------------------------------------------------------------- YAML


class YamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    """SafeLoader that also reads '1e5' and '1.1e4' as floats.

    PyYAML follows YAML 1.1, which wants a dot and a signed exponent; Cartographer's
    Lua files are full of '1e5', and silently getting a string would be a trap. libyaml's parser when PyYAML
    has it: every run reads the default profile and its base, and the pure-Python parser took 50 ms of a
    2 s run on the sample.
    """


YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _parse_scalar(text: str) -> Any:
    try:
        return yaml.load(text, Loader=YamlLoader)
    except yaml.YAMLError:
        # Not YAML (e.g. an unbalanced quote): keep the text, the type check will name it.
        return text


def read_yaml(path: Path) -> tuple[dict, dict[str, int]]:
    """(mapping, dotted key -> 1-based line) of a YAML options file."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CartoError("no such profile file", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise CartoError(f"cannot read profile: {e}", path) from None
    lines: dict[str, int] = {}
    loader = None
    try:
        loader = YamlLoader(text)  # the reader already refuses control characters here (found by tests/io/test_fuzz)
        node = loader.get_single_node()
        if node is None:
            return {}, lines
        if not isinstance(node, yaml.MappingNode):
            raise CartoError(f"line {node.start_mark.line + 1}: expected a mapping of option names to values", path)
        data = _construct(loader, node, "", lines, path)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        # A reader error (a control character) has no 'problem' and a second line saying where: keep the first
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise CartoError(f"{where}invalid YAML: {problem}", path) from None
    finally:
        if loader is not None:
            loader.dispose()
    return data, lines


def _construct(loader: Any, node: Any, prefix: str, lines: dict[str, int], path: Path) -> Any:
    if not isinstance(node, yaml.MappingNode):
        return loader.construct_object(node, deep=True)
    out: dict = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        if not isinstance(key, str):
            raise CartoError(f"line {line}: option names are text, got {key!r}", path)
        full = prefix + key
        if key in out:
            raise CartoError(f"line {line}: '{full}' is given twice (first on line {lines[full]})", path)
        lines[full] = line
        out[key] = _construct(loader, value_node, full + ".", lines, path)
    return out


# --------------------------------------------------------------------------- applying values


_DEG = re.compile(r"^\s*([-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*deg\s*$")


@dataclass
class Layer:
    """Where values come from, for error messages; the default is values handed over by code."""

    path: Path | None = None  # the file, for CartoError.path; None for --set and code
    lines: dict[str, int] = field(default_factory=dict)  # dotted key -> line in the file
    cli: bool = False  # --set: values are text, 'deg' is accepted

    def fail(self, key: str, message: str) -> CartoError:
        if self.cli:
            return CartoError(f"--set {key}: {message}")
        line = self.lines.get(key)
        where = f"line {line}: " if line else ""
        return CartoError(f"{where}{key}: {message}", self.path)


def _show(value: Any) -> str:
    """A value as the user would have typed it in YAML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null (no value)"
    return repr(value)


def _coerce(value: Any, tp: Any, f: dataclasses.Field, key: str, layer: Layer) -> Any:
    unit = f.metadata.get("unit", "")
    # Values handed over by code (layer without a file) get no unit parsing at all.
    deg = _DEG.match(value) if isinstance(value, str) else None
    if deg is not None and (layer.cli or layer.path is not None):
        if unit != "rad":
            raise layer.fail(key, f"'deg' is only allowed on angles; this option is in {unit or 'no unit'}")
        degrees = float(deg.group(1))
        if not layer.cli:
            raise layer.fail(key, f"angles in profile files are radians: write {math.radians(degrees):.10g} "
                                  f"for {degrees:g}deg")
        value = math.radians(degrees)
    if tp is bool:
        if not isinstance(value, bool):
            raise layer.fail(key, f"expected true or false, got {_show(value)}")
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise layer.fail(key, f"expected an integer, got {_show(value)}")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            hint = " (radians; on the command line '20deg' also works)" if unit == "rad" and layer.cli else ""
            raise layer.fail(key, f"expected a number, got {_show(value)}{hint}")
        value = float(value)
        if not math.isfinite(value):
            raise layer.fail(key, f"expected a finite number, got {_show(value)}")
    elif tp is str:
        # A word or a small expression (trajectory_builder_2d.cloud_band); its meaning is checked by
        # validate_options, where the options that go with it are known.
        if not isinstance(value, str):
            raise layer.fail(key, f"expected text, got {_show(value)}")
        value = value.strip()
    else:  # pragma: no cover - only int/float/bool/str leaves are declared
        raise TypeError(f"unsupported option type {tp!r} for {key}")
    md = f.metadata
    shown = f"{value:g}" if isinstance(value, float) else str(value)
    if unit:
        shown += f" {unit}"
    for k, bad in (("gt", lambda v, b: v <= b), ("ge", lambda v, b: v < b),
                   ("lt", lambda v, b: v >= b), ("le", lambda v, b: v > b)):
        bound = md.get(k)
        if bound is not None and bad(value, bound):
            raise layer.fail(key, f"must be {bounds_text(md)}, got {shown}")
    return value


def apply_values(obj: Any, mapping: dict, layer: Layer, prefix: str = "") -> Any:
    """``obj`` (options or one of their sections) with a nested or dotted {key: value} mapping applied.

    Each value is type- and bounds-checked; unknown keys are rejected with the closest valid
    one. Checks across options are ``validate_options``'s (run once on the final values).
    """
    cls: type = type(obj)
    types = hints(cls)
    by_name = {f.name: f for f in dataclasses.fields(cls)}
    for key, value in mapping.items():
        if not isinstance(key, str):
            raise layer.fail(prefix.rstrip(".") or "(top level)", f"option names are text, got {key!r}")
        head, dot, rest = key.partition(".")
        full = prefix + head
        f = by_name.get(head)
        if f is None:
            written = prefix + key
            raise layer.fail(written, f"unknown option{suggestion(written)}")
        tp = types[head]
        if is_section(tp):
            current = getattr(obj, head)
            if dot:
                new = apply_values(current, {rest: value}, layer, full + ".")
            elif isinstance(value, dict):
                new = apply_values(current, value, layer, full + ".")
            elif value is None:  # 'submaps:' with nothing under it
                new = current
            else:
                keys = ", ".join(n.name for n in dataclasses.fields(tp))
                raise layer.fail(full, f"is a section, not a value; set one of its keys: {keys}")
            obj = dataclasses.replace(obj, **{head: new})
        else:
            if dot:
                raise layer.fail(prefix + key, f"'{full}' is a value, not a section")
            obj = dataclasses.replace(obj, **{head: _coerce(value, tp, f, full, layer)})
    return obj


def validate_options(options: Options, where: str | Path | None = None) -> Options:
    """Checks that involve more than one option; returns ``options`` unchanged."""
    tb = options.trajectory_builder_2d
    if tb.min_range >= tb.max_range:
        raise CartoError(f"trajectory_builder_2d.min_range ({tb.min_range:g} m) must be less than "
                         f"trajectory_builder_2d.max_range ({tb.max_range:g} m)", where)
    if tb.min_z > tb.max_z:
        raise CartoError(f"trajectory_builder_2d.min_z ({tb.min_z:g} m) must not exceed "
                         f"trajectory_builder_2d.max_z ({tb.max_z:g} m)", where)
    if tb.cloud_band.strip().lower() != "sensor":
        try:
            height_band(tb.cloud_band)
        except ValueError as e:
            raise CartoError(f"trajectory_builder_2d.cloud_band: {e}", where) from None
    return options


def _parse_assignment(item: str) -> tuple[str, Any]:
    key, eq, text = item.partition("=")
    key = key.strip()
    if not eq or not key:
        raise CartoError(f"--set expects key=value, got {item!r}")
    if not text.strip():
        raise CartoError(f"--set {key}: no value given")
    return key, _parse_scalar(text)


def apply_overrides(options: Options, overrides: Iterable[str] | dict[str, Any]) -> Options:
    """``options`` with ``key=value`` strings (as given to --set) or a {dotted key: value} dict applied.

    Dict values are taken as they are (no YAML parsing, no 'deg' suffix): that form is
    for code such as ``tune``, which already has typed values.
    """
    if isinstance(overrides, dict):
        layer = Layer()
        for key, value in overrides.items():
            options = apply_values(options, {key: value}, layer)
        return validate_options(options)
    layer = Layer(cli=True)
    for item in overrides:
        key, value = _parse_assignment(item)
        options = apply_values(options, {key: value}, layer)
    return validate_options(options, None)


def packaged_defaults() -> Options:
    """The packaged ``default.yaml`` on the schema (checked value by value; the cross-option checks are
    ``validate_options``'s, run on the final values of every layer)."""
    path = profiles.profiles_dir() / "default.yaml"
    data, lines = read_yaml(path)
    return apply_values(Options(), data, Layer(path, lines))
