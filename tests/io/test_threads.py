"""The thread setting: torch's and COLMAP's counts from one place; 0 leaves every core."""

import subprocess
import sys

import pytest
import torch

from ntp_engine.io import threads
from ntp_engine.io.errors import NtpInputError


def test_threads_reach_torch_and_colmap_and_refuse_a_negative_count():
    try:
        threads.set_threads(1)
        assert torch.get_num_threads() == 1 and threads.colmap_threads() == 1
        threads.set_threads(0)  # every core: COLMAP's own default (-1), torch's own choice again
        assert threads.colmap_threads() == -1 and torch.get_num_threads() == threads._TORCH_DEFAULT
        with pytest.raises(NtpInputError, match="--threads -2: need 0"):
            threads.set_threads(-2)
        assert threads.colmap_threads() == -1
    finally:
        threads.set_threads(0)


def test_one_thread_holds_for_torch_and_numba_after_numbas_first_parallel_loop():
    """A fresh process (as ``ntp reconstruct --threads 1`` is, or a Ray task): the setting made
    before numba's threading layer starts still holds after its first parallel loop — the layer's
    OpenMP start set the thread's OpenMP count, torch's included, back to every core."""
    code = (
        "import numba, torch\n"
        "from ntp_engine.io.threads import set_threads\n"
        "from ntp_engine.io.thread_pools import numba_threads_as_torch\n"
        "set_threads(1)\n"
        "with numba_threads_as_torch():\n"
        "    inner = numba.get_num_threads()\n"
        "print(torch.get_num_threads(), inner)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "1"], out.stdout + out.stderr
