"""What every experiment script shares: ``--threads`` and ``--json``, and printing the result."""

from __future__ import annotations

import argparse
import json


def add_common_arguments(ap: argparse.ArgumentParser, *, threads: int = 1) -> None:
    """Add ``--threads`` (torch threads, default ``threads``) and ``--json`` to ``ap``."""
    ap.add_argument(
        "--threads",
        type=int,
        default=threads,
        help=f"torch threads (default {threads}: the problems are small, and on a busy machine more "
        "threads make them many times slower)",
    )
    ap.add_argument("--json", action="store_true", help="print the result as one JSON object on the last line")


def emit_json(result: dict, args: argparse.Namespace) -> None:
    """Print ``result`` as one JSON object on one line when ``--json`` was given."""
    if getattr(args, "json", False):
        print(json.dumps(result))
