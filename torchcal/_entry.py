"""The ``torchcal`` command's entry point (``[project.scripts]`` and ``python -m torchcal``).

It imports nothing heavy itself (``import torchcal`` is light, see ``torchcal/__init__.py``), so a Ctrl-C
during the first second, while torch loads, ends the command with exit code 130 and one line instead of a
traceback through torch's import machinery.

As the process's command (no ``argv`` given) it ends the process itself once the command has returned: the
standard streams flushed and the ``atexit`` handlers run, it skips the interpreter's teardown (clearing every
module of torch and matplotlib and collecting their objects), which cost a kinematic calibration of Series C
0.4-0.5 s of CPU, more than its report.json and URDF together (measured in docs/benchmarks.md).
"""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """Load the command line (:func:`torchcal.cli.main`) and run it; return its exit code.

    With ``argv`` None (the console script and ``python -m torchcal``: the process's own command line) the process
    ends here with that code (:func:`_end`) unless another thread of Python's is still running or Ray is loaded."""
    try:
        from torchcal.cli import main as cli_main
    except KeyboardInterrupt:
        print("torchcal: interrupted while starting; nothing was written", file=sys.stderr)
        return 130
    code = cli_main(argv)
    if code == 130 and "ray" in sys.modules:
        # interrupted with Ray loaded: its own instance is stopped by now (torchcal.sweep.on_ray), but Ray's core
        # worker, cut off mid-start, crashed the interpreter's exit (SIGSEGV after 'interrupted'): end here, without
        # its atexit handlers either (as before this ending was shared)
        _end(code, handlers=False)
    if argv is None and "ray" not in sys.modules and _alone():  # a fleet on Ray exits the usual way, as it was tried
        _end(code)
    return code


def _alone() -> bool:
    """Whether the main thread is the only live Python thread but daemons (the interpreter's exit would join the
    others: then it exits the usual way)."""
    import threading

    main_thread = threading.main_thread()
    return not any(t is not main_thread and t.is_alive() and not t.daemon for t in threading.enumerate())


def _end(code: int, *, handlers: bool = True) -> None:
    """End the process with ``code`` without the interpreter's teardown: the standard streams flushed and, with
    ``handlers``, the ``atexit`` handlers run first (logging's, Ray's, temporary files'), as the usual exit does."""
    import atexit
    import os

    if handlers:
        atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more can reach it
            pass
    os._exit(code if isinstance(code, int) else 1)
