"""`carto profiles`: the packaged profiles with their one-sentence descriptions, and a profile's effective options."""
from __future__ import annotations

import shutil
import textwrap
from collections.abc import Sequence

import yaml

from carto_cli.options import changed_options, dump_options_yaml, list_profiles, load_options, profiles_dir

__all__ = ["AUTO", "describe_profiles", "format_profile_list", "show_profile"]

NAME_WIDTH = 12
MAX_WIDTH = 100  # a wider terminal still gets lines one can read
# `--profile auto` is the default of the commands that map, yet no file: what `profiles show auto` says instead.
AUTO = ("auto is the default of `carto map`, not a fixed set of options: they are chosen for each recording. carto "
        "surveys the start of the recording (motion between scans, beams, range, odometry, IMU) and picks the mapping "
        "system, a base profile (sparse, wheeled or office) and a few settings derived from what it measured. "
        "`carto info REC` shows what auto would choose for a recording (`carto map` prints the same 'auto:' line); "
        "`carto profiles show NAME` then shows that base profile, and `carto profiles show default` the options every "
        "profile starts from. The rules and what they were measured on: docs/profiles.md (\"auto\").")


def describe_profiles() -> list[tuple[str, str]]:
    """(name, the first sentence of its file's opening comment, or '') for every packaged profile."""
    out = []
    for name in list_profiles():
        lines = []
        for line in (profiles_dir() / f"{name}.yaml").read_text().splitlines():
            text = line.lstrip("#").strip()
            if not line.startswith("#") or not text:
                break  # the opening comment ends at its first blank line
            lines.append(text)
        out.append((name, _first_sentence(" ".join(lines))))
    return out


def _first_sentence(text: str) -> str:
    """Up to the first full stop outside parentheses that ends a word (not one inside a number: "0.5-1 m")."""
    depth = 0
    for i, c in enumerate(text):
        if c == "(":
            depth += 1
        elif c == ")":
            depth = max(0, depth - 1)
        elif c == "." and depth == 0 and (i + 1 == len(text) or text[i + 1].isspace()):
            return text[:i + 1]
    return text


def _width(width: int | None) -> int:
    return width if width is not None else min(shutil.get_terminal_size().columns, MAX_WIDTH)


def format_profile_list(width: int | None = None) -> str:
    """One entry per profile: its name, then its description wrapped to ``width`` (default: the terminal's, at
    most MAX_WIDTH) under itself."""
    indent = " " * (NAME_WIDTH + 1)
    entries = []
    for name, first in describe_profiles():
        entries.append(textwrap.fill(first, _width(width), initial_indent=f"{name:<{NAME_WIDTH}} ",
                                     subsequent_indent=indent, break_on_hyphens=False)
                       if first else name)
    return "\n".join(entries)


def show_profile(name: str, overrides: Sequence[str] = (), *, changed: bool = False, width: int | None = None) -> str:
    """The merged options of a profile (default + profile + --set) as YAML; with ``changed`` only those
    that differ from the default. For 'auto', what it is (no file holds its options: they depend on the
    recording)."""
    if name == "auto":
        load_options(None, list(overrides))  # a bad --set is still an error
        return textwrap.fill(AUTO, _width(width), break_on_hyphens=False)
    options = load_options(name, list(overrides))
    if changed:
        return yaml.safe_dump(changed_options(options), sort_keys=False).rstrip()
    return dump_options_yaml(options).rstrip()
