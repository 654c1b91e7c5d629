"""Run one ``torchcal`` command in this process and measure each of its stages: wall and CPU time, peak memory.

Run as a script in a fresh interpreter (``python _memprobe.py [--no-reset] -- calibrate DATA ...``): it imports
only the standard library, then runs the command's entry (``torchcal._entry.main(ARGS)``) in this process, so
the stages see every import the command makes (``import torchcal``: torch; ``import torchcal.cli``).
:mod:`experiments.bench_memory` starts it and reads the JSON line it prints last.

How: the functions of :data:`TARGETS` are wrapped as their modules are imported, and the imports of
:data:`IMPORTS` are stages themselves (a ``sys.meta_path`` hook, so that a stage's own imports stay in that
stage); the stages nest under ``command``, each thread's on a stack of its own (a stage that starts in a worker
thread is named under the stage the main thread is in at that moment). The peak resident memory of a stage is the
kernel's high-water mark (``VmHWM`` of ``/proc/self/status``) between its entry and exit; the mark is reset
(``/proc/self/clear_refs``, Linux) at every entry and exit, so each stage reports its own peak and the enclosing
stage takes the maximum of its children's. torch's allocator is outside ``tracemalloc``; the resident set is what
the machine pays. With ``--no-reset`` (or where the reset is refused) the marks are cumulative: each stage's peak
is then the process's peak so far.
"""

from __future__ import annotations

import functools
import importlib.abc
import importlib.util
import json
import resource
import sys
import threading
import time

#: (module, attribute, stage) wrapped when the module is imported; the attribute is looked up where it is called
#: (``torchcal.report.rundir.write_run`` is what the CLI calls, ``torchcal.pipeline.methods.solve`` what the stages
#: call)
TARGETS = [
    ("torchcal.robot", "load_robot", "robot"),
    ("torchcal.data", "read_measurements", "read"),
    ("torchcal.data", "convert_ipa", "convert"),
    ("torchcal.pipeline", "calibrate", "fit"),
    ("torchcal.pipeline.run", "screen_gross_errors", "screening"),
    ("torchcal.pipeline.methods", "solve", "least squares"),
    ("torchcal.pipeline.state", "StageWork.add_stage", "held-out errors"),
    ("torchcal.pipeline.methods", "close_loop", "closed loop"),
    ("torchcal.pipeline.methods", "learned_stage", "learned stage"),
    ("torchcal.estimate.robust", "screen_geometric", "robust fit and snooping"),
    ("torchcal.estimate.fit", "whitening", "whitening"),
    ("torchcal.estimate.fit", "jacobian_of", "identifiability Jacobian"),
    ("torchcal.estimate.fit", "analyse", "identifiability analysis"),
    ("torchcal.estimate.fit", "levenberg_marquardt", "LM"),
    ("torchcal.report.rundir", "write_run", "report"),
    ("torchcal.report.rundir", "build_report", "report.json"),
    ("torchcal.robot.export", "write_urdf", "URDF"),
    ("torchcal.report.urdf", "urdf_gap", "URDF gap"),
    ("torchcal.report.urdf", "urdf_fk_difference", "URDF reload check"),
    ("torchcal.report.markdown", "write_markdown", "report.md and figures"),
    ("torchcal.sim", "simulate", "simulate"),
    ("torchcal.sim", "write_campaign", "write campaign"),
]

#: modules whose import is a stage of its own (``torchcal`` imports torch)
IMPORTS = ("torchcal", "torchcal.cli")

_MB = 1.0 / 1024.0  # /proc and ru_maxrss give kB


def _status() -> dict[str, float]:
    """``VmRSS`` and ``VmHWM`` [MB], or the rusage maximum where there is no /proc."""
    try:
        with open("/proc/self/status") as f:
            out = {}
            for line in f:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    out[line[:5]] = float(line.split()[1]) * _MB
            return out
    except OSError:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * _MB
        return {"VmRSS": peak, "VmHWM": peak}


class Meter:
    """Nested stages with their own time and peak memory (module docstring)."""

    def __init__(self, reset: bool):
        self.reset_ok = reset and self._reset()
        self.stacks: dict[int, list[dict]] = {}  # per thread: a stage run in a worker thread nests on its own stack
        self.main = threading.get_ident()
        self.lock = threading.Lock()
        self.records: dict[str, dict] = {}  # by path "fit/screening", in order of first entry

    @property
    def stack(self) -> list[dict]:
        return self.stacks.setdefault(threading.get_ident(), [])

    def _reset(self) -> bool:
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # 5: reset the peak resident set size to the current one
            return True
        except OSError:
            return False

    def _hwm(self) -> float:
        return _status()["VmHWM"]

    def enter(self, name: str) -> None:
        hwm = self._hwm()
        if self.stack:
            self.stack[-1]["child_peak"] = max(self.stack[-1]["child_peak"], hwm)
        if self.reset_ok:
            self._reset()
        r = resource.getrusage(resource.RUSAGE_SELF)
        # a worker thread's outermost stage is named under the stage the main thread is in when it starts (the
        # learned stage's GP fit beside the network's: the path is approximate, the stage's own numbers are not)
        main = self.stacks.get(self.main, []) if not self.stack and threading.get_ident() != self.main else []
        self.stack.append(
            {
                "name": name,
                "prefix": [f["name"] for f in main],
                "t0": time.perf_counter(),
                "cpu0": r.ru_utime + r.ru_stime,
                "rss0": _status()["VmRSS"],
                "child_peak": 0.0,
                "mods0": set(sys.modules),
                "child_mods": set(),
            }
        )

    def exit(self) -> None:
        fr = self.stack.pop()
        st = _status()
        r = resource.getrusage(resource.RUSAGE_SELF)
        peak = max(st["VmHWM"], fr["child_peak"])
        new = {m.split(".")[0] for m in set(sys.modules) - fr["mods0"]}
        root = self.stack[0] if self.stack else fr  # the thread's outermost stage carries its prefix
        path = "/".join(root["prefix"] + [f["name"] for f in self.stack] + [fr["name"]])
        with self.lock:
            self._record(path, fr, st, r, peak, new)
        if self.stack:
            self.stack[-1]["child_peak"] = max(self.stack[-1]["child_peak"], peak)
            self.stack[-1]["child_mods"] |= new
        if self.reset_ok:
            self._reset()

    def _record(self, path: str, fr: dict, st: dict, r, peak: float, new: set) -> None:
        rec = self.records.setdefault(
            path, {"stage": path, "calls": 0, "wall_s": 0.0, "cpu_s": 0.0, "peak_mb": 0.0, "imports": []}
        )
        rec["calls"] += 1
        rec["wall_s"] += time.perf_counter() - fr["t0"]
        rec["cpu_s"] += r.ru_utime + r.ru_stime - fr["cpu0"]
        rec["peak_mb"] = max(rec["peak_mb"], peak)
        rec["rss_before_mb"] = rec.get("rss_before_mb", fr["rss0"])
        rec["rss_after_mb"] = st["VmRSS"]
        # the top-level packages this stage imported itself (not those of its children), the large ones named
        rec["imports"] = sorted(set(rec["imports"]) | (new - fr["child_mods"]))

    def wrap(self, fn, name: str):
        @functools.wraps(fn)
        def staged(*a, **k):
            self.enter(name)
            try:
                return fn(*a, **k)
            finally:
                self.exit()

        staged.__wrapped_by_memprobe__ = True
        return staged


def _patch(module, attr: str, name: str, meter: Meter) -> None:
    owner_path, _, leaf = attr.rpartition(".")
    owner = module
    for part in filter(None, owner_path.split(".")):
        owner = getattr(owner, part, None)
        if owner is None:
            return
    fn = getattr(owner, leaf, None)
    if fn is None or getattr(fn, "__wrapped_by_memprobe__", False):
        return
    setattr(owner, leaf, meter.wrap(fn, name))


class _Hook(importlib.abc.MetaPathFinder):
    """Wraps the :data:`TARGETS` of a module right after it has been executed."""

    def __init__(self, meter: Meter):
        self.meter = meter
        self.by_module: dict[str, list[tuple[str, str]]] = {m: [] for m in IMPORTS}
        for mod, attr, name in TARGETS:
            self.by_module.setdefault(mod, []).append((attr, name))

    def find_spec(self, fullname, path, target=None):
        if fullname not in self.by_module:
            return None
        sys.meta_path.remove(self)  # find the real spec without ourselves
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            sys.meta_path.insert(0, self)
        if spec is None or spec.loader is None:
            return spec
        loader, hook = spec.loader, self

        class Patching(importlib.abc.Loader):
            def __getattr__(self, attr):  # resources, source, ...: the real loader's
                return getattr(loader, attr)

            def create_module(self, spec):
                return loader.create_module(spec)

            def exec_module(self, module):
                if fullname in IMPORTS:
                    hook.meter.enter(f"import {fullname}")
                try:
                    loader.exec_module(module)
                finally:
                    if fullname in IMPORTS:
                        hook.meter.exit()
                for attr, name in hook.by_module[fullname]:
                    _patch(module, attr, name, hook.meter)

        spec.loader = Patching()
        return spec


def main(argv: list[str]) -> int:
    opts, args = (argv[: argv.index("--")], argv[argv.index("--") + 1 :]) if "--" in argv else ([], argv)
    reset = "--no-reset" not in opts
    # --target MODULE:ATTR=STAGE adds a stage (repeatable), e.g. torchcal.estimate.robust:snooping_statistics=snooping
    for k, o in enumerate(opts):
        if o == "--target":
            where, _, name = opts[k + 1].partition("=")
            mod, _, attr = where.partition(":")
            TARGETS.append((mod, attr, name or attr))
    meter = Meter(reset)
    sys.meta_path.insert(0, _Hook(meter))
    start = _status()
    sys.argv = ["torchcal", *args]
    meter.enter("command")
    try:
        # the command's entry with its arguments given: as the process's own command (python -m torchcal) it ends
        # the process itself once it returns (torchcal._entry), and this probe's report would never be printed
        from torchcal._entry import main as command

        rc = command(args)
    except SystemExit as e:  # argparse's --help and usage errors
        rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        meter.exit()
    records = list(meter.records.values())
    print(
        json.dumps(
            {
                "argv": args,
                "rc": rc,
                "peak_reset": meter.reset_ok,
                "start_rss_mb": start["VmRSS"],
                "peak_mb": max(r["peak_mb"] for r in records),
                "stages": records,
            }
        )
    )
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
