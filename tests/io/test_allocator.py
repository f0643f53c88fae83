"""Within ``io.allocator.freed_memory_kept`` glibc keeps freed memory for the next large block: a
block freed and asked for again comes back without the kernel faulting (and zeroing) its pages in
again; after the block, glibc maps large blocks afresh as before."""

import subprocess
import sys

import pytest

PROBE = """
import resource
import numpy as np
from ntp_engine.io.allocator import freed_memory_kept

def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

def again():  # an 80 MB block, every page touched, freed, then asked for again: its faults
    a = np.ones(10_000_000)
    del a
    before = faults()
    b = np.ones(10_000_000)
    return faults() - before

fresh = again()
with freed_memory_kept() as kept:
    inside = again()
print(kept, fresh, inside, again())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_large_block_freed_is_reused_within_the_block_only():
    run = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True)
    kept, fresh, inside, after = run.stdout.split()
    assert kept == "True"
    assert int(fresh) > 100 and int(inside) < 10 and int(after) > 100, run.stdout  # measured 625, 0, 625
