"""Torch's CPU thread count, set for a block and restored after it."""

from __future__ import annotations

import contextlib


@contextlib.contextmanager
def torch_threads(n: int):
    """Run the block with ``n`` torch threads (at least 1), then restore the previous number.

    The filters and the many small least-squares kernels gain nothing from a second thread: a call's work is too
    small to share, so the threads only add synchronisation, and where several processes share a few cores their
    thread teams contend for the same cores and every call waits for its slowest thread.
    """
    import torch  # here: the command line's modules import this one, and `torchcal --help` needs no torch

    before = torch.get_num_threads()
    torch.set_num_threads(max(1, n))
    try:
        yield
    finally:
        torch.set_num_threads(before)
