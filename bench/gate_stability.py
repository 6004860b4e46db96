#!/usr/bin/env python
"""Does `carto profile`'s speed gate cry wolf? (docs/ci.md)

Records a baseline on a recording (default: the sample in data/), then gates RUNS profiles of the same code
against it while another process keeps the other core busy (each must pass), and RUNS profiles with the
local least-squares matcher slowed by 30 % of its own CPU time (each must fail on that stage). Every profile
maps the recording --repeat times, as docs/ci.md recommends.

    python bench/gate_stability.py [--runs 20] [--repeat 3] [--max-regression 0.2] [RECORDING]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from carto_cli.commands.profile import ProfileRun, run_profile  # noqa: E402
from carto_cli.matching import least_squares  # noqa: E402
from carto_cli.pipeline import Auto, MapRequest  # noqa: E402

SLOWED = "scan/match/least squares"


def profile(recording: Path, repeat: int) -> dict:
    return run_profile(MapRequest(recording, Auto(())), repeat=repeat).report


def gate(report: dict, baseline: dict, max_regression: float):
    return ProfileRun(report, baseline).gates(max_regression)


def slowed(fraction: float):
    """least_squares.match burning ``fraction`` of its own CPU time on top."""
    original = least_squares.match

    def match(*args, **kwargs):
        t0 = time.process_time()
        out = original(*args, **kwargs)
        extra = fraction * (time.process_time() - t0)
        end = time.process_time() + extra
        while time.process_time() < end:
            pass
        return out

    return original, match


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recording", nargs="?", type=Path, default=ROOT / "data" / "ccny_laser_scan_matcher_demo.bag")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--max-regression", type=float, default=0.2)
    args = ap.parse_args()

    profile(args.recording, 1)  # kernels compiled or loaded before anything is timed
    baseline = profile(args.recording, args.repeat)
    print(f"baseline: {args.recording.name}, --repeat {args.repeat}, scan "
          f"{baseline['timing']['stages']['scan']['cpu_ms_per_scan']:.3f} CPU ms/scan", flush=True)

    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    passed, worst = 0, 0.0
    try:
        for i in range(args.runs):
            gates = gate(profile(args.recording, args.repeat), baseline, args.max_regression)
            ok = all(g.passed for g in gates)
            passed += ok
            worst = max([worst] + [g.change for g in gates])
            print(f"  busy neighbour, run {i + 1}: {'pass' if ok else 'FAIL ' + '; '.join(g.message for g in gates if not g.passed)}",
                  flush=True)
    finally:
        busy.kill()
    print(f"unchanged code, busy neighbour: {passed} of {args.runs} passed (largest stage change +{100 * worst:.0f}%)")

    original, slow = slowed(0.3)
    least_squares.match = slow
    caught = 0
    try:
        for i in range(args.runs):
            gates = gate(profile(args.recording, args.repeat), baseline, args.max_regression)
            hit = any(not g.passed and g.name == SLOWED for g in gates)
            caught += hit
            change = next((g.change for g in gates if g.name == SLOWED), float("nan"))
            print(f"  slowed by 30 %, run {i + 1}: {SLOWED} {100 * change:+.0f}% -> {'fail (caught)' if hit else 'PASS (missed)'}",
                  flush=True)
    finally:
        least_squares.match = original
    print(f"least squares 30 % slower: {caught} of {args.runs} failed the gate")
    return 0 if passed == args.runs and caught == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())
