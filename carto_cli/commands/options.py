"""`carto options`: every option with its type, default, unit, bounds and what it does."""
from __future__ import annotations

from pathlib import Path

from carto_cli.options import OptionInfo, option_info
from carto_cli.options.cartographer_lua import LuaImport, import_lua

__all__ = ["format_option", "import_configuration", "list_options"]


def import_configuration(path: str | Path) -> LuaImport:
    """A Cartographer Lua configuration's settings as carto options (``carto options import``)."""
    return import_lua(path)


def list_options(filter_: str | None = None) -> list[OptionInfo]:
    """The options whose dotted name contains ``filter_`` (all without one), in declaration order."""
    return [i for i in option_info() if filter_ is None or filter_ in i.name]


def format_option(info: OptionInfo) -> str:
    """'name = default unit (type)  [bounds]' and the doc on an indented second line."""
    unit = f" {info.unit}" if info.unit else ""
    bounds = f"  [{info.bounds}]" if info.bounds else ""
    return f"{info.name} = {info.default!r}{unit} ({info.type}){bounds}\n    {info.doc}"
