"""The packaged profiles: where they are, their names, and resolving a name or path to a file."""
from __future__ import annotations

import difflib
from pathlib import Path

from carto_cli.core.errors import CartoError

__all__ = ["PROFILE_SUFFIXES", "list_profiles", "profiles_dir", "resolve_profile"]

PROFILE_SUFFIXES = (".yaml", ".yml")
LUA_SUFFIX = ".lua"  # a Cartographer configuration (options.cartographer_lua)


def profiles_dir() -> Path:
    """The directory of the packaged profiles (``carto_cli/profiles``)."""
    return Path(__file__).resolve().parents[1] / "profiles"


def list_profiles() -> list[str]:
    """Names of the packaged profiles, 'default' included."""
    d = profiles_dir()
    return sorted(p.stem for p in d.iterdir() if p.suffix in PROFILE_SUFFIXES) if d.is_dir() else []


def resolve_profile(profile: str | Path) -> Path:
    """The file of a packaged profile's name, or ``profile`` itself when it is a path (.yaml, or with a slash)."""
    if isinstance(profile, Path):
        return profile
    text = str(profile)
    if text.endswith(PROFILE_SUFFIXES + (LUA_SUFFIX,)) or "/" in text or "\\" in text:
        return Path(text).expanduser()
    for suffix in PROFILE_SUFFIXES:
        candidate = profiles_dir() / f"{text}{suffix}"
        if candidate.is_file():
            return candidate
    names = list_profiles()
    close = difflib.get_close_matches(text, names, n=1)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    raise CartoError(f"unknown profile '{text}'{hint} (profiles: {', '.join(names) or 'none'}; "
                     "a path ending in .yaml is read as a file, one ending in .lua as a Cartographer configuration)")
