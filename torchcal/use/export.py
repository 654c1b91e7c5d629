"""Exporting a finished run to the files other software reads: the calibrated URDF, the UR ROS 2 driver's kinematics
parameter file (``ur-ros2``) and a DH / MDH robot file that ``--robot`` loads back (``dh``); and checking such a file
against its run (:func:`check_export`).

A file carries the geometry (the URDF also the lever arm and the tracker pose); none can carry the non-geometric
effects. So for a run with effects the chain written is by default the run's stand-alone geometry
(:mod:`torchcal.pipeline.standalone`: the one of its kinematic calibration and of a refit to the full model that
predicts the held-out rows better alone), not the geometry fitted together with the effects, which leans on them;
``geometry="cofitted"`` writes that one for users who apply the effects themselves. Every file's header (and
:attr:`Exported.summary`, which the CLI prints) gives the held-out error of the chain in the file alone and of the full
run.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import torch

from torchcal._inputs import check_regular, load_json, read_text_bounded
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.robot import load_robot
from torchcal.robot.export import write_text, write_urdf
from torchcal.robot.export_formats import dh_yaml, ur_ros2_yaml
from torchcal.robot.load import calibrated_flange
from torchcal.stats import rmse
from torchcal.use.rundir import load_holdout, load_model, load_standalone

Tensor = torch.Tensor
#: the formats ``torchcal export --format`` writes
FORMATS = ("ur-ros2", "dh", "urdf")
#: which geometry an export of a run with effects carries (``--geometry``)
GEOMETRIES = ("standalone", "cofitted")
#: the formats ``check-export`` reads back
CHECKED_FORMATS = {".yaml": "dh", ".yml": "dh", ".urdf": "urdf"}
#: the largest distance [mm] at which a file still reproduces a run's chain: the exports write every number in full
#: (repr), so theirs is ~1e-13 mm; 1 um leaves room for a file rounded to micrometres by other software
MATCH_TOLERANCE_MM = 1e-3
_UR_ROS2 = re.compile(r"^kinematics\s*:", re.MULTILINE)


@dataclass(frozen=True)
class Exported:
    """What :func:`export_run` wrote.

    Attributes:
        model: the model whose chain (instrument pose and lever arm) the file carries; no effects.
        which: ``run`` (a run without effects: its own geometry), ``standalone`` or ``cofitted``.
        source: for ``standalone``: the candidate chosen (``kinematic`` or ``refit``), else None.
        rmse_mm: the held-out RMSE of the chain in the file alone [mm]; None where the run does not say.
        rmse_full_mm: the full run's held-out RMSE [mm]; None where the run does not say.
        left_out: labels of the run's effects the file lacks.
    """

    model: MeasurementModel
    which: str
    source: str | None
    rmse_mm: float | None
    rmse_full_mm: float | None
    left_out: tuple[str, ...]

    @property
    def summary(self) -> str:
        """The line the file's header and stderr give: the held-out error of the file alone and of the full run."""

        def mm(v):
            return "not measured" if v is None else f"{v:.4f} mm held-out"

        if self.which == "run":
            return f"this chain alone is the full run: {mm(self.rmse_mm)}"
        what = {
            "standalone": f"the run's stand-alone geometry ({self.source}), the best of it without the effects",
            "cofitted": "the geometry fitted together with the effects: apply them yourself",
        }[self.which]
        return (
            f"this chain alone: {mm(self.rmse_mm)} ({what}); the full run: {mm(self.rmse_full_mm)}; "
            "torchcal compensate applies the rest"
        )


def left_out(model: MeasurementModel) -> list[str]:
    """Labels of the model's parts that a robot file (geometry, lever arm, tracker pose only) cannot carry."""
    return [e.label() for e in model.effects]


def _report_rmse(run: Path) -> float | None:
    path = run / "report.json"
    if not path.exists():
        return None
    rep = load_json(path, "report.json", lambda m: OptionError(f"{run}: report.json {m}"))
    v = rep.get("rmse_after_mm") if isinstance(rep, dict) else None
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def exported_model(run: str | Path, geometry: str = "standalone") -> Exported:
    """The model whose chain an export of the run directory ``run`` carries, and its numbers (module docstring).

    A run written before stand-alone geometries were kept exports its co-fitted geometry, said so."""
    if geometry not in GEOMETRIES:
        raise OptionError(f"--geometry must be one of {', '.join(GEOMETRIES)}, got {geometry!r}")
    run = Path(run)
    model, meta = load_model(run)
    left = tuple(left_out(model))
    full = _report_rmse(run)
    if not left:
        return Exported(MeasurementModel(model.robot), "run", None, full, full, ())
    info = meta.get("standalone") if isinstance(meta.get("standalone"), dict) else {}

    def num(key):
        v = info.get(key)
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None

    cofitted = MeasurementModel(model.robot)
    alone = load_standalone(run, model) if geometry == "standalone" else None
    if alone is None:
        return Exported(cofitted, "cofitted", None, num("rmse_cofitted_mm"), num("rmse_full_mm") or full, left)
    source = info.get("source") if isinstance(info.get("source"), str) else "?"
    return Exported(alone, "standalone", source, num("rmse_holdout_mm"), num("rmse_full_mm") or full, left)


def export_run(run: str | Path, fmt: str, out_file: Path, geometry: str = "standalone") -> Exported:
    """Write the calibrated robot of the run directory ``run`` as ``fmt`` (one of :data:`FORMATS`) to ``out_file``:
    the chain of :func:`exported_model` (``geometry``: one of :data:`GEOMETRIES`), its header saying what it is.

    A format the robot cannot be written in (``ur-ros2`` of a robot that is not a UR arm) is refused before any
    folder is made; ``out_file``'s folder is made as ``predict`` and ``plan`` make theirs.
    """
    if fmt not in FORMATS:
        raise ValueError(f"export format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    ex = exported_model(run, geometry)
    robot = ex.model.robot
    notes = [ex.summary]
    if ex.left_out:
        notes.append(f"NOT in this file: {', '.join(ex.left_out)} (torchcal compensate {run} applies them)")
    if ex.which == "cofitted" and geometry == "standalone":
        notes.append(_no_standalone(Path(run)))
    text = None
    if fmt != "urdf":
        write = ur_ros2_yaml if fmt == "ur-ros2" else dh_yaml
        text = f"# written_by: torchcal export\n{write(robot, tuple(notes))}"
    else:
        tip = robot.link_names[-1]
        notes.append(
            f"The run's robot ends at link '{tip}' (the flange); 'probe' beyond it is the run's lever arm. Loaded "
            f"as a torchcal robot this file ends at '{tip}'; other loaders take the deepest leaf 'probe' unless "
            f"asked for '{tip}'."
        )
    out_file.parent.mkdir(parents=True, exist_ok=True)
    if text is None:
        write_urdf(robot, out_file, notes=notes)
    else:
        write_text(out_file, text)
    return ex


def _no_standalone(run: Path) -> str:
    """Why a run with effects exports its co-fitted geometry though the stand-alone one was asked for."""
    meta = load_json(run / "model.json", "model.json", lambda m: OptionError(f"{run}: model.json {m}"))
    station = meta.get("station") if isinstance(meta, dict) else None
    if isinstance(station, dict):
        return (
            f"this re-stationed run keeps no stand-alone geometry (that of {station.get('from_run')} is of the old "
            "placement): the chain above is the co-fitted one; the chain of the run it came from stands alone"
        )
    return "this run keeps no stand-alone geometry (written before it existed): the co-fitted one; calibrate again"


@dataclass(frozen=True)
class ExportCheck:
    """What :func:`check_export` found.

    Attributes:
        fk_gap_mm: the largest distance between the file's and the run's exported chain [mm], at the flange and at
            the probe, over the held-out rows' joints.
        rmse_mm: the held-out RMSE of the file's chain with the run's instrument pose and lever arm [mm].
        expected_mm: the held-out RMSE the run recorded for that chain [mm] (None where it recorded none).
        n: the held-out rows.
        tip: the link the file's chain was loaded to.
        which: see :attr:`Exported.which`.
    """

    fk_gap_mm: float
    rmse_mm: float
    expected_mm: float | None
    n: int
    tip: str
    which: str

    @property
    def matches(self) -> bool:
        """Whether the file reproduces the run's chain (within :data:`MATCH_TOLERANCE_MM`)."""
        return self.fk_gap_mm <= MATCH_TOLERANCE_MM


def _positions(model: MeasurementModel, T: Tensor, rows: dict[str, Tensor]) -> Tensor:
    """Probe positions ``(N, 3)`` [m] in the tracker frame of flange poses ``T (N, 4, 4)``, placed by ``model``'s
    instrument pose and lever arm of each row's station and probe."""
    robot = model.robot
    Ti = robot.instrument.rows(rows.get("station"))
    t = robot.tool.rows(rows.get("probe"))
    p_base = (T[:, :3, :3] @ t.unsqueeze(-1)).squeeze(-1) + T[:, :3, 3]
    return (Ti[..., :3, :3] @ p_base.unsqueeze(-1)).squeeze(-1) + Ti[..., :3, 3]


def check_export(run: str | Path, file: str | Path, geometry: str | None = None) -> ExportCheck:
    """Load an exported file back as ``--robot`` loads it and compare it with the run it was written from: with the
    chain ``geometry`` names (one of :data:`GEOMETRIES`), by default the one of them closest to the file.

    Raises:
        OptionError: the file is no regular file, not a DH YAML or URDF file (by its exact ending, as ``--robot``
            reads it; a UR ROS 2 file is named as such), the run keeps no held-out rows, or the file's chain has
            another number of joints. A file whose chain differs is no error: see :attr:`ExportCheck.matches`.
    """
    file, run = Path(file), Path(run)

    def error(m: str) -> OptionError:
        return OptionError(f"{file}: {m}")

    check_regular(file, "robot description", error)
    if file.suffix not in CHECKED_FORMATS:
        # --robot tells a description by its exact ending: a file that check-export read as '.URDF' would not load
        rename = f"; rename it to end in {file.suffix.lower()}" if file.suffix.lower() in CHECKED_FORMATS else ""
        raise OptionError(
            f"{file}: check-export reads DH files (.yaml, .yml) and URDF files (.urdf), by their ending as --robot "
            f"loads them{rename}"
        )
    if CHECKED_FORMATS[file.suffix] == "dh" and _UR_ROS2.search(read_text_bounded(file, "robot description", error)):
        raise OptionError(
            f"{file}: a UR ROS 2 kinematics file (export --format ur-ros2, a top-level 'kinematics' key), which "
            "--robot does not load: check the run's DH or URDF export instead (export --format dh or urdf)"
        )
    tip = calibrated_flange(file) if file.suffix == ".urdf" else None
    loaded = load_robot(file, tip_link=tip) if tip else load_robot(file)
    checks = [_check_one(run, loaded, g) for g in ((geometry,) if geometry is not None else GEOMETRIES)]
    return min(checks, key=lambda c: c.fk_gap_mm)


def _check_one(run: Path, loaded, geometry: str) -> ExportCheck:
    ex = exported_model(run, geometry)
    rows = load_holdout(run, ex.model.robot.dof)
    if rows is None:
        raise OptionError(f"{run}: the run keeps no held-out rows (holdout.pt); calibrate again to check its exports")
    if loaded.dof != ex.model.robot.dof:
        raise OptionError(f"{loaded.source}: its chain has {loaded.dof} joints, the run's robot {ex.model.robot.dof}")
    for k, names in (("station", ex.model.robot.stations), ("probe", ex.model.robot.probes)):
        if k in rows and (not names or int(rows[k].max()) >= len(names) or int(rows[k].min()) < 0):
            raise OptionError(f"{run}: holdout.pt's {k} indices do not fit the run's {k}s")
    with torch.no_grad():
        T_file, T_run = loaded(rows["q"]), ex.model.robot(rows["q"])
        p_file, p_run = _positions(ex.model, T_file, rows), _positions(ex.model, T_run, rows)
        gap = max(
            float((T_file[:, :3, 3] - T_run[:, :3, 3]).norm(dim=-1).max()), float((p_file - p_run).norm(dim=-1).max())
        )
        err = rmse((p_file - rows["p"]).norm(dim=-1))
    return ExportCheck(gap * 1e3, err * 1e3, ex.rmse_mm, int(rows["q"].shape[0]), loaded.link_names[-1], ex.which)


__all__ = [
    "CHECKED_FORMATS",
    "FORMATS",
    "GEOMETRIES",
    "MATCH_TOLERANCE_MM",
    "ExportCheck",
    "Exported",
    "check_export",
    "export_run",
    "exported_model",
    "left_out",
]
