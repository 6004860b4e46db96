"""Regression gates for CI: per-stage speed against a baseline, accuracy against limits, JUnit XML.

Speed is compared per scan (ms/scan) for stages inside scans and as totals for
the rest, on CPU time where both reports measured it (wall time otherwise). A stage
fails when it is slower than the baseline by more than ``max_regression`` plus the
spread the repeated runs of either report showed (``profile --repeat``), *and* by
more than a noise floor, so that sub-millisecond stages do not flap. With calibration in both reports, the
current times are first scaled by ``baseline_calibration / current_calibration``:
a machine twice as slow on the reference kernel is expected to be twice as slow
everywhere.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree as ET

from carto_cli.core import kernels
from carto_cli.core.errors import CartoError
from carto_cli.io.atomic import write_text_atomic

NOISE_FLOOR_MS_PER_SCAN = 0.05
NOISE_FLOOR_MS_TOTAL = 20.0
# One-off work whose time depends on the numba cache, not on the code under test.
UNGATED = {kernels.STAGE}


@dataclass(frozen=True)
class GateResult:
    name: str
    unit: str
    baseline: float
    current: float
    limit: float
    passed: bool
    message: str = ""

    @property
    def change(self) -> float:
        return (self.current - self.baseline) / self.baseline if self.baseline > 0 else 0.0


def calibration_scale(report: dict, baseline: dict) -> float:
    """Factor that brings the current machine's times onto the baseline machine's scale (1 without calibration)."""
    cur, base = report.get("calibration"), baseline.get("calibration")
    if not cur or not base:
        return 1.0
    if cur.get("kernel") != base.get("kernel"):
        raise CartoError(f"calibration kernels differ ({cur.get('kernel')} vs {base.get('kernel')}); "
                         "re-record the baseline with this carto")
    return float(base["ms"]) / float(cur["ms"])


def compare_profiles(report: dict, baseline: dict, max_regression: float = 0.20,
                     noise_floor_ms_per_scan: float = NOISE_FLOOR_MS_PER_SCAN,
                     noise_floor_ms_total: float = NOISE_FLOOR_MS_TOTAL) -> list[GateResult]:
    if baseline.get("schema") != "carto.profile":
        raise CartoError("baseline is not a carto profile report (schema 'carto.profile')")
    scale = calibration_scale(report, baseline)
    base_stages = baseline["timing"]["stages"]
    results = []
    for path, cur in report["timing"]["stages"].items():
        base = base_stages.get(path)
        if base is None or path.split("/")[-1] in UNGATED or path in UNGATED:
            continue
        # CPU time where both runs measured it: a job on another core barely changes it, the wall clock it
        # does (a baseline from the same code failed 5 runs in 5 on wall time with a neighbour job)
        cpu = "cpu_ms" in cur and "cpu_ms" in base
        per_scan, whole = ("cpu_ms_per_scan", "cpu_ms") if cpu else ("ms_per_scan", "total_ms")
        kind = "CPU " if cpu else ""
        if cur.get("in_scan") and cur.get(per_scan) is not None and base.get(per_scan) is not None:
            b, c, unit, floor = base[per_scan], cur[per_scan] * scale, f"{kind}ms/scan", noise_floor_ms_per_scan
        elif path == "total":
            continue  # the wall clock includes reading the file and compiling; gated through 'scan' instead
        else:
            b, c, unit, floor = base[whole], cur[whole] * scale, f"{kind}ms", noise_floor_ms_total
        # The noise the repeats showed, in either run, widens the allowance (merge_repeats)
        noise = max(base.get("cpu_spread", 0.0), cur.get("cpu_spread", 0.0)) if cpu else 0.0
        limit = b * (1.0 + max_regression + noise)
        passed = not (c > limit and c - b > floor)
        msg = "" if passed else (f"{path}: {b:.3f} -> {c:.3f} {unit} "
                                 f"(+{100 * (c - b) / b:.0f}%, limit +{100 * (max_regression + noise):.0f}%)")
        results.append(GateResult(path, unit, b, c, limit, passed, msg))
    return results


def accuracy_gates(evaluation_json: dict, max_trans_error: float | None,
                   max_rot_error_deg: float | None) -> list[GateResult]:
    """Gate the mean relation error, else the ATE RMSE, of a `carto eval` result."""
    results = []
    source = None
    for key in ("relations", "ate"):
        if evaluation_json.get(key):
            source = key
            break
    if source is None:
        raise CartoError("nothing to gate: the evaluation has no relation or ATE result")
    block = evaluation_json[source]
    stat = "mean" if source == "relations" else "rmse"
    for limit, part, unit in ((max_trans_error, "translation_m", "m"), (max_rot_error_deg, "rotation_deg", "deg")):
        if limit is None:
            continue
        value = float(block[part][stat])
        passed = value <= limit
        msg = "" if passed else f"{source} {part} {stat} {value:.4f} {unit} exceeds {limit:g} {unit}"
        results.append(GateResult(f"{source}/{part}/{stat}", unit, limit, value, limit, passed, msg))
    return results


def write_junit(path: str | Path, suite: str, results: list[GateResult]) -> Path:
    failures = sum(not r.passed for r in results)
    root = ET.Element("testsuites", name="carto", tests=str(len(results)), failures=str(failures))
    ts = ET.SubElement(root, "testsuite", name=suite, tests=str(len(results)), failures=str(failures), errors="0")
    for r in results:
        case = ET.SubElement(ts, "testcase", classname=suite, name=r.name)
        ET.SubElement(case, "system-out").text = (
            f"baseline/limit {r.baseline:.6g} {r.unit}, current {r.current:.6g} {r.unit}")
        if not r.passed:
            failure = ET.SubElement(case, "failure", message=r.message, type="regression")
            failure.text = r.message
    text = ET.tostring(root, encoding="unicode")
    write_text_atomic(path, '<?xml version="1.0" encoding="UTF-8"?>\n' + text + "\n")
    return Path(path)
