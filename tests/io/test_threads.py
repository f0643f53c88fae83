"""The thread setting: torch's and COLMAP's counts from one place; 0 leaves every core."""

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
