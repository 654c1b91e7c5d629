"""Fixtures shared by the whole suite, and each xdist worker's share of the cores."""

import os

import pytest
import torch

from torchcal._threads import torch_threads


def pytest_configure(config):
    """Under pytest-xdist (``make test``: two workers), each worker's torch, and the processes its tests start, use
    the worker's share of the cores: torch's default team is every core, so two workers on two cores ran four
    threads, and the small kernels of the suite waited on their slowest thread. A run without xdist keeps torch's
    default."""
    workers = getattr(config, "workerinput", {}).get("workercount")
    if not workers or "OMP_NUM_THREADS" in os.environ:  # not under xdist, or the caller chose
        return
    share = max(1, (os.cpu_count() or 1) // int(workers))
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # the CLI, scripts and docs the tests run in a fresh process
        os.environ[name] = str(share)
    torch.set_num_threads(share)


@pytest.fixture
def one_thread():
    """Run the test with one torch thread and restore the caller's after it: the calibration kernels are small, and
    on a shared machine a second thread makes them many times slower (:func:`torchcal._threads.torch_threads`).

    Use it for a whole file with ``pytestmark = pytest.mark.usefixtures("one_thread")``.
    """
    with torch_threads(1):
        yield
