"""`carto profiles`: the packaged profiles with their one-line descriptions, and a profile's effective options."""
from __future__ import annotations

from collections.abc import Sequence

import yaml

from carto_cli.options import changed_options, dump_options_yaml, list_profiles, load_options, profiles_dir

__all__ = ["describe_profiles", "show_profile"]


def describe_profiles() -> list[tuple[str, str]]:
    """(name, the first comment line of its file, or '') for every packaged profile."""
    out = []
    for name in list_profiles():
        first = ""
        for line in (profiles_dir() / f"{name}.yaml").read_text().splitlines():
            if line.startswith("#"):
                first = line.lstrip("# ").strip()
                break
        out.append((name, first))
    return out


def show_profile(name: str, overrides: Sequence[str] = (), *, changed: bool = False) -> str:
    """The merged options of a profile (default + profile + --set) as YAML; with ``changed`` only those
    that differ from the default."""
    options = load_options(name, list(overrides))
    if changed:
        return yaml.safe_dump(changed_options(options), sort_keys=False).rstrip()
    return dump_options_yaml(options).rstrip()
