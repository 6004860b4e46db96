"""carto's options: the typed schema, loading it from YAML profiles and --set, the packaged profiles.

``from carto_cli.options import Options, load_options, ...`` is the public face; the
modules are ``schema`` (dataclasses and introspection), ``layering`` (YAML and --set values onto the schema,
checked), ``loader`` (the defaults, a profile and --set, stacked), ``cartographer_lua`` (a Cartographer
configuration's values) and ``profiles`` (the packaged profile files).
"""
from carto_cli.options.layering import Layer, apply_overrides, apply_values, read_yaml, validate_options
from carto_cli.options.loader import dump_options_yaml, load_options
from carto_cli.options.profiles import list_profiles, profiles_dir, resolve_profile
from carto_cli.options.schema import (
    CeresSolverOptions,
    FastCorrelativeScanMatcher,
    GMapping,
    OptionInfo,
    Options,
    PoseGraph,
    Relocalization,
    TrajectoryBuilder2D,
    changed_options,
    get_option,
    option_info,
    option_names,
    options_to_dict,
    suggestion,
)

__all__ = [
    "CeresSolverOptions", "FastCorrelativeScanMatcher", "GMapping", "Layer", "OptionInfo", "Options", "PoseGraph",
    "Relocalization", "TrajectoryBuilder2D", "apply_overrides", "apply_values", "changed_options",
    "dump_options_yaml", "get_option", "list_profiles", "load_options", "option_info", "option_names",
    "options_to_dict", "profiles_dir", "read_yaml", "resolve_profile", "suggestion", "validate_options",
]
