"""Trajectory files: TUM (``t x y z qx qy qz qw``) and plain ``t x y theta``.

Reading autodetects the format by the number of columns (8 or 4); '#' starts a
comment, blank lines are skipped, and commas count as separators (TUM exports
from spreadsheets use them). Times must increase strictly: evaluation interpolates
between poses, and a step back in time is always a bug in whatever wrote the file.
A 3D pose is reduced to its yaw.

Writing goes through ``carto_cli.io.atomic`` (a sibling temporary, then
``os.replace``), so a crash never leaves a half-written trajectory where a good one was.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.core.transform import wrap_angle
from carto_cli.io.atomic import atomic_output

__all__ = ["TRAJECTORY_FORMATS", "Trajectory", "parse_table", "read_trajectory", "write_trajectory"]

TRAJECTORY_FORMATS = ("tum", "xyt")
_COLUMNS = {8: "tum", 4: "xyt"}


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Planar poses at strictly increasing times: ``t`` (n,), ``xy`` (n, 2), ``theta`` (n,) radians."""

    t: np.ndarray
    xy: np.ndarray
    theta: np.ndarray

    def __post_init__(self):
        n = self.t.shape[0]
        if self.t.shape != (n,) or self.xy.shape != (n, 2) or self.theta.shape != (n,):
            raise ValueError(f"inconsistent trajectory shapes {self.t.shape} {self.xy.shape} {self.theta.shape}")

    @classmethod
    def from_arrays(cls, t, x, y, theta) -> Trajectory:
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        xy = np.stack([np.asarray(x, np.float64).reshape(-1), np.asarray(y, np.float64).reshape(-1)], axis=1)
        return cls(t, xy, np.asarray(theta, dtype=np.float64).reshape(-1))

    @classmethod
    def from_poses(cls, t, poses) -> Trajectory:
        """From times and an (n, 3) array of ``x y theta``."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        return cls(np.asarray(t, dtype=np.float64).reshape(-1), poses[:, :2].copy(), poses[:, 2].copy())

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def poses(self) -> np.ndarray:
        """(n, 3) ``x y theta``."""
        return np.column_stack([self.xy, self.theta])

    @property
    def span(self) -> tuple[float, float]:
        return (float(self.t[0]), float(self.t[-1])) if len(self) else (math.nan, math.nan)


def parse_table(path: str | Path, allowed_columns: tuple[int, ...], what: str) -> tuple[np.ndarray, list[int]]:
    """Rows of numbers from a whitespace (or comma) separated text file.

    Returns the (n, k) float64 array and the 1-based line number of each row. Every
    data row must have the same column count, one of ``allowed_columns``; values
    must be finite. Errors name the file and the line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CartoError(f"no such {what} file", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise CartoError(f"cannot read {what}: {e}", path) from None
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    ncols = None
    for number, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].replace(",", " ").split()
        if not body:
            continue
        if ncols is None:
            if len(body) not in allowed_columns:
                expected = " or ".join(str(c) for c in allowed_columns)
                raise FormatError(f"line {number}: expected {expected} columns in a {what} file, got {len(body)}",
                                  path)
            ncols = len(body)
        elif len(body) != ncols:
            raise FormatError(f"line {number}: expected {ncols} columns like the lines before, got {len(body)}",
                              path)
        rows.append(body)
        line_numbers.append(number)
    if not rows:
        raise FormatError(f"no data: the {what} file is empty or only comments", path)
    try:
        data = np.array(rows, dtype=np.float64)
    except ValueError:
        for body, number in zip(rows, line_numbers):
            for token in body:
                try:
                    float(token)
                except ValueError:
                    raise FormatError(f"line {number}: not a number: {token!r}", path) from None
        raise  # pragma: no cover - numpy and float() agree on what a number is
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        raise FormatError(f"line {line_numbers[int(np.argmax(bad))]}: values must be finite", path)
    return data, line_numbers


def _yaw_from_quaternion(qx, qy, qz, qw) -> np.ndarray:
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def read_trajectory(path: str | Path) -> Trajectory:
    """A TUM or ``t x y theta`` file (autodetected by its column count)."""
    path = Path(path)
    data, lines = parse_table(path, (8, 4), "trajectory")
    t = data[:, 0]
    steps = np.diff(t)
    if steps.size and (steps <= 0).any():
        i = int(np.argmax(steps <= 0)) + 1
        raise FormatError(f"line {lines[i]}: time {t[i]:.9f} does not come after {t[i - 1]:.9f} "
                          "(times must increase strictly)", path)
    if data.shape[1] == 8:
        q = data[:, 4:8]
        norm = np.linalg.norm(q, axis=1)
        if (norm < 1e-9).any():
            raise FormatError(f"line {lines[int(np.argmax(norm < 1e-9))]}: zero quaternion", path)
        q = q / norm[:, None]
        theta = _yaw_from_quaternion(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    else:
        theta = data[:, 3]
    return Trajectory(t.copy(), data[:, 1:3].copy(), np.asarray(theta, dtype=np.float64).copy())


def _format_rows(traj: Trajectory, fmt: str) -> str:
    t, x, y, th = traj.t, traj.xy[:, 0], traj.xy[:, 1], traj.theta
    cols: tuple[np.ndarray, ...]
    if fmt == "tum":
        header = "# t x y z qx qy qz qw\n"
        half = 0.5 * th
        cols = (t, x, y, np.zeros_like(t), np.zeros_like(t), np.zeros_like(t), np.sin(half), np.cos(half))
        pattern = "%.9f %.6f %.6f %.1f %.1f %.1f %.12f %.12f\n"
    else:
        header = "# t x y theta\n"
        cols = (t, x, y, wrap_angle(th))
        pattern = "%.9f %.6f %.6f %.12f\n"
    table = np.column_stack(cols)
    return header + "".join(pattern % tuple(row) for row in table.tolist())


def write_trajectory(path: str | Path, traj: Trajectory, fmt: str = "tum") -> Path:
    """Write ``traj`` as 'tum' (z = 0, yaw-only quaternion) or 'xyt' (``t x y theta``), atomically.

    Missing parent directories are created, as for every carto output.
    """
    if fmt not in TRAJECTORY_FORMATS:
        raise CartoError(f"unknown trajectory format '{fmt}' (choose {' or '.join(TRAJECTORY_FORMATS)})")
    path = Path(path)
    text = _format_rows(traj, fmt)
    try:
        with atomic_output(path) as tmp:
            tmp.write_text(text, encoding="utf-8")
            # mkstemp creates 0600; a trajectory is an ordinary, shareable output file.
            umask = os.umask(0)
            os.umask(umask)
            tmp.chmod(0o666 & ~umask)
    except OSError as e:
        raise CartoError(f"cannot write trajectory: {e.strerror or e}", path) from None
    return path
