"""A fleet of robots: one calibration (or re-check from a prior run) per line of a manifest, as independent tasks.

The manifest is a CSV file with a header row: ``name,data,robot`` and optionally ``method`` and ``prior`` (paths
relative to the manifest's folder; ``robot`` a built-in name or a file). Line ``name`` becomes the run directory
``OUT/name/``, exactly as ``torchcal calibrate DATA --robot ROBOT [--method M] [--prior RUN] --out OUT/name`` would
write it; ``OUT/report.json`` and ``OUT/report.md`` table every robot.

The tasks run on Ray (:func:`run_fleet`, ``engine="ray"``): a local instance with ``workers`` CPUs, or an existing
cluster at ``address`` (every node must see the manifest's files at the same paths and have torchcal installed). Each
task calibrates with one torch thread and the manifest line's seed (calibrate's default, 0), in a temporary folder
of its worker, and returns the run's files; the driver writes them. A task's refusal or error is reported as that
robot's, and the others go on; a task whose worker dies is retried (:data:`RETRIES`) and then reported, never lost.
Without Ray (``pip install torchcal[fleet]``) the same tasks run one after another in this process, with the same
results.

Which robots need a new calibration (:func:`verdict`): a re-check (a line with ``prior``) where a parameter moved
beyond the prior's threshold (``report.json`` ``prior.moved``: more than 3 prior sigmas, or released), or where the
updated model fails the global test (it does not explain the new rows to their noise); a fresh calibration only where
it fails the global test (what the model lacks is more than noise: look at its report). A line whose task failed
gets no verdict: it is listed with its error.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import sys
import tempfile
import time
import traceback
import unicodedata
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from torchcal import _console
from torchcal._outdir import check_out_dir, replace_dir
from torchcal._threads import torch_threads
from torchcal.errors import OptionError, TorchcalError
from torchcal.sweep import RETRIES as RETRIES  # the fleet's own name of it
from torchcal.sweep import TaskFailure, on_ray, ray_available

#: the manifest's columns: required, then optional
REQUIRED = ("name", "data", "robot")
OPTIONAL = ("method", "prior")
#: the methods a line may name (calibrate's)
METHODS = ("auto", "kinematic", "pcm", "kinematic+ann", "integrated")
#: the seed of every task's global torch generator (calibrate's own seed is its default, 0)
SEED = 0
#: the prefix of a task's temporary folder
TMP = "torchcal-fleet-"
#: the largest manifest: lines beyond are refused (a fleet is hundreds of robots, not millions)
MAX_LINES = 10_000


@dataclass(frozen=True)
class Line:
    """One manifest line, its paths resolved against the manifest's folder.

    Attributes:
        number: the line's number in the file (the header is line 1).
        name: the run's name (``OUT/name/``); data: the measurement file; robot: built-in name or file;
        method: calibrate's method (None: its default); prior: a run directory to update (None: a fresh calibration).
    """

    number: int
    name: str
    data: str
    robot: str
    method: str | None = None
    prior: str | None = None


def _bad(path: Path, number: int, column: str, what: str) -> TorchcalError:
    return TorchcalError(f"{path}: line {number}, column '{column}': {what}")


def _resolve(folder: Path, text: str) -> str:
    """Absolute: a worker's working folder need not be the driver's."""
    return str(Path(text) if Path(text).is_absolute() else folder.resolve() / text)


def _robot(folder: Path, text: str) -> str:
    """A built-in name stays a name; a path (with a separator or an extension, or a file there) is resolved."""
    here = folder / text
    if "/" in text or "\\" in text or Path(text).suffix or here.exists():
        return _resolve(folder, text)
    return text


def _check_name(path: Path, number: int, name: str, seen: dict[str, int]) -> None:
    if not name or name in (".", "..") or any(c in name for c in '/\\\0:*?"<>|') or name.startswith("."):
        raise _bad(
            path,
            number,
            "name",
            f"{name!r} is not a folder name (none of / \\ : * ? \" < > |, which folders or report.md's table cannot "
            "hold; not hidden, not empty)",
        )
    if any(unicodedata.category(c).startswith("C") for c in name):
        raise _bad(path, number, "name", f"{name!r} holds control characters (a line break in a quoted cell?)")
    if len(name.encode()) > 200:
        raise _bad(path, number, "name", "longer than 200 bytes")
    if name.lower() in {"report.json", "report.md"}:
        raise _bad(path, number, "name", f"{name!r} is the fleet summary's own file name")
    key = unicodedata.normalize("NFC", name).lower()  # the same folder on a file system that normalises or folds
    if key in seen:
        raise _bad(path, number, "name", f"{name!r} repeats line {seen[key]} (names must differ)")
    seen[key] = number


def _header(path: Path, header: list[str] | None) -> list[str]:
    if header is None:
        raise TorchcalError(f"{path}: empty manifest; expected a header row {','.join(REQUIRED)}[,method][,prior]")
    cols = [c.strip() for c in header]
    unknown = [c for c in cols if c not in REQUIRED + OPTIONAL]
    missing = [c for c in REQUIRED if c not in cols]
    if unknown or missing or len(set(cols)) != len(cols):
        raise TorchcalError(
            f"{path}: line 1: the header must name the columns {', '.join(REQUIRED)} and optionally "
            f"{', '.join(OPTIONAL)}, each once; got {','.join(cols)}"
        )
    return cols


def read_manifest(path: str | os.PathLike) -> list[Line]:
    """The manifest's lines, every one checked before any task runs (module docstring).

    Raises:
        TorchcalError: naming the file, line and column of the first bad cell.
    """
    from torchcal._inputs import read_text_bounded

    path = Path(path)
    # bounded, and a device or FIFO refused unopened (/dev/zero grew to 19.8 GB); a spreadsheet's "CSV UTF-8"
    # starts with a byte-order mark, which is dropped
    text = read_text_bounded(path, "fleet manifest", lambda m: TorchcalError(f"{path}: {m}"))
    reader = csv.reader(io.StringIO(text, newline=""))  # a quoted cell may hold a line break: lines as in the file
    rows = [(reader.line_num, r) for r in reader if r and not r[0].startswith("#")]
    cols = _header(path, rows[0][1] if rows else None)
    folder, lines, seen = path.parent, [], {}
    if len(rows) - 1 > MAX_LINES:
        raise TorchcalError(f"{path}: {len(rows) - 1} lines; a manifest holds at most {MAX_LINES}")
    for number, row in rows[1:]:
        if len(row) != len(cols):
            raise TorchcalError(f"{path}: line {number}: {len(row)} cells for the {len(cols)} columns of the header")
        cell = {c: v.strip() for c, v in zip(cols, row)}
        _check_name(path, number, cell["name"], seen)
        for c in ("data", "robot"):
            if not cell[c]:
                raise _bad(path, number, c, "empty")
        method = cell.get("method") or None
        if method is not None and method not in METHODS:
            raise _bad(path, number, "method", f"unknown method {method!r}; valid: {', '.join(METHODS)}")
        prior = cell.get("prior") or None
        lines.append(
            Line(
                number,
                cell["name"],
                _resolve(folder, cell["data"]),
                _robot(folder, cell["robot"]),
                method,
                None if prior is None else _resolve(folder, prior),
            )
        )
    if not lines:
        raise TorchcalError(f"{path}: no lines after the header; nothing to run")
    return lines


def inputs_of(manifest: str | os.PathLike, lines: list[Line]) -> list[str]:
    """The files and run directories a fleet reads (the output must not hold any of them)."""
    out = [str(manifest)]
    for ln in lines:
        out += [ln.data, *([ln.robot] if Path(ln.robot).is_file() else []), *([ln.prior] if ln.prior else [])]
    return out


def missing_inputs(path: str | os.PathLike, lines: list[Line]) -> list[str]:
    """Before any task of a fleet on this machine: each line whose data file, robot or prior run is not there, as
    the manifest's line and column (a typo in line 57 told at the start, not when line 57's turn comes). Those lines
    are still run and reported refused with their own error while the others go on; so are lines whose files hold
    what calibrate refuses (the data, robot and prior read as the task reads them). Not for a cluster at
    ``--address``: its nodes, not this machine, must see the files."""
    from torchcal._inputs import check_regular
    from torchcal.errors import RobotSpecError
    from torchcal.robot.load import resolve_robot_spec

    path, out = Path(path), []
    for ln in lines:
        try:
            check_regular(ln.data, "measurement file", lambda m, d=ln.data: TorchcalError(f"{d}: {m}"))
        except TorchcalError as e:
            out.append(str(_bad(path, ln.number, "data", str(e))))
        try:
            resolve_robot_spec(ln.robot)
        except RobotSpecError as e:
            out.append(str(_bad(path, ln.number, "robot", _console.one_line(str(e)))))
        if ln.prior and not (Path(ln.prior) / "model.json").is_file():
            out.append(str(_bad(path, ln.number, "prior", f"{ln.prior}: not a run directory (no model.json in it)")))
        elif not any(f"line {ln.number}," in o for o in out):
            try:  # what the files hold, as the task will read them: told now, not when the line's turn comes
                _line_inputs(ln)
            except TorchcalError as e:
                out.append(f"{path}: line {ln.number}: {_console.one_line(str(e))}")
    return out


def _check_robot_line(data, spec: str, robot) -> None:
    """Refuse a file whose ``# robot:`` line names another robot (the rule of ``torchcal calibrate``: names compared
    without folder, extension and case)."""
    from torchcal.errors import MeasurementFileError

    def key(name: str) -> str:
        n = Path(str(name).strip()).name.lower()
        for ext in (".urdf", ".yaml", ".yml"):
            n = n.removesuffix(ext)
        return n

    named = data.meta.get("robot")
    if named and key(named) not in {key(spec), key(robot.name)}:
        raise MeasurementFileError(
            data.source, f"the file's '# robot: {named}' line names another robot than the manifest's '{spec}'"
        )


def _line_inputs(line: Line):
    """The robot, options, prior (or None) and data of one line, each checked as ``calibrate`` checks them."""
    from torchcal import pipeline as C
    from torchcal.data import read_measurements
    from torchcal.robot import load_robot
    from torchcal.robot.load import calibrated_flange

    robot = load_robot(line.robot, tip_link=calibrated_flange(line.robot))
    opts = C.Options.of(**({} if line.method is None else {"method": line.method}))
    prior = None
    if line.prior:
        from torchcal.use.rundir import check_prior_robot, load_prior

        prior = load_prior(line.prior)
        check_prior_robot(line.prior, robot, line.robot)
    data = read_measurements(
        line.data,
        require_positions=True,
        min_poses=C.MIN_PRIOR_POSES if prior is not None else C.min_poses(robot, opts.split.holdout),
        purpose=f"fleet line {line.name}",
        dof=robot.dof,
        joint_limits=robot.limits,
        robot_name=robot.name,
        joint_types=robot.joint_types,
    )
    _check_robot_line(data, line.robot, robot)
    if prior is None:
        C.check_holdout(data.n, opts.split.holdout)
    return robot, opts, prior, data


def _calibrate(line: Line, out: Path):
    """``torchcal calibrate`` of one line into the run directory ``out`` (calibrate's defaults otherwise)."""
    from torchcal import pipeline as C
    from torchcal.report.rundir import write_run

    robot, opts, prior, data = _line_inputs(line)
    run = C.calibrate(robot, data, opts, robot_spec=line.robot, prior=prior)
    write_run(run, out, inputs=[line.data, *([line.prior] if line.prior else [])])


def calibrate_line(line: Line) -> dict:
    """One task: calibrate ``line`` with one torch thread in a temporary folder; its summary and, where it
    succeeded, the run's files (``files``: relative path -> bytes) for the driver to write. Never raises: a refusal
    (``status`` ``refused``, exit 2 of calibrate) or an internal error (``failed``) is the line's result."""
    t0 = time.perf_counter()
    out: dict = {"name": line.name, "line": line.number, "data": line.data, "robot": line.robot}
    try:
        # one thread and the global generator seeded afresh: a worker that ran other lines before gives the results
        # of this line alone (calibrate seeds its own generators; this guards any draw from the global one)
        with torch_threads(1), torch.random.fork_rng(devices=[]), tempfile.TemporaryDirectory(prefix=TMP) as tmp:
            torch.manual_seed(SEED)
            run = Path(tmp) / "run"
            _calibrate(line, run)
            report = json.loads((run / "report.json").read_text(encoding="utf-8"))
            files = {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
        out.update(status="ok", report=summary_of(report), files=files)
    except TorchcalError as e:
        out.update(status="refused", error=str(e))
    except Exception as e:  # an internal error of one task must not end the fleet: it is that robot's result
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        out.update(status="failed", error=f"internal error: {type(e).__name__}: {first[:300]}")
        out["traceback"] = traceback.format_exc()[-4000:]
    out["seconds"] = time.perf_counter() - t0
    return out


def summary_of(report: dict) -> dict:
    """What the fleet tables of a run's ``report.json``: held-out errors, the global test, what moved since the
    prior."""
    gt = report.get("global_test") or {}
    prior = report.get("prior")
    moved = None
    if isinstance(prior, dict):
        ratio = {r["name"]: r["ratio"] for r in prior.get("parameters", [])}
        moved = [{"name": n, "sigmas": ratio.get(n)} for n in prior.get("moved", [])]
    return {
        "method": report.get("method"),
        "n_train": report.get("n_train"),
        "n_holdout": report.get("n_holdout"),
        "rmse_before_mm": report.get("rmse_before_mm"),
        "rmse_geometric_mm": report.get("rmse_geometric_mm"),
        "rmse_after_mm": report.get("rmse_after_mm"),
        "max_after_mm": report.get("max_after_mm"),
        "global_test_passed": gt.get("passed"),
        "global_test_statistic": gt.get("statistic"),
        "prior": None if prior is None else prior.get("source"),
        "moved": moved,
    }


def verdict(result: dict) -> tuple[bool | None, str]:
    """Whether the line's robot needs a new calibration, and why (module docstring); None for a failed task."""
    if result["status"] != "ok":
        return None, f"no verdict: the task {result['status']}"
    r = result["report"]
    if r["moved"]:
        names = ", ".join(m["name"] for m in r["moved"][:5]) + (" ..." if len(r["moved"]) > 5 else "")
        return True, f"moved since its prior beyond the threshold: {names}"
    if r["global_test_passed"] is False:
        return True, "the model fails the global test: it does not explain these data to their noise"
    if r["prior"] is not None:
        return False, "nothing moved beyond the threshold since its prior"
    return False, "calibrated; the model explains the data to their noise"


def run_serial(lines: list[Line], done: Callable[[dict], None]) -> None:
    """Every line's task in this process, one after another."""
    for ln in lines:
        done(calibrate_line(ln))


def run_ray(
    lines: list[Line],
    done: Callable[[dict], None],
    workers: int | None,
    address: str | None,
    task: Callable[[Line], dict] = calibrate_line,
) -> None:
    """Every line's ``task`` on Ray (:func:`torchcal.sweep.on_ray`): a local instance of ``workers`` CPUs (default:
    this machine's), or the cluster at ``address``; results are handed to ``done`` as they finish. A task whose
    worker died is run again up to :data:`RETRIES` times, then reported failed with Ray's error."""

    def each(i: int, r) -> None:
        if isinstance(r, TaskFailure):  # the worker died RETRIES + 1 times, or the cluster lost the task
            ln = lines[i]
            r = {
                "name": ln.name,
                "line": ln.number,
                "data": ln.data,
                "robot": ln.robot,
                "status": "failed",
                "error": r.error,
            }
        done(r)

    on_ray(task, lines, workers or os.cpu_count() or 1, address, each)


@dataclass
class FleetResult:
    """What :func:`run_fleet` did: the engine (``ray`` or ``serial``), the results by line, the wall time [s]."""

    engine: str
    results: list[dict]
    seconds: float

    def to_dict(self) -> dict:
        rows = []
        for r in self.results:
            need, why = verdict(r)
            rows.append(
                {k: v for k, v in r.items() if k not in ("files", "traceback")}
                | {"needs_calibration": need, "reason": why}
            )
        return {
            "written_by": "torchcal fleet",
            "engine": self.engine,
            "seconds": self.seconds,
            "n_lines": len(rows),
            "n_ok": sum(r["status"] == "ok" for r in rows),
            "n_failed": sum(r["status"] != "ok" for r in rows),
            "needs_calibration": [r["name"] for r in rows if r["needs_calibration"]],
            "rule": RULE,
            "robots": rows,
        }


#: the verdict's rule in words (report.json and report.md)
RULE = (
    "a robot needs a new calibration where a re-check from its prior moved a parameter beyond the prior's threshold "
    "(report.json prior.moved: more than 3 prior sigmas, or released), or where its model fails the global test; a "
    "line whose task failed has no verdict"
)


def _mm(v) -> str:
    return "-" if not isinstance(v, (int, float)) or not math.isfinite(v) else f"{v:.4f}"


def markdown(d: dict) -> str:
    """The fleet summary as markdown: one row per robot."""
    lines = [
        f"# Fleet: {d['n_lines']} robots, {d['n_ok']} calibrated, {d['n_failed']} failed",
        "",
        f"Engine: {d['engine']}; {d['seconds']:.1f} s. Needs a new calibration: "
        + (", ".join(d["needs_calibration"]) or "none")
        + ".",
        "",
        f"Rule: {d['rule']}.",
        "",
        "| robot | status | held-out before [mm] | held-out after [mm] | global test | moved since prior | "
        "needs calibration | why |",
        "|---|---|---:|---:|---|---|---|---|",
    ]
    for r in d["robots"]:
        rep = r.get("report") or {}
        gt = {True: "passed", False: "failed"}.get(rep.get("global_test_passed"), "-")
        moved = rep.get("moved")
        moved = "-" if moved is None else (", ".join(m["name"] for m in moved) or "nothing")
        need = {True: "**yes**", False: "no", None: "?"}[r["needs_calibration"]]
        why = r["reason"] if r["status"] == "ok" else f"{r['reason']}: {r['error']}"
        why = why.replace("|", "/").replace("\n", " ")
        lines.append(
            f"| {r['name']} | {r['status']} | {_mm(rep.get('rmse_before_mm'))} | {_mm(rep.get('rmse_after_mm'))} | "
            f"{gt} | {moved} | {need} | {why} |"
        )
    return "\n".join(lines) + "\n"


def run_fleet(
    manifest: str | os.PathLike,
    out: str | os.PathLike,
    *,
    workers: int | None = None,
    address: str | None = None,
    engine: str | None = None,
    progress: Callable[[dict], None] | None = None,
) -> FleetResult:
    """Calibrate every line of ``manifest`` into ``out/name/`` and write ``out/report.json`` and ``report.md``
    (module docstring); ``out`` is replaced as a whole when everything is written (an earlier torchcal output, or
    absent; anything else is refused before any task runs).

    Args:
        workers: CPUs of a local Ray instance (default: this machine's); address: an existing Ray cluster.
        engine: ``"ray"`` or ``"serial"`` (default: Ray where it is installed).
        progress: called with each line's result as it finishes.
    """
    lines = read_manifest(manifest)
    for problem in missing_inputs(manifest, lines) if address is None else []:
        print(f"torchcal fleet: {problem}; that line will be reported refused, the others run", file=sys.stderr)
    inputs = inputs_of(manifest, lines)
    check_out_dir(out, inputs=inputs)  # before any task: refuse, touching nothing
    engine = engine or ("ray" if ray_available() else "serial")
    if engine not in ("ray", "serial"):
        raise OptionError(f"unknown engine {engine!r}; valid: ray, serial")
    if engine == "serial" and address:
        raise OptionError("--address needs Ray (pip install torchcal[fleet])")
    results: dict[str, dict] = {}

    def done(r: dict) -> None:
        results[r["name"]] = r
        if progress is not None:
            progress(r)

    t0 = time.perf_counter()
    if engine == "ray":
        run_ray(lines, done, workers, address)
    else:
        run_serial(lines, done)
    ordered = [results[ln.name] for ln in lines]
    fleet = FleetResult(engine, ordered, time.perf_counter() - t0)
    _write(fleet, out, inputs)
    return fleet


def _write(fleet: FleetResult, out: str | os.PathLike, inputs: list[str]) -> None:
    with replace_dir(out, kind="fleet", inputs=inputs) as tmp:
        for r in fleet.results:
            for rel, data in (r.get("files") or {}).items():
                target = tmp / r["name"] / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(data)
        d = fleet.to_dict()
        (tmp / "report.json").write_text(json.dumps(d, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        (tmp / "report.md").write_text(markdown(d), encoding="utf-8")


def print_progress(r: dict) -> None:
    """One line on stderr per finished task (a failed one even with ``--quiet``)."""
    if r["status"] == "ok":
        _console.info(f"torchcal fleet: {r['name']}: held-out {_mm(r['report']['rmse_after_mm'])} mm")
    else:
        print(_console.one_line(f"torchcal fleet: {r['name']}: {r['status']}: {r['error']}"), file=sys.stderr)
