"""The ``torchcal`` command's entry point (``[project.scripts]`` and ``python -m torchcal``).

It imports nothing heavy itself (``import torchcal`` is light, see ``torchcal/__init__.py``), so a Ctrl-C
during the first second, while torch loads, ends the command with exit code 130 and one line instead of a
traceback through torch's import machinery.
"""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """Load the command line (:func:`torchcal.cli.main`) and run it; return its exit code."""
    try:
        from torchcal.cli import main as cli_main
    except KeyboardInterrupt:
        print("torchcal: interrupted while starting; nothing was written", file=sys.stderr)
        return 130
    code = cli_main(argv)
    if code == 130 and "ray" in sys.modules:
        # interrupted with Ray loaded: its own instance is stopped by now (torchcal.sweep.on_ray), but Ray's core
        # worker, cut off mid-start, crashed the interpreter's exit (SIGSEGV after 'interrupted'): end here
        import os

        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    return code
