"""Torch's CPU thread count, set for a block and restored after it."""

from __future__ import annotations

import contextlib

import torch


@contextlib.contextmanager
def torch_threads(n: int):
    """Run the block with ``n`` torch threads (at least 1), then restore the previous number.

    The filters and the many small least-squares kernels gain nothing from a second thread, and on a shared
    2-core machine two threads per process are many times slower (measured: 190 s instead of 17 s for one
    integrated calibration).
    """
    before = torch.get_num_threads()
    torch.set_num_threads(max(1, n))
    try:
        yield
    finally:
        torch.set_num_threads(before)
