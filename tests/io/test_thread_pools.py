import numba
import numpy as np
import torch
from threadpoolctl import threadpool_info

from ntp_engine.io.thread_pools import numba_threads_as_torch, single_threaded_blas


def _numpy_blas_threads() -> int:
    (lib,) = [i for i in threadpool_info() if i["internal_api"] == "openblas" and "numpy" in i["filepath"]]
    return lib["num_threads"]


def test_openblas_runs_on_one_thread_inside_the_block_and_as_before_after_it():
    np.linalg.solve(np.eye(3), np.ones(3))  # numpy's OpenBLAS is loaded
    before, torch_before = _numpy_blas_threads(), torch.get_num_threads()
    with single_threaded_blas():
        assert _numpy_blas_threads() == 1
        assert torch.get_num_threads() == torch_before  # torch's pool is not OpenBLAS
    assert _numpy_blas_threads() == before


def test_numba_loops_follow_torchs_thread_count_and_restore_it():
    before, torch_before = numba.get_num_threads(), torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with numba_threads_as_torch():
            assert numba.get_num_threads() == 1
        assert numba.get_num_threads() == before
    finally:
        torch.set_num_threads(torch_before)
