#!/usr/bin/env python3
"""Speed of one integrated ANN-EKF pass: the fast path against a per-step autograd baseline, a user's own
``nn.Module`` of the same size, and (``--load``) the fast path beside a busy process
(experiments.bench_ekf); prints a summary to stderr and the result as JSON (``--json``: one line).

    python scripts/bench_ekf.py [--samples 7342] [--device cpu|cuda] [--threads 1] [--load] [--no-baseline]
        [--repeat 3] [--json]
"""

import sys

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)
import torch

from experiments import common
from experiments.bench_ekf import run

#: the process's own thread count, before --threads sets one: what ``--load`` measures with
DEFAULT_THREADS = torch.get_num_threads()

ap = common.parser(__doc__)
ap.add_argument("--samples", type=int, default=7342)
ap.add_argument("--device", default="cpu")
ap.add_argument("--load", action="store_true", help="also time the fast path beside a busy competing process")
ap.add_argument("--no-baseline", action="store_true", help="skip the (slow) baseline pass")
ap.add_argument("--repeat", type=int, default=3, help="fast and module passes, alternating; the shortest of each")


def main(argv=None) -> dict:
    args, out = common.run(
        ap, lambda a: run(a.samples, a.device, not a.no_baseline, a.load, DEFAULT_THREADS, a.repeat), argv
    )
    print(", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in out.items()), file=sys.stderr)
    common.emit(out, args)
    return out


if __name__ == "__main__":
    main()
