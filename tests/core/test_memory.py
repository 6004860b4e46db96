"""carto_cli.core.memory: free heap pages handed back to the system."""
import platform

import numpy as np
import pytest

from carto_cli.core.memory import give_back


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc_trim")
def test_freed_blocks_leave_the_process():
    """Blocks freed in the middle of the heap (small live arrays between them, glibc's mapping threshold raised
    past their size) stay with the process, 120 MB of them, until given back."""
    keep = [np.ones(4 << 20, np.uint8)]  # one mapped block freed raises the threshold past the blocks' size
    keep.clear()
    blocks, pins = [], []
    for _ in range(40):
        blocks.append(np.ones(3 << 20, np.uint8))
        pins.append(np.ones(2000))  # stays: the blocks are not at the top of the heap, free() cannot trim them
    before = _rss_mb()
    blocks.clear()
    assert _rss_mb() > before - 30  # freed, but still the process's
    assert give_back()
    assert _rss_mb() < before - 90
    assert len(pins) == 40
