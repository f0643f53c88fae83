"""glibc keeps freed memory for the next large block (``io.allocator``): a block freed and asked
for again comes back without the kernel faulting (and zeroing) its pages in again."""

import subprocess
import sys

import pytest

PROBE = """
import resource, sys
import numpy as np
from ntp_engine.io.allocator import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = np.ones(10_000_000)  # 80 MB, every page touched
del a
before = faults()
b = np.ones(10_000_000)
print(faults() - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_large_block_freed_is_reused_without_faulting_its_pages_in_again():
    def faults(mode: str) -> int:
        run = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
        return int(run.stdout.split()[-1])

    fresh, kept = faults("fresh"), faults("keep")
    assert fresh > 100 and kept < 10, (fresh, kept)  # measured 625 and 0
