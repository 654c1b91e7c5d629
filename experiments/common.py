"""What every experiment script shares: ``--threads`` and ``--json``, running under that many torch threads, and
printing the result.

A script builds its parser with :func:`parser`, adds its own arguments, and ends with :func:`run` and
:func:`emit`::

    ap = common.parser(__doc__)
    ap.add_argument("--seed", type=int, default=0)

    def main(argv=None) -> int:
        args, result = common.run(ap, lambda a: experiment.run(a.seed), argv)
        common.emit(result, args, plain=result)
        return 0
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import time
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from torchcal._threads import torch_threads

T = TypeVar("T")


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


def add_sweep_arguments(ap: argparse.ArgumentParser, what: str = "seeds") -> None:
    """Add ``--workers`` and ``--address``: the experiment's independent fits (its ``what``) as tasks of
    :func:`torchcal.sweep.map_tasks`, on a local Ray instance of N CPUs or on a Ray cluster; one after another by
    default, with the same results."""
    ap.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"run the {what}' fits as tasks on a local Ray instance of N CPUs, one torch thread each (default: one "
        "after another; the same results; pip install torchcal[fleet])",
    )
    ap.add_argument(
        "--address",
        default=None,
        help="run them on the Ray cluster at ADDR (ray://HOST:PORT or auto; every node sees this checkout's paths)",
    )


def parser(doc: str, *, threads: int = 1) -> argparse.ArgumentParser:
    """An argument parser described by ``doc`` (a script's docstring, shown as written) with the common arguments."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(ap, threads=threads)
    return ap


def run(
    ap: argparse.ArgumentParser, experiment: Callable[[argparse.Namespace], T], argv: list[str] | None = None
) -> tuple[argparse.Namespace, T]:
    """Parse ``argv`` with ``ap`` and run ``experiment(args)`` under ``--threads`` torch threads (restored after).

    Returns:
        The parsed arguments and the experiment's result.
    """
    args = ap.parse_args(argv)
    with torch_threads(args.threads):
        return args, experiment(args)


def emit_json(result: Any, args: argparse.Namespace) -> None:
    """Print ``result`` as one JSON object on one line when ``--json`` was given."""
    if getattr(args, "json", False):
        print(json.dumps(result))


def emit(result: Any, args: argparse.Namespace, *, plain: Any = None) -> None:
    """Print ``result`` as one JSON line with ``--json``; without it, ``plain`` as indented JSON (if not None)."""
    if getattr(args, "json", False):
        print(json.dumps(result))
    elif plain is not None:
        print(json.dumps(plain, indent=1))


def comma_list(
    ap: argparse.ArgumentParser,
    text: str,
    valid: Sequence[str] | None = None,
    *,
    what: str = "name",
    upper: bool = False,
) -> tuple[str, ...]:
    """The comma-separated names of an argument, blanks dropped (``"c, a"`` -> ``("C", "A")`` with ``upper``).

    Raises:
        SystemExit: a usage error of ``ap`` naming the names outside ``valid`` (when given) and the valid ones.
    """
    names = tuple(s.strip().upper() if upper else s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in names if valid is not None and s not in valid]
    if bad:
        ap.error(f"unknown {what} {', '.join(bad)}; valid: {', '.join(valid)}")
    return names


def run_markdown(
    ap: argparse.ArgumentParser,
    experiment: Callable[[argparse.Namespace], tuple[Any, str]],
    argv: list[str] | None = None,
) -> int:
    """For an experiment that returns ``(result, markdown)``: :func:`run` it, print the markdown, then
    :func:`emit` the result; returns the exit status 0."""
    args, (result, md) = run(ap, experiment, argv)
    print(md)
    emit(result, args)
    return 0


def child_cpu() -> float:
    """CPU seconds (user and system) of this process's finished children."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed_command(argv: list[str], *, env: dict, cwd, what: str) -> tuple[float, float]:
    """Wall and CPU seconds of one command (the CPU time of the child alone, where the wall time counts the other
    work of a shared machine too); raises, naming ``what``, where it fails."""
    c0, t0 = child_cpu(), time.perf_counter()
    done = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, child_cpu() - c0
    if done.returncode != 0:
        raise RuntimeError(f"{what} exited {done.returncode}: {done.stderr.strip()[-500:]}")
    return wall, cpu
