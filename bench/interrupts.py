#!/usr/bin/env python
"""Ctrl-C and SIGTERM at random moments of `carto map` on the real logs: each must end as an interrupt.

For each log (a key-scan log, which auto maps with GMapping; a dense one, mapped with Cartographer), MOMENTS runs
of `carto map LOG -o DIR` (every core, the graph's and the reader's processes included) are each sent one signal
at a random moment between --from and --until seconds after the start (the warm-up, the survey, mapping):
SIGINT and SIGTERM in turn, to the process (`kill`) or to its process group (a terminal's Ctrl-C, `timeout`) in
turn. A run passes when it exits 130 with 'carto: interrupted' as its last line on stderr, no traceback and no
'internal error'; left no output directory or only a whole output set (never a staging directory or a temporary
file); and no process of its group outlived it. docs/ci.md has the last figures (issue 42, item 2).

    python bench/interrupts.py [--moments 10] [--seed 0] [--key LOG] [--dense LOG]
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
OUTPUTS = ["map.carto", "map.pgm", "map.png", "map.yaml", "summary.json", "trajectory.tum"]


def interrupted_map(recording: Path, outdir: Path, sig: signal.Signals, to_group: bool, at: float):
    """One run signalled ``at`` s after its start: (exit status, stderr, processes left), or None if the map was
    done first."""
    # SIGINT as at a terminal: started in the background by a shell without job control, this script and its
    # children have it ignored, and carto keeps an ignored SIGINT ignored (as nohup intends).
    p = subprocess.Popen([sys.executable, "-m", "carto_cli", "map", str(recording), "-o", str(outdir)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        p.wait(timeout=at)
        p.communicate()
        return None
    except subprocess.TimeoutExpired:
        pass
    (os.killpg if to_group else os.kill)(p.pid, sig)
    _, stderr = p.communicate(timeout=600)
    deadline = time.monotonic() + 10.0  # a child killed by its parent's death (PR_SET_PDEATHSIG) takes a moment
    left = True
    while left and time.monotonic() < deadline:
        try:
            os.killpg(p.pid, 0)
            time.sleep(0.1)
        except ProcessLookupError:
            left = False
    if left:
        os.killpg(p.pid, signal.SIGKILL)
    return p.returncode, stderr, left


def verdict(status: int, stderr: str, left: bool, outdir: Path) -> str:
    """'' for a clean interrupt, else what was wrong."""
    lines = stderr.strip().splitlines()
    wrong = []
    if status != 130:
        wrong.append(f"exit {status}")
    if not lines or lines[-1] != "carto: interrupted":
        wrong.append(f"last line {lines[-1] if lines else ''!r}")
    if "Traceback" in stderr or "internal error" in stderr:
        wrong.append("traceback or internal error")
    written = sorted(p.name for p in outdir.iterdir()) if outdir.exists() else []
    if written not in ([], OUTPUTS):
        wrong.append(f"outputs {written}")
    if left:
        wrong.append("a process of its group outlived it")
    return "; ".join(wrong)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--moments", type=int, default=10, help="Signals per log (default 10).")
    ap.add_argument("--seed", type=int, default=None, help="Seed of the moments (default: a random one, printed).")
    ap.add_argument("--key", type=Path, default=DATA / "bench" / "intel" / "scans.clf.gz",
                    help="Key-scan log (GMapping under auto).")
    ap.add_argument("--dense", type=Path, default=DATA / "bench-dense" / "aces" / "scans.clf.gz",
                    help="Dense log (Cartographer under auto).")
    ap.add_argument("--key-window", type=float, nargs=2, default=(2.0, 60.0), metavar=("FROM", "UNTIL"),
                    help="Seconds after the start the key-scan log's moments are drawn from (intel: the survey "
                         "ends at about 16 s, mapping takes 4 min).")
    ap.add_argument("--dense-window", type=float, nargs=2, default=(2.0, 9.0), metavar=("FROM", "UNTIL"),
                    help="The same for the dense log (aces: the survey ends at about 2-5 s, mapping ~10 s).")
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(10**6)
    rng = random.Random(seed)
    commit = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    print(f"commit {commit}, seed {seed}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}", flush=True)
    passed = total = 0
    with tempfile.TemporaryDirectory(prefix="carto-interrupts-") as scratch:
        for log, (start, end) in ((args.key, args.key_window), (args.dense, args.dense_window)):
            for k in range(args.moments):
                sig = (signal.SIGINT, signal.SIGTERM)[k % 2]
                to_group = (k // 2) % 2 == 1
                outcome, at, outdir = None, 0.0, Path(scratch)
                for attempt in range(5):  # the map done before the moment: another one, earlier
                    at = rng.uniform(start, start + (end - start) / 2 ** attempt)
                    outdir = Path(scratch) / f"{log.parent.name}-{k}-{attempt}"
                    outcome = interrupted_map(log, outdir, sig, to_group, at)
                    if outcome is not None:
                        break
                total += 1
                if outcome is None:
                    print(f"{log.parent.name:8} {sig.name:7} mapped before every moment drawn", flush=True)
                    continue
                status, stderr, left = outcome
                wrong = verdict(status, stderr, left, outdir)
                passed += not wrong
                target = "group" if to_group else "process"
                print(f"{log.parent.name:8} {sig.name:7} to the {target:7} at {at:5.1f} s: "
                      f"{wrong or 'exit 130, interrupted'}", flush=True)
    print(f"{passed} of {total} ended as interrupts (commit {commit}, seed {seed})")
    return 0 if passed == total else 1


if __name__ == "__main__":
    sys.exit(main())
