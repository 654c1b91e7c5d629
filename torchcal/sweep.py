"""Independent tasks on Ray, or one after another: the engine of ``torchcal fleet`` and of the experiments' seed sweeps.

:func:`map_tasks` calls ``fn(item)`` for every item and returns the results in the items' order. With ``workers``
above 1 (a local Ray instance of that many CPUs) or an ``address`` (an existing Ray cluster: ``ray://HOST:PORT`` or
``auto``) the calls are Ray tasks, one CPU and one torch thread each; otherwise, or where Ray is not installed
(``pip install torchcal[fleet]``; said once on stderr), they run in this process one after another.

The results do not depend on the engine: every call starts from the global torch generator seeded afresh
(:data:`SEED`, restored after), so no call sees what another drew, and on Ray each runs with one torch thread, as the
experiments' default ``--threads 1`` does here. ``fn`` and the items must pickle (``fn`` a module-level function, or
a :func:`functools.partial` of one); a local instance's workers inherit this process's ``sys.path``, so the code of
a checkout (``experiments/``) imports there too. On a cluster every node must have torchcal and see the same paths.

A failure is the item's own, never the sweep's: a call that raises, or whose worker died (a killed process, a lost
node) more than :data:`RETRIES` times, becomes a :class:`TaskFailure` in its place while the others run to the end;
then :func:`map_tasks` raises :class:`SweepError`, which names every failure and carries the others' results.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import re
import shutil
import sys
import tempfile
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from torchcal._threads import torch_threads
from torchcal.errors import OptionError, TorchcalError

#: how often Ray runs a task again whose worker died (a killed process, a lost node) before reporting it failed
RETRIES = 2
#: the seed of the global torch generator at the start of every call
SEED = 0
#: the longest error message kept per failure (its first line)
MAX_ERROR = 300

_said_serial = False


@dataclass(frozen=True)
class TaskFailure:
    """A call that did not return: ``index`` of its item, the ``item`` as text, the ``error`` in one line, ``lost``
    whether its worker died (rather than the call raising) and, where it raised, the ``traceback``."""

    index: int
    item: str
    error: str
    lost: bool = False
    traceback: str | None = None


class SweepError(TorchcalError, RuntimeError):
    """Some calls of a sweep failed; ``failures`` names each, ``results`` holds every item's outcome in order (a
    :class:`TaskFailure` at a failed one)."""

    def __init__(self, failures: list[TaskFailure], results: list):
        self.failures, self.results = failures, results
        named = "; ".join(f"item {f.index} ({f.item}): {f.error}" for f in failures)
        super().__init__(f"{len(failures)} of {len(results)} tasks failed: {named}")


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return (text.splitlines()[0] if text else "")[:MAX_ERROR]


def _short(item: Any) -> str:
    text = repr(item)
    return text if len(text) <= 80 else text[:77] + "..."


def call(fn: Callable, item: Any) -> Any:
    """``fn(item)`` with the global torch generator seeded afresh (:data:`SEED`) and restored after: what every
    engine runs per item."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(SEED)
        return fn(item)


def _ray_call(fn: Callable, item: Any) -> Any:
    """:func:`call` in a Ray worker: one torch thread (the worker may have been started with more)."""
    with torch_threads(1):
        return call(fn, item)


def _driver_path() -> str:
    """This process's ``sys.path`` as ``PYTHONPATH`` (the working folder for its empty entry), this torchcal first."""
    here = str(Path(__file__).resolve().parents[1])
    paths = [here] + [p or os.getcwd() for p in sys.path]
    paths += [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return os.pathsep.join(dict.fromkeys(p for p in paths if os.path.isdir(p)))


@contextlib.contextmanager
def worker_env():
    """The environment a local Ray instance's workers inherit while it starts: this process's ``sys.path`` (a worker
    is a fresh interpreter: a checkout's torchcal and ``experiments/`` import there too) and one thread. Set in this
    process for the start and restored after, not as a Ray runtime environment, whose agent took as long again as the
    start itself on a 2-core machine."""
    want = {"PYTHONPATH": _driver_path(), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    before = {k: os.environ.get(k) for k in want}
    os.environ.update(want)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _ray_failure(index: int, item: Any, e: Exception) -> TaskFailure:
    """What a Ray error of one task means: the call raised (Ray wraps its exception) or its worker was lost."""
    from ray.exceptions import RayTaskError

    if isinstance(e, RayTaskError):
        cause = e.cause if isinstance(getattr(e, "cause", None), BaseException) else e
        return TaskFailure(index, _short(item), f"{type(cause).__name__}: {_first_line(cause)}", traceback=str(e))
    error = f"the task was lost after {RETRIES + 1} tries: {type(e).__name__}: {_first_line(e) or type(e).__name__}"
    return TaskFailure(index, _short(item), error, lost=True)


#: seconds to wait for a cluster's address to accept a connection before Ray is asked to join it
REACH_TIMEOUT = 5.0


def _check_reachable(address: str) -> None:
    """Refuse a ``HOST:PORT`` (or ``ray://HOST:PORT``) nothing answers at: Ray retries such an address for many
    minutes, one warning after another, before it gives up. ``auto`` and other forms are left to Ray."""
    import socket

    m = re.fullmatch(r"(?:ray://)?\[?([^\[\]/]+?)\]?:(\d+)", address.strip())
    if m is None:
        return
    try:
        socket.create_connection((m.group(1), int(m.group(2))), timeout=REACH_TIMEOUT).close()
    except OSError as e:
        client = (
            " (a ray:// address is the head's Ray Client server, port 10001 by default, which runs only where the head "
            "was started with one; the address 'ray start --head' prints, HOST:PORT without ray://, needs none)"
            if address.strip().startswith("ray://")
            else ""
        )
        raise OptionError(
            f"--address {address}: nothing answers there within {REACH_TIMEOUT:g} s ({e.strerror or e}){client}; "
            "start the cluster (ray start --head) or give its address"
        ) from None


#: what Ray's log says when the head wants a token this process did not send
_AUTH_SIGNS = ("InvalidAuthToken", "Unauthenticated", "AuthenticationError", "auth token", "authentication token")


@contextlib.contextmanager
def _stderr_kept(into: list):
    """Ray's C++ client writes to file descriptor 2 directly (20 lines of 'Unauthenticated ... InvalidAuthToken'
    while it retries a head that wants a token): held in a file while it connects, the text put into ``into``."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as f:
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            f.seek(0)
            into.append(f.read().decode(errors="replace"))


def _join(address: str) -> None:
    """``ray.init`` at a cluster's ``address``; a refusal that says why where it cannot join."""
    import ray

    log: list[str] = []
    try:
        with _stderr_kept(log):
            ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    except (ConnectionError, RuntimeError, ValueError) as e:
        text = "".join(log) + str(e)
        if any(sign.lower() in text.lower() for sign in _AUTH_SIGNS):
            raise OptionError(
                f"--address {address}: the cluster wants an authentication token this process did not send (Ray "
                "turns token authentication on for a head started where ~/.ray/auth_token exists); set "
                "RAY_AUTH_MODE=token, with the head's token in RAY_AUTH_TOKEN or ~/.ray/auth_token, and run again"
            ) from None
        last = next((ln for ln in reversed(text.splitlines()) if ln.strip()), type(e).__name__)
        raise OptionError(f"--address {address}: Ray could not join the cluster there: {last.strip()[:300]}") from None


def on_ray(fn: Callable, items: list, cpus: int | None, address: str | None, done: Callable[[int, Any], None]) -> list:
    """Every item's call on Ray: a local instance of ``cpus`` CPUs (one started here is stopped here; an instance
    already running is used as it is), or the cluster at ``address``. ``done(index, outcome)`` is called as each
    finishes (an outcome is the result or a :class:`TaskFailure`); returns the outcomes in the items' order."""
    import ray
    from ray.exceptions import RayError

    started = not ray.is_initialized()
    if started and address:
        _check_reachable(address)
    private = None
    if started:
        if not address:
            # a private instance whatever else runs: address "local" never joins another instance (another fleet,
            # another user's Ray, a stale ray_current_cluster file of a killed one: 'num_cpus must not be provided'),
            # and its own temp root shares no sockets, session or cluster file with them
            private = tempfile.mkdtemp(prefix="tcray-", dir="/tmp" if os.path.isdir("/tmp") else None)
            kw = {"address": "local", "num_cpus": cpus or os.cpu_count() or 1, "_temp_dir": private}
    earlier = _descendants(os.getpid()) if private is not None else {}
    pending: dict = {}
    watchdog = None
    try:
        if started and address:
            _join(address)
        elif started:  # within the try: Ctrl-C while Ray starts stops what has started
            with worker_env():
                ray.init(**kw, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
        remote = ray.remote(num_cpus=1, max_retries=RETRIES)(_ray_call)
        fn_ref = ray.put(fn)  # once, not with every task
        pending = {remote.remote(fn_ref, it): i for i, it in enumerate(items)}
        out: list = [None] * len(items)
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            i = pending.pop(ready[0])
            try:
                out[i] = ray.get(ready[0])
            except RayError as e:
                out[i] = _ray_failure(i, items[i], e)
            done(i, out[i])
        return out
    except KeyboardInterrupt:
        watchdog = _interrupted(ray, pending)
        raise
    finally:
        ours = {k: v for k, v in _descendants(os.getpid()).items() if earlier.get(k) != v} if private else {}
        if started:
            with contextlib.suppress(Exception):  # after an interrupted start there may be nothing to stop
                ray.shutdown()
        if private is not None:
            _end(ours)
            shutil.rmtree(private, ignore_errors=True)
            # Ray's monitor and dashboard, stopping, may write a last log there: once more when this process ends
            atexit.register(shutil.rmtree, private, ignore_errors=True)
        if watchdog is not None:  # stopped in time
            watchdog.cancel()


def _descendants(pid: int) -> dict[int, str]:
    """``{pid: start time}`` of the live processes below ``pid`` (Linux ``/proc``; elsewhere none)."""
    parent, start = {}, {}
    with contextlib.suppress(OSError):
        for p in os.listdir("/proc"):
            if p.isdigit():
                try:
                    fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
                except (OSError, IndexError):
                    continue
                parent[int(p)], start[int(p)] = int(fields[1]), fields[19]
    out, todo = {}, [pid]
    while todo:
        here = todo.pop()
        for child, up in parent.items():
            if up == here and child not in out:
                out[child] = start[child]
                todo.append(child)
    return out


def _end(procs: dict[int, str]) -> None:
    """Kill what is left of a private instance's processes ``{pid: start time}`` once Ray has stopped it: its
    dashboard and runtime-env agents outlived an interrupted fleet by minutes, holding its temp root."""
    import signal
    import time

    deadline = time.monotonic() + 2.0
    while procs and time.monotonic() < deadline:
        procs = {pid: t for pid, t in procs.items() if _descendants_alive(pid, t)}
        if procs:
            time.sleep(0.1)
    for pid in procs:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)


def _descendants_alive(pid: int, start: str) -> bool:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return False
    return fields[19] == start and fields[0] != "Z"


#: seconds an interrupted sweep is given to end its tasks and stop its instance before the process exits regardless
INTERRUPT_GRACE = 8.0


def _interrupted(ray, pending: dict):
    """Ctrl-C: the running tasks are cancelled (their workers killed), and a watchdog ends this process with 130
    should stopping Ray take longer than :data:`INTERRUPT_GRACE` s (under load it was still alive 290 s later)."""
    import threading

    def give_up() -> None:
        print("interrupted; Ray did not stop in time: exiting", file=sys.stderr, flush=True)
        os._exit(130)

    timer = threading.Timer(INTERRUPT_GRACE, give_up)
    timer.daemon = True
    timer.start()
    with contextlib.suppress(Exception):
        for ref in pending:
            ray.cancel(ref, force=True)
    return timer


def in_process(fn: Callable, items: list, done: Callable[[int, Any], None]) -> list:
    """Every item's call in this process, one after another; a call that raises is its item's
    :class:`TaskFailure`."""
    out: list = []
    for i, it in enumerate(items):
        try:
            out.append(call(fn, it))
        except Exception as e:  # one item's error must not end the others: it is reported with them at the end
            tb = traceback.format_exc()[-4000:]
            out.append(TaskFailure(i, _short(it), f"{type(e).__name__}: {_first_line(e)}", traceback=tb))
        done(i, out[-1])
    return out


def _engine(workers: int | None, address: str | None, n: int) -> str:
    """``ray`` or ``serial`` for a sweep of ``n`` items (module docstring); a bad choice raises."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise OptionError(f"workers must be a whole number of at least 1 (or None: one after another), got {workers!r}")
    if not address and (workers or 1) == 1:
        return "serial"
    if ray_available():
        return "ray"
    if address:
        raise OptionError(f"--address {address} needs Ray (pip install torchcal[fleet])")
    global _said_serial
    if not _said_serial:
        _said_serial = True
        print(
            f"torchcal: Ray is not installed (pip install torchcal[fleet]): the {n} tasks run one after another "
            f"instead of on {workers} workers",
            file=sys.stderr,
        )
    return "serial"


def map_tasks(
    fn: Callable[[Any], Any],
    items: Iterable,
    *,
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, Any], None] | None = None,
) -> list:
    """``[fn(item) for item in items]``, the calls independent tasks on Ray or one after another (module docstring).

    Args:
        fn: a picklable function of one item; items: picklable, each one call.
        workers: CPUs of a local Ray instance; None or 1: one after another in this process.
        address: an existing Ray cluster (``ray://HOST:PORT`` or ``auto``) instead of a local instance.
        progress: called with ``(index, outcome)`` as each call finishes, in the order they finish; the outcome is the
            result, or a :class:`TaskFailure`.

    Returns:
        The results in the items' order.

    Raises:
        SweepError: after every call finished, where any failed; it names each failure and holds every outcome.
        OptionError: ``workers`` below 1, or an ``address`` without Ray.
    """
    items = list(items)
    engine = _engine(workers, address, len(items))
    done = progress or (lambda i, r: None)
    out = on_ray(fn, items, workers, address, done) if engine == "ray" and items else in_process(fn, items, done)
    failures = [r for r in out if isinstance(r, TaskFailure)]
    if failures:
        raise SweepError(failures, out)
    return out
