"""What several commands share: the point-cloud slice of --min-z/--max-z, the --algorithm check, the gates'
JUnit output and the note on compiling kernels."""
from __future__ import annotations

from pathlib import Path

from carto_cli.core.errors import CartoError
from carto_cli.evaluation.gates import GateResult, write_junit
from carto_cli.io.recording import ReadOptions

__all__ = ["COMPILE_NOTE_MIN_S", "check_algorithm", "compiling_note", "record_gates", "z_slice"]

COMPILE_NOTE_MIN_S = 1.0  # below this, compiling kernels is not worth a mention


def z_slice(min_z: float | None, max_z: float | None) -> ReadOptions:
    """How to read point clouds: sliced to 2D between ``min_z`` and ``max_z`` (m, sensor frame) when either is
    given, else in the band ``auto`` chooses above the floor."""
    if min_z is None and max_z is None:
        return ReadOptions()
    low = ReadOptions.min_z if min_z is None else min_z
    high = ReadOptions.max_z if max_z is None else max_z
    if low > high:
        raise CartoError(f"--min-z ({low}) is above --max-z ({high})")
    return ReadOptions(min_z=low, max_z=high, cloud_band="sensor")


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


def compiling_note(seconds: float) -> str:
    """' (incl. N s compiling kernels: ...)' after a figure that includes ``seconds`` of compiling, when they are
    worth a mention (the first run after installing), else ''. The same words for every command."""
    if seconds > COMPILE_NOTE_MIN_S:
        return f" (incl. {seconds:.0f} s compiling kernels: later runs load them from the cache)"
    return ""
