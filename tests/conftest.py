"""Fixtures shared by the whole suite."""

import pytest

from torchcal._threads import torch_threads


@pytest.fixture
def one_thread():
    """Run the test with one torch thread and restore the caller's after it: the calibration kernels are small, and
    on a shared machine a second thread makes them many times slower (:func:`torchcal._threads.torch_threads`).

    Use it for a whole file with ``pytestmark = pytest.mark.usefixtures("one_thread")``.
    """
    with torch_threads(1):
        yield
