"""Quantities people type (on the command line, in query files): numbers, angles, poses.

Angles are radians unless suffixed ``deg``; every error is a one-line CartoError naming what was wrong.
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable

from carto_cli.core.errors import CartoError

__all__ = ["NUMBER", "angle", "number", "pose"]

NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_ANGLE = re.compile(rf"^({NUMBER})(deg)?$")

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
