"""Messages to stderr and progress bars that respect ``--quiet`` and only draw on a terminal."""

from __future__ import annotations

import sys

from tqdm import tqdm

_quiet = False


def set_quiet(quiet: bool) -> None:
    global _quiet
    _quiet = bool(quiet)


def one_line(text: str) -> str:
    """``text`` as one line of printable characters: control characters (line breaks, NUL, terminal escapes) are
    written as Python escapes, so a name read from a file cannot forge lines or codes on the terminal."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


#: the levels :func:`set_verbosity` takes: "info" says each stage and warning on stderr, "quiet" nothing
LEVELS = ("info", "quiet")


def set_verbosity(level: str) -> str:
    """How much torchcal says on stderr (the library's ``--quiet``): ``"info"`` (default: stages, decisions, warnings
    and progress bars) or ``"quiet"`` (nothing; the run's notes and report hold all of it). Returns the previous level,
    so a caller can restore it.

    Raises:
        OptionError: another level (the message lists the valid ones).
    """
    from torchcal.errors import OptionError

    if level not in LEVELS:
        raise OptionError(f"verbosity level {level!r} is not one of {', '.join(LEVELS)}")
    before = "quiet" if _quiet else "info"
    set_quiet(level == "quiet")
    return before


def info(msg: str) -> None:
    """Say ``msg`` on stderr (one line) unless quiet, through the progress bars' writer: a bar drawing on the terminal
    is cleared and redrawn below the message instead of being overwritten by it."""
    if not _quiet:
        tqdm.write(one_line(msg), file=sys.stderr)
        sys.stderr.flush()


def progress(iterable=None, *, total=None, desc: str | None = None):
    """A tqdm bar on stderr, shown only on a terminal and when not quiet."""
    return tqdm(
        iterable, total=total, desc=desc, file=sys.stderr, leave=False, disable=_quiet or not sys.stderr.isatty()
    )
