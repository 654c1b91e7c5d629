"""Run one ``torchcal`` command in this process under ``cProfile``, every thread with a profiler of its own, and write
the merged statistics (``python _cprofile_run.py OUT.prof -- calibrate DATA ...``).

The timer is each thread's own CPU time (``time.thread_time``): on a shared machine the wall time counts the other
processes too, and the threads' CPU times add up to the process's (the learned stage fits its GP in a second thread,
which a profiler of the main thread alone would not see). :mod:`experiments.profile_calibration` starts it.

From Python 3.12 ``cProfile`` runs on ``sys.monitoring``: one profiler at a time sees the events of every thread, and
a second one raises. There the main thread's profiler is the only one, timed by the process's CPU time
(``time.process_time``, every thread's), so the functions' own times still add up to the process's CPU; where two
threads overlap, the time of one is charged to what the other was running, so the per-function split is approximate.
"""

from __future__ import annotations

import cProfile
import pstats
import sys
import threading
import time

_profiles: list[cProfile.Profile] = []
_lock = threading.Lock()


def _profiled_run(run):
    """``Thread.run`` under a profiler of the thread's own, kept for the merge."""

    def profiled(self):
        prof = cProfile.Profile(time.thread_time)
        with _lock:
            _profiles.append(prof)
        prof.enable()
        try:
            return run(self)
        finally:
            prof.disable()

    return profiled


def main(argv: list[str]) -> int:
    out, args = argv[0], argv[argv.index("--") + 1 :]
    process_wide = sys.version_info >= (3, 12)  # cProfile on sys.monitoring (module docstring)
    if not process_wide:
        threading.Thread.run = _profiled_run(threading.Thread.run)
    sys.argv = ["torchcal", *args]
    main_prof = cProfile.Profile(time.process_time if process_wide else time.thread_time)
    rc = 0
    main_prof.enable()
    try:
        # the command's entry with its arguments given: as the process's own command it would end the process once
        # it returned (torchcal._entry), before the statistics were written
        from torchcal._entry import main as command

        rc = command(args)
    except SystemExit as e:  # argparse's --help and usage errors
        rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        main_prof.disable()
    stats = pstats.Stats(main_prof)
    for p in _profiles:
        stats.add(p)
    stats.dump_stats(out)
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
