"""`carto profile` as a library call: the whole pipeline under the StageTimer, as one report, and its gates."""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from carto_cli.core.errors import CartoError
from carto_cli.core.timing import StageTimer
from carto_cli.evaluation.gates import GateResult, compare_profiles
from carto_cli.evaluation.profiling import build_report, calibrate, merge_repeats
from carto_cli.io.atomic import write_text_atomic
from carto_cli.pipeline import Auto, MapRequest, execute, finished, planned, read_options

__all__ = ["ProfileRun", "read_baseline", "run_profile"]


@dataclass
class ProfileRun:
    report: dict  # see evaluation/profiling.py for its schema
    baseline: dict | None = None
    warnings: list[str] = field(default_factory=list)  # as `carto map` tells them: the recording's, what was dropped

    def gates(self, max_regression: float = 0.20) -> list[GateResult]:
        """Per-stage speed against the baseline (a slow-down of up to ``max_regression`` passes)."""
        if self.baseline is None:
            raise CartoError("no baseline to compare against")
        return compare_profiles(self.report, self.baseline, max_regression)


def read_baseline(path: Path) -> dict:
    """A report written by an earlier ``--output``."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise CartoError(f"cannot read baseline: {e}", path) from None


def run_profile(
    request: MapRequest,
    *,
    output: Path | None = None,
    baseline: Path | None = None,
    calibrate_first: bool = False,
    relocalize_map: Path | None = None,
    on_total: Callable[[int], None] | None = None,
    on_scan: Callable[[int], None] | None = None,
    force: bool = False,
    repeat: int = 1,
) -> ProfileRun:
    """Map as ``request`` asks (its first ``max_scans`` scans) under a StageTimer and build the report; with
    ``relocalize_map`` also time relocalizing the recording's scans in that map.carto; with ``output`` write the
    report there (an existing file only with ``force``, refused before any work). ``on_total`` hears how many
    scans will be mapped. Every stage's CPU time (the whole process's) is recorded beside its wall time; with
    ``repeat`` > 1 the recording is mapped that many times and each stage keeps its lowest CPU time and the spread
    of the repeats (what the gates compare, and their noise floor). Compare a baseline profiled with as many
    ``jobs``, since the graph's stages move to a concurrent branch of the tree with more than one."""
    if repeat < 1:
        raise CartoError(f"--repeat must be at least 1, got {repeat}")
    if relocalize_map is not None and not isinstance(request.source, (str, Path)):
        raise CartoError("profiling relocalization reads the recording again: give a recording file")
    if output is not None and Path(output).exists() and not force:
        raise CartoError("exists; --force replaces it, or give another --output", output)
    base = read_baseline(baseline) if baseline is not None else None

    def check_baseline(runs: str) -> None:
        # The two systems share no stage below 'scan': the gates would compare unrelated work.
        if base is not None and base.get("algorithm", "cartographer") != runs:
            raise CartoError(f"the baseline was profiled with {base.get('algorithm', 'cartographer')}, this run "
                             f"maps with {runs}: compare a run with a baseline of the same algorithm", baseline)

    # Known before the recording is opened unless auto is to choose it.
    known = request.system or (None if isinstance(request.options, Auto) else "cartographer")
    if known is not None:
        check_baseline(known)
    calibration = calibrate() if calibrate_first else None
    label = request.source if isinstance(request.source, (str, Path)) else request.name  # the report's recording
    runs = []
    with planned(request) as plan:
        # The records as `carto map` reads them (io.read_ahead); each repeat is a pass of its own.
        check_baseline(plan.configured.algorithm)
        total = plan.scan_count
        if on_total is not None:
            on_total(repeat * min(total, request.max_scans or total))
        for _ in range(repeat):
            timer = StageTimer(cpu_clock=time.process_time_ns)
            # The map's last steps too (turned square, cleaned): `carto map` pays for them
            result = finished(execute(plan, timer=timer, on_scan=on_scan), request, timer)
            timer.stop()
            runs.append(build_report(result, timer, result.configured.options, label, calibration))
    report = merge_repeats(runs)
    if result.auto is not None and result.regime is not None:
        report["auto"] = {"detected": result.regime.describe(), "profile": result.auto.profile,
                          "settings": result.auto.settings, "algorithm": result.auto.algorithm,
                          "note": result.auto.note}
    if relocalize_map is not None:
        from carto_cli.evaluation.profiling import profile_relocalization
        from carto_cli.io.map_file import load_map
        from carto_cli.io.sources.open import open_recording

        assert isinstance(request.source, (str, Path))  # checked before mapping
        with open_recording(request.source, read_options(request.options)) as rec:
            report["relocalization"] = profile_relocalization(load_map(relocalize_map), rec,
                                                              scan_topic=request.topics.scan)
    if output is not None:
        write_text_atomic(output, json.dumps(report, indent=2) + "\n")
    return ProfileRun(report, base, list(result.warnings))  # every repeat reads the same records
