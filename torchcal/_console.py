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


def info(msg: str) -> None:
    if not _quiet:
        print(one_line(msg), file=sys.stderr, flush=True)


def progress(iterable=None, *, total=None, desc: str | None = None):
    """A tqdm bar on stderr, shown only on a terminal and when not quiet."""
    return tqdm(
        iterable, total=total, desc=desc, file=sys.stderr, leave=False, disable=_quiet or not sys.stderr.isatty()
    )
