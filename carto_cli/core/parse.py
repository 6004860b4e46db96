"""Quantities people type (on the command line, in query files): numbers, angles, poses.

Angles are radians unless suffixed ``deg``; every error is a one-line CartoError naming what was wrong.
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable

from carto_cli.core.errors import CartoError

__all__ = ["NUMBER", "angle", "height_band", "megabytes", "number", "pose"]

NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_ANGLE = re.compile(rf"^({NUMBER})(deg)?$")
_SIZE = re.compile(rf"^({NUMBER})\s*(b|kb|k|mb|m|gb|g|kib|mib|gib)?$")
_SIZE_MB = {None: 1.0, "b": 2.0**-20, "k": 2.0**-10, "kb": 2.0**-10, "kib": 2.0**-10, "m": 1.0, "mb": 1.0,
            "mib": 1.0, "g": 1024.0, "gb": 1024.0, "gib": 1024.0}

Fail = Callable[[str], CartoError]


def number(text: str, what: str, fail: Fail) -> float:
    try:
        v = float(text)
    except ValueError:
        raise fail(f"{what} must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise fail(f"{what} must be finite, got {text!r}")
    return v


def angle(text: str, what: str, fail: Fail) -> float:
    m = _ANGLE.match(text.strip().lower())
    if not m:
        raise fail(f"{what} must be a number of radians (or degrees with a 'deg' suffix), got {text!r}")
    v = float(m.group(1))
    return math.radians(v) if m.group(2) else v


def megabytes(text: str, what: str) -> float:
    """A memory size ('512', '512MB', '1.5GB'; plain numbers are MB; K/M/G are powers of 1024) in MB."""
    m = _SIZE.match(text.strip().lower())
    if not m or float(m.group(1)) <= 0:
        raise CartoError(f"{what} must be a positive size such as 512MB or 1GB, got {text!r}")
    return float(m.group(1)) * _SIZE_MB[m.group(2)]


def laser_poses(texts: list[str], what: str
                ) -> tuple[float, float, float] | dict[str, tuple[float, float, float]]:
    """``--laser-pose`` as given: one 'x,y,yaw' (the one laser), or 'TOPIC=x,y,yaw' for each of several lasers."""
    named = [t for t in texts if "=" in t]
    if not named:
        if len(texts) > 1:
            raise CartoError(f"{what}: several poses need their lasers' topics, as TOPIC=x,y,yaw")
        return pose(texts[0], what)
    if len(named) != len(texts):
        raise CartoError(f"{what}: give every laser's pose as TOPIC=x,y,yaw, or one pose without a topic")
    out: dict[str, tuple[float, float, float]] = {}
    for text in named:
        topic, _, value = text.partition("=")
        topic = topic.strip()
        if not topic or topic in out:
            raise CartoError(f"{what}: {'a topic is missing' if not topic else f'{topic} given twice'} in {text!r}")
        out[topic] = pose(value, f"{what} {topic}")
    return out


def pose(text: str, what: str) -> tuple[float, float, float]:
    """'x,y,yaw' (commas and/or spaces; yaw in radians, or degrees with a 'deg' suffix) -> (x, y, yaw).

    ``what`` names the option in errors (``--initial-pose``, ``--laser-pose``).
    """
    def fail(msg: str) -> CartoError:
        return CartoError(f"{what}: {msg}")
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    if len(parts) != 3:
        raise fail(f"expected x,y,yaw, got {text!r}")
    return (number(parts[0], "x", fail), number(parts[1], "y", fail), angle(parts[2], "yaw", fail))


def height_band(text: str) -> tuple[float, float] | None:
    """A point cloud's band (trajectory_builder_2d.cloud_band): 'auto' -> None, 'LOW..HIGH' (m above the floor) ->
    (LOW, HIGH); anything else a ValueError saying what is expected. ('sensor' is the caller's to handle.)"""
    text = text.strip().lower()
    if text == "auto":
        return None
    lo, sep, hi = text.partition("..")
    try:
        low, high = float(lo), float(hi)
    except ValueError:
        low = high = math.nan
    if not sep or not (math.isfinite(low) and math.isfinite(high)) or low >= high:
        raise ValueError(f"{text!r} is neither 'auto', 'sensor' nor a band LOW..HIGH in metres above the floor "
                         "with LOW below HIGH")
    return low, high
