"""Shared fixtures of the filter tests."""

import pytest

from torchcal._threads import torch_threads


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread: the filters are thousands of tiny kernels, and two threads sharing two busy cores make
    them many times slower (see :func:`torchcal._threads.torch_threads`)."""
    with torch_threads(1):
        yield
