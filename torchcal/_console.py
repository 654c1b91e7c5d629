"""Messages to stderr and progress bars that respect ``--quiet`` and only draw on a terminal."""

from __future__ import annotations

import sys

from tqdm import tqdm

_quiet = False


def set_quiet(quiet: bool) -> None:
    global _quiet
    _quiet = bool(quiet)


def info(msg: str) -> None:
    if not _quiet:
        print(msg, file=sys.stderr, flush=True)


def progress(iterable=None, *, total=None, desc: str | None = None):
    """A tqdm bar on stderr, shown only on a terminal and when not quiet."""
    return tqdm(
        iterable, total=total, desc=desc, file=sys.stderr, leave=False, disable=_quiet or not sys.stderr.isatty()
    )
