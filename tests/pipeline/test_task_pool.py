"""Where work runs: in this process or as Ray tasks on a local Ray instance (no mocks)."""

import operator
import subprocess
import sys

import pytest
from ray_tasks import kill_task_once, napping, times

from ntp_engine.io.errors import NtpInputError
from ntp_engine.pipeline.task_pool import LocalPool, RayPool
from ntp_engine.scanner.scan_folder import load_scan


def test_local_pool_runs_every_item_in_order_with_the_shared_arguments():
    with LocalPool() as pool:
        assert list(pool.map(operator.pow, [2, 3, 4], shared=(2,))) == [(0, 4), (1, 9), (2, 16)]


def test_ray_pool_returns_every_result_by_index_and_a_functions_error_as_itself(ray_local, tmp_path):
    with RayPool() as pool:
        got = dict(pool.map(times, range(25), shared=(3,)))
    assert got == {i: 3 * i for i in range(25)}
    with RayPool() as pool, pytest.raises(NtpInputError, match="no scan.toml"):
        list(pool.map(load_scan, [tmp_path]))
    assert ray_local.is_initialized()  # a connection the pool did not make is left open


def test_ray_pool_retries_a_task_whose_worker_is_killed(ray_local):
    killed = kill_task_once("napping")
    with RayPool() as pool:
        ((i, pid),) = pool.map(napping, [1.5])
    assert killed, "no worker was killed: the test did not test anything"
    assert i == 0 and pid != killed[0]  # finished by another worker


@pytest.mark.parametrize(
    "address, problem",
    [("127.0.0.1:1", "cannot reach the Ray cluster"), ("nohost", "expected HOST:PORT"), ("ray://h:x", "expected")],
)
def test_an_unreachable_or_malformed_address_is_one_line_before_any_work(address, problem):
    with pytest.raises(NtpInputError, match=problem):
        RayPool(address)


def test_nothing_imports_ray_without_ray():
    code = "import sys, ntp_engine.cli, ntp_engine.pipeline.collection; print('ray' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"
