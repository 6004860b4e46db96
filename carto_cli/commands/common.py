"""What several commands share: the point-cloud slice of --min-z/--max-z, the --algorithm check, and the gates'
JUnit output."""
from __future__ import annotations

from pathlib import Path

from carto_cli.core.errors import CartoError
from carto_cli.evaluation.gates import GateResult, write_junit
from carto_cli.io.recording import ReadOptions

__all__ = ["check_algorithm", "record_gates", "z_slice"]


def z_slice(min_z: float, max_z: float) -> ReadOptions:
    """How to read point clouds when slicing them to 2D between ``min_z`` and ``max_z`` (m)."""
    if min_z > max_z:
        raise CartoError(f"--min-z ({min_z}) is above --max-z ({max_z})")
    return ReadOptions(min_z=min_z, max_z=max_z)


def check_algorithm(algorithm: str) -> str:
    """``algorithm`` when it names a mapping system; else a CartoError before any recording is read."""
    # Imported here: `carto info` and `carto convert` use this module and need none of the mapping kernels.
    from carto_cli.gmapping import ALGORITHMS

    if algorithm not in ALGORITHMS:
        raise CartoError(f"--algorithm: unknown algorithm '{algorithm}' (choose from {', '.join(ALGORITHMS)})")
    return algorithm


def record_gates(gates: list[GateResult], junit: Path | None, suite: str) -> list[GateResult]:
    """Write the gates' outcome as JUnit XML when ``junit`` is given; the failed gates."""
    if junit is not None:
        write_junit(junit, suite, gates)
    return [g for g in gates if not g.passed]
