"""The ``torchcal`` command line: the parser of every command, and the exit codes of the module docstring of
:mod:`torchcal.cli`."""

from __future__ import annotations

import argparse
import errno
import sys
import traceback
import warnings

from torchcal import _console
from torchcal._version import __version__
from torchcal.cli import (
    calibrate,
    check_export,
    compensate,
    convert,
    demo,
    export,
    fleet,
    locate,
    plan,
    predict,
    simulate,
    station,
)
from torchcal.errors import TorchcalError

#: Where unexpected errors should be reported (printed with the one-line summary).
REPORT_TO = "the torchcal issue tracker (see README.md, 'Reporting problems')"

#: the commands in the order ``torchcal --help`` lists them, each a module with ``add_parser(sub)`` and
#: ``handle(args) -> exit code``
COMMANDS = {
    "simulate": simulate,
    "calibrate": calibrate,
    "predict": predict,
    "compensate": compensate,
    "station": station,
    "locate": locate,
    "plan": plan,
    "fleet": fleet,
    "convert": convert,
    "export": export,
    "check-export": check_export,
    "demo": demo,
}


def build_parser() -> argparse.ArgumentParser:
    """The ``torchcal`` parser: each command's options from its own module."""
    parser = argparse.ArgumentParser(prog="torchcal", description="Robot arm calibration from laser-tracker data.")
    parser.add_argument("--debug", action="store_true", help="print the full traceback of an unexpected error")
    parser.add_argument("--version", action="version", version=f"torchcal {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS.values():
        command.add_parser(sub)
    return parser


def _warning_printer(command: str):
    """``warnings.showwarning`` for the command: one line naming the command, not the library's source file and
    line (a user cannot act on torch's internals; ``--debug`` tracebacks still show where)."""

    def show(message, category, filename, lineno, file=None, line=None):
        _console.info(f"torchcal {command}: warning: {category.__name__}: {message}")

    return show


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code (module docstring) instead of raising."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _console.set_quiet(getattr(args, "quiet", False))
    debug = bool(getattr(args, "debug", False))
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_printer(args.command)
            return COMMANDS[args.command].handle(args)
    except TorchcalError as e:
        if debug:
            traceback.print_exc()
        print(f"torchcal {args.command}: error: {_console.one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchcal {args.command}: interrupted; the output was left as it was", file=sys.stderr)
        return 130
    except OSError as e:
        if e.errno not in _REFUSED_ERRNOS:
            return _internal_error(args.command, e, debug)
        if debug:
            traceback.print_exc()
        # the output the user named: a failed write() carries no file name ("cannot write No space left on
        # device"), and a failed copy names its source (station named the input run's report.json)
        target = getattr(args, "out", None) or e.filename2 or e.filename
        where = f"{target}: " if target else ""
        print(
            f"torchcal {args.command}: error: cannot write {where}{e.strerror or e}; nothing was written "
            "(the output was left as it was)",
            file=sys.stderr,
        )
        return 2
    except Exception as e:  # the last line of defence: a summary, never a bare traceback
        return _internal_error(args.command, e, debug)


#: what the file system answers when the output cannot be written for a reason the user can act on (a full disk or
#: quota, a file too large, a name over 255 bytes or a path over PATH_MAX, a read-only file system): a refusal, exit
#: 2. Every writer writes into a temporary and renames it (``torchcal._outdir``), so nothing half-written stays.
_REFUSED_ERRNOS = frozenset(
    getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG", "ENAMETOOLONG", "EROFS") if hasattr(errno, n)
)


def _internal_error(command: str, e: BaseException, debug: bool) -> int:
    """Exit 1 with a one-line summary and where to report it (a bug; never a bare traceback)."""
    if debug:
        traceback.print_exc()
    first = _console.one_line(str(e).strip().splitlines()[0]) if str(e).strip() else ""
    print(f"torchcal {command}: internal error: {type(e).__name__}: {first[:300]}", file=sys.stderr)
    print(
        f"torchcal {command}: this is a bug; please report it at {REPORT_TO} with the command line"
        + ("" if debug else " and the output of the same command with --debug"),
        file=sys.stderr,
    )
    return 1
