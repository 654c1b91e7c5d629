"""The ``torchcal`` command. Messages go to stderr, results to files under ``--out``.

One module per command, its parser beside its handler (``add_parser(sub)``, ``handle(args)``); the argument types
and the options several commands share in :mod:`torchcal.cli._args`, what several handlers do alike in
:mod:`torchcal.cli._common`, the parser and the exit codes in :mod:`torchcal.cli._main`.

Exit codes: 0 success; 2 a usage error or a :class:`~torchcal.errors.TorchcalError` (bad input, option or
file, with a message saying what was expected and what came); 1 an unexpected internal error (a one-line
summary and where to report it; the traceback with ``--debug``); 130 interrupted.
"""

from __future__ import annotations

from torchcal.cli._args import METHOD_CHOICES
from torchcal.cli._common import calibration_module
from torchcal.cli._main import REPORT_TO, build_parser, main
from torchcal.cli.calibrate import CALIBRATE_FLAGS, _warn_global_test

__all__ = [
    "CALIBRATE_FLAGS",
    "METHOD_CHOICES",
    "OUTSIDE_TOL_SIGMAS",
    "REPORT_TO",
    "_warn_global_test",
    "build_parser",
    "calibration_module",
    "main",
    "outside_rows",
]


def __getattr__(name: str):
    # the rows-beyond-the-region rule lives in the library (torchcal.use.outside); importing it here at once would
    # load torchcal.use for every command
    if name in ("OUTSIDE_TOL_SIGMAS", "outside_rows"):
        from torchcal.use import outside

        return getattr(outside, name)
    raise AttributeError(f"module 'torchcal.cli' has no attribute {name!r}")
