"""Reading options: the packaged defaults, then a profile (YAML, or a Cartographer ``.lua`` configuration), then
``--set`` values, layered onto the schema and checked (``layering``: each layer's values and their checks).
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import yaml

from carto_cli.options import profiles
from carto_cli.options.cartographer_lua import import_lua
from carto_cli.options.layering import Layer, apply_overrides, apply_values, packaged_defaults, read_yaml
from carto_cli.options.schema import Options, options_to_dict

__all__ = ["dump_options_yaml", "load_options"]


# --------------------------------------------------------------------------- loading


def _load_file(options: Options, path: Path) -> Options:
    if path.suffix == profiles.LUA_SUFFIX:
        return apply_values(options, import_lua(path).nested(), Layer(path))
    data, lines = read_yaml(path)
    return apply_values(options, data, Layer(path, lines))


def load_options(profile: str | Path | None = None, overrides: Iterable[str] = ()) -> Options:
    """The packaged defaults, then ``profile`` (a name from ``profiles_dir()``, a .yaml path, or a Cartographer
    .lua configuration), then --set.

    Raises CartoError naming the key and the file (or --set) for unknown keys,
    wrong types, out-of-range values and malformed files.
    """
    default_path = profiles.profiles_dir() / "default.yaml"
    options = packaged_defaults()
    if profile is not None:
        path = profiles.resolve_profile(profile)
        if path.resolve() != default_path.resolve():
            options = _load_file(options, path)
    # Cross-option checks run once, on the final values: a profile may set
    # min_range past the default max_range and --set may then fix max_range.
    return apply_overrides(options, list(overrides))


def dump_options_yaml(options: Options) -> str:
    """The complete options as YAML that ``load_options`` reads back to the same values."""
    return yaml.safe_dump(options_to_dict(options), sort_keys=False, default_flow_style=False)
