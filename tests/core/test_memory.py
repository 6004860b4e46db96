"""carto_cli.core.memory: free heap pages handed back to the system, and the peak resident memory."""
import platform
import subprocess
import sys

import pytest

# Run in a fresh interpreter: whether free() itself trims depends on the heap's layout, which the tests before
# this one shape. Here 120 MB of blocks are freed in the middle of the heap (small live arrays between them,
# glibc's mapping threshold raised past their size by one larger block freed first).
SCENARIO = """
import sys
import numpy as np
from carto_cli.core.memory import give_back

def rss():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024

keep = [np.ones(4 << 20, np.uint8)]
keep.clear()
blocks, pins = [], []
for _ in range(40):
    blocks.append(np.ones(3 << 20, np.uint8))
    pins.append(np.ones(2000))
before = rss()
blocks.clear()
freed = rss()
trimmed = give_back() if sys.argv[1] == "give_back" else False
print(before - freed, before - rss(), trimmed)
"""


def _run(mode: str) -> tuple[float, float, bool]:
    out = subprocess.run([sys.executable, "-c", SCENARIO, mode], capture_output=True, text=True, check=True)
    kept, dropped, trimmed = out.stdout.split()
    return float(kept), float(dropped), trimmed == "True"


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc_trim")
def test_freed_blocks_leave_the_process():
    freed_alone, after, trimmed = _run("free only")
    assert freed_alone < 30 and after < 30 and not trimmed  # freed, but still the process's
    freed, after, trimmed = _run("give_back")
    assert freed < 30 and trimmed and after > 90  # handed back


PEAKS = """
import numpy as np
from carto_cli.core.memory import peak_kb, peak_rss_mb, reset_peak

block = np.ones(200 << 20, np.uint8)
del block
print(peak_kb() / 1024, peak_rss_mb(), reset_peak(), peak_kb() / 1024, peak_rss_mb())
"""


@pytest.mark.skipif(platform.system() != "Linux", reason="/proc/self/status and clear_refs")
def test_both_peaks_count_a_freed_block_until_reset_peak_starts_them_afresh():
    # Started by a process holding 300 MB, whose footprint Linux's ru_maxrss would count as this one's own.
    starter = ("import subprocess, sys, numpy as np; held = np.ones(300 << 20, np.uint8); "
               f"subprocess.run([sys.executable, '-c', {PEAKS!r}], check=True)")
    out = subprocess.run([sys.executable, "-c", starter], capture_output=True, text=True, check=True)
    high, high_rss, reset, after, after_rss = out.stdout.split()
    assert float(high) > 200 and float(high_rss) > 200  # the 200 MB block counted, freed or not
    assert float(high) < 290 and float(high_rss) < 290  # the starter's 300 MB did not
    assert reset == "True" and float(after) < 100 and float(after_rss) < 100  # afresh: it no longer counts
