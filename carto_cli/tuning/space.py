"""Search spaces for ``carto tune``: which options to vary, and over what range.

A space is a YAML mapping of option names (as ``carto options`` lists them) to either
a range or a list of choices::

    trajectory_builder_2d.ceres_scan_matcher.translation_weight: {low: 0.1, high: 100, log: true}
    trajectory_builder_2d.submaps.num_range_data: {low: 20, high: 120, int: true}
    trajectory_builder_2d.use_online_correlative_scan_matching: {choices: [false, true]}

Keys may also be nested by section, as in a profile. Every entry is checked against
``option_info()``: an unknown option is an error naming the closest valid one, a range
or choice outside the option's own bounds is an error, and so is a wrong type (a
non-integer range for an integer option, a range for a true/false option, ``log``
with a non-positive ``low``...). Errors name the file, the line and the key.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from carto_cli.core.errors import CartoError
from carto_cli.options import Layer, Options, apply_values, option_info, profiles_dir, read_yaml, suggestion

__all__ = ["Param", "base_values", "default_space_path", "load_space", "spaces_dir", "suggest_params"]

_SPEC_KEYS = {"low", "high", "log", "int", "step", "choices"}


@dataclass(frozen=True)
class Param:
    """One dimension of a search space."""

    name: str  # dotted option key
    kind: str  # 'float' | 'int' | 'categorical'
    low: float | int | None = None
    high: float | int | None = None
    log: bool = False
    step: float | int | None = None
    choices: tuple = ()

    def contains(self, value: Any) -> bool:
        if self.kind == "categorical":
            return any(value == c and type(value) is type(c) for c in self.choices)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        low, high = self.low, self.high
        return low is not None and high is not None and low <= value <= high

    def describe(self) -> str:
        if self.kind == "categorical":
            return "{" + ", ".join(map(repr, self.choices)) + "}"
        return f"[{self.low:g}, {self.high:g}]" + (" log" if self.log else "") + (" int" if self.kind == "int" else "")


def spaces_dir() -> Path:
    """``carto_cli/profiles/spaces``: the default search space of each packaged profile."""
    return profiles_dir() / "spaces"


def default_space_path(profile: str | Path | None = None) -> Path:
    """The packaged space for ``profile`` (a packaged profile's name), else ``default.yaml``."""
    if profile is not None and not str(profile).endswith((".yaml", ".yml")):
        candidate = spaces_dir() / f"{profile}.yaml"
        if candidate.is_file():
            return candidate
    return spaces_dir() / "default.yaml"


def _flatten(data: dict, prefix: str, leaves: dict[str, Any], fail) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        if not isinstance(key, str):
            raise fail(prefix.rstrip(".") or "(top level)", f"option names are text, got {key!r}")
        full = prefix + key
        if full in leaves:
            out[full] = value
        elif isinstance(value, dict) and any(n.startswith(full + ".") for n in leaves):
            out.update(_flatten(value, full + ".", leaves, fail))
        elif any(n.startswith(full + ".") for n in leaves):
            raise fail(full, "is a section, not an option: give a range or choices for one of its options")
        else:
            raise fail(full, f"unknown option{suggestion(full)}")
    return out


def _check_value(name: str, value: Any, what: str, fail) -> Any:
    """``value`` as the option would take it; CartoError when its type or bounds reject it."""
    try:
        # This option's own type and bounds only: cross-option checks (min_range < max_range)
        # depend on the other values of a trial and are made when the trial applies them.
        opts = apply_values(Options(), {name: value}, Layer())
    except CartoError as e:
        # "key: must be >= 0, got -1" -> keep what follows the key.
        msg = e.message.split(": ", 1)[-1] if e.message.startswith(name) else e.message
        raise fail(name, f"{what} {value!r} is not a valid value: {msg}") from None
    obj: Any = opts
    for part in name.split("."):
        obj = getattr(obj, part)
    return obj


def load_space(space: Path | str | dict, *, where: str | Path | None = None) -> list[Param]:
    """The parameters of a space file (or of a dict in the same form), validated (see the module doc)."""
    lines: dict[str, int]
    if isinstance(space, dict):
        data, lines, path = space, {}, where
    else:
        path = Path(space)
        if not path.is_file():
            raise CartoError("no such search-space file", path)
        data, lines = read_yaml(path)

    def fail(key: str, message: str) -> CartoError:
        line = lines.get(key)
        return CartoError((f"line {line}: " if line else "") + f"{key}: {message}", path)

    if not isinstance(data, dict) or not data:
        raise CartoError("a search space is a mapping of option names to {low, high[, log, int]} "
                         "or {choices: [...]}, and this one is empty", path)
    infos = {i.name: i for i in option_info()}
    flat = _flatten(data, "", infos, fail)
    params: list[Param] = []
    for name, spec in flat.items():
        info = infos[name]
        if not isinstance(spec, dict):
            raise fail(name, f"expected {{low: .., high: ..}} or {{choices: [..]}}, got {spec!r}")
        unknown = set(spec) - _SPEC_KEYS
        if unknown:
            raise fail(name, f"unknown field(s) {', '.join(sorted(map(str, unknown)))} "
                             f"(allowed: low, high, log, int, step, choices)")
        if "choices" in spec:
            if set(spec) - {"choices"}:
                raise fail(name, "give either choices or low/high, not both")
            choices = spec["choices"]
            if not isinstance(choices, list) or not choices:
                raise fail(name, f"choices must be a non-empty list, got {choices!r}")
            checked = tuple(_check_value(name, c, "choice", fail) for c in choices)
            if len(set(checked)) != len(checked):
                raise fail(name, f"choices repeat a value: {list(choices)!r}")
            params.append(Param(name, "categorical", choices=checked))
            continue
        if info.type == "bool":
            raise fail(name, "is true/false: give {choices: [false, true]}, not a range")
        if "low" not in spec or "high" not in spec:
            raise fail(name, "a range needs both low and high")
        for flag in ("log", "int"):
            if flag in spec and not isinstance(spec[flag], bool):
                raise fail(name, f"{flag} must be true or false, got {spec[flag]!r}")
        is_int = spec.get("int", info.type == "int")
        if info.type == "int" and not is_int:
            raise fail(name, "is an integer option: its range cannot have int: false")
        log = bool(spec.get("log", False))
        lo, hi = spec["low"], spec["high"]
        for what, v in (("low", lo), ("high", hi)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise fail(name, f"{what} must be a finite number, got {v!r}")
            if is_int and int(v) != v:
                raise fail(name, f"{what} must be an integer for an integer range, got {v!r}")
        if is_int:
            lo, hi = int(lo), int(hi)
        if not lo < hi:
            raise fail(name, f"low ({lo:g}) must be less than high ({hi:g})")
        if log and lo <= 0:
            raise fail(name, f"a log range needs low > 0, got {lo:g}")
        step = spec.get("step")
        if step is not None:
            if isinstance(step, bool) or not isinstance(step, (int, float)) or step <= 0:
                raise fail(name, f"step must be a positive number, got {step!r}")
            if log:
                raise fail(name, "step and log cannot be combined")
        typed = int if info.type == "int" else float
        _check_value(name, typed(lo), "low", fail)
        _check_value(name, typed(hi), "high", fail)
        params.append(Param(name, "int" if is_int else "float", lo, hi, log, step))
    return params


def suggest_params(trial, params: list[Param]) -> dict[str, Any]:
    """{option: value} drawn by an Optuna trial, typed as the options want them."""
    infos = {i.name: i for i in option_info()}
    out: dict[str, Any] = {}
    for p in params:
        if p.kind == "categorical":
            v = trial.suggest_categorical(p.name, list(p.choices))
        elif p.kind == "int":
            v = trial.suggest_int(p.name, p.low, p.high, log=p.log, step=int(p.step or 1))
        else:
            low, high = p.low, p.high
            assert low is not None and high is not None  # load_space gives every range both ends
            v = trial.suggest_float(p.name, float(low), float(high), log=p.log, step=p.step)
        if infos[p.name].type == "float" and not isinstance(v, bool):
            v = float(v)
        out[p.name] = v
    return out


def base_values(options: Options, params: list[Param]) -> dict[str, Any]:
    """The values ``options`` has for the space's parameters that lie inside the space."""
    out = {}
    for p in params:
        obj: Any = options
        for part in p.name.split("."):
            obj = getattr(obj, part)
        if p.contains(obj):
            out[p.name] = obj
    return out

