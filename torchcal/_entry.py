"""The ``torchcal`` command's entry point (``[project.scripts]`` and ``python -m torchcal``).

It imports nothing heavy itself (``import torchcal`` is light, see ``torchcal/__init__.py``), so a Ctrl-C
during the first second, while torch loads, ends the command with exit code 130 and one line instead of a
traceback through torch's import machinery.
"""

from __future__ import annotations

import os
import sys

#: the commands that run with one torch thread (:func:`torchcal.cli._one_torch_thread`)
ONE_THREAD_COMMANDS = ("predict", "compensate", "plan")


def main(argv: list[str] | None = None) -> int:
    """Load the command line (:func:`torchcal.cli.main`) and run it; return its exit code."""
    args = sys.argv[1:] if argv is None else argv
    if args and args[0] in ONE_THREAD_COMMANDS and "torch" not in sys.modules:
        # one OpenMP thread from before torch loads, as the command then asks of torch: with torch.set_num_threads(1)
        # alone these commands still took up to twice the CPU time of OMP_NUM_THREADS=1 on a shared machine, for a
        # reason not found (docs/benchmarks.md, *Speed of predict, compensate and plan*); a value the user set is kept
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        os.environ.setdefault("MKL_NUM_THREADS", "1")
    try:
        from torchcal.cli import main as cli_main
    except KeyboardInterrupt:
        print("torchcal: interrupted while starting; nothing was written", file=sys.stderr)
        return 130
    return cli_main(argv)
