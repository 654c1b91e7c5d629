"""What a plan is made for and what it writes: the model, noise and scene from a calibrated run or a robot, the
candidates (a file's distinct poses with their load columns, or sampled where the tracker sees the probe), and the
planned poses with the plan's JSON and Markdown beside them. :mod:`torchcal.use.plan` chooses the poses;
``torchcal plan`` is these steps with their arguments read from the command line."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import torch
from torch import Tensor

from torchcal._method import DEFAULT_METHOD
from torchcal.data.load import is_load_column
from torchcal.data.measurements import Measurements
from torchcal.effects import MeasurementModel
from torchcal.errors import OptionError
from torchcal.use.plan import (
    Plan,
    candidate_region,
    distinct_index,
    loads_summary,
    plan_loads,
    scene_of,
)

#: the tracker's noise per axis [m] and a joint's [rad] a plan assumes without a run (the simulator's defaults)
SIGMA_TRACKER = 15e-6
SIGMA_JOINT = math.radians(0.0005)


@dataclasses.dataclass
class PlanSetting:
    """What a plan is made for: the model (a run's calibrated one at one station and probe, or a robot's nominal),
    the robot's name as the planned file's header gives it, the method the poses will be calibrated with, the noise
    [m, rad], the variance factor the run's residuals had (1 without a run) and the scene (tracker position and
    lever arm [m], ``None``: the sampler's defaults)."""

    model: MeasurementModel
    robot_name: str
    method: str
    sigma_tracker: float = SIGMA_TRACKER
    sigma_joint: float = SIGMA_JOINT
    s0_sq: float = 1.0
    tracker: Tensor | None = None
    lever: Tensor | None = None

    def with_scene(self, tracker=None, lever=None) -> PlanSetting:
        """This setting with the tracker position and lever arm [m] replaced where given (sequences of three)."""

        def given(v):
            return torch.tensor(v, dtype=torch.float64, device=self.model.robot.device)

        return dataclasses.replace(
            self,
            tracker=self.tracker if tracker is None else given(tracker),
            lever=self.lever if lever is None else given(lever),
        )


def robot_setting(robot: str, base_link=None, tip_link=None, method: str | None = None) -> PlanSetting:
    """A plan for ``robot`` (a built-in name or a description file; ``base_link``/``tip_link`` for a URDF) at its
    nominal geometry, with the default noise and scene; ``method`` None: the default method."""
    from torchcal.robot import load_robot

    model = MeasurementModel(load_robot(robot, base_link=base_link, tip_link=tip_link))
    return PlanSetting(model, robot, method or DEFAULT_METHOD.value)


def run_setting(
    run: str | Path, robot: str | None = None, method: str | None = None, station=None, probe=None
) -> PlanSetting:
    """A plan with the run's calibrated model (at ``station`` / ``probe`` of a run of several), robot file, method
    (``method`` overrides it), noise, variance factor and scene (tracker position, lever arm). ``robot`` given must be
    the run's: the run's model is what is planned for, and another robot would be ignored without a word."""
    from torchcal.data.header import robot_key
    from torchcal.use.rundir import at_station, load_model, own_names
    from torchcal.use.station import station_options

    model, meta = load_model(run)
    if robot is not None and robot_key(robot) not in {robot_key(meta["robot_file"]), robot_key(model.robot.name)}:
        raise OptionError(
            f"robot {robot} (--robot) is not the robot of the run {run} ({meta['robot_file']}); the plan is made for "
            "the run's calibrated robot: drop it, or plan for that robot without the run (--run)"
        )
    station, probe = own_names(meta, station, probe)
    if model.robot.stations or model.robot.probes:  # plan for one placement and probe of a several-station run
        model, _, _ = at_station(model, station, probe)
    elif station is not None or probe is not None:
        raise OptionError(
            "station and probe (--station, --probe) name one of a run's several stations or probes; this run has one"
        )
    so = station_options(run)
    s0_sq = 1.0
    report = Path(run) / "report.json"
    if report.exists():
        s0 = json.loads(report.read_text(encoding="utf-8")).get("parameters", {}).get("sigma0_sq")
        s0_sq = float(s0) if isinstance(s0, (int, float)) and math.isfinite(s0) and s0 > 0 else 1.0
    tracker, lever = scene_of(model)
    return PlanSetting(
        model,
        meta["robot_file"],
        method or meta.get("method") or "auto",
        so.sigma_tracker,
        so.sigma_joint,
        s0_sq,
        tracker,
        lever,
    )


def file_candidates(data: Measurements) -> tuple[Tensor, dict[str, Tensor], int]:
    """A candidates file's distinct poses ``(M, dof)`` (a file of several probes has a row per probe and pose: a plan
    chooses poses), their load columns (each pose's payload and torques, kept in the planned rows) and how many rows
    repeated another row's joints."""
    rows = distinct_index(data.q)
    q = data.q[rows.to(data.q.device)]
    loads = {k: v[rows] for k, v in data.extra.items() if is_load_column(k)}
    return q, loads, data.n - len(q)


def sampling_region(setting: PlanSetting, in_region: bool) -> tuple[Tensor | None, str]:
    """Where a plan samples its candidates (:func:`~torchcal.use.plan.sample_candidates`' ``region``) and the words
    that say so. ``in_region`` (a run's setting): within the run's calibrated region, its narrow joints opened to their
    limits (only poses that move them tell what the run held near nominal: :func:`~torchcal.use.plan.candidate_region`);
    else the joint limits (None, no words)."""
    region, narrow = candidate_region(setting.model) if in_region else (None, [])
    within = " within the run's calibrated region" if region is not None else ""
    if narrow:
        within += f" ({', '.join(f'q{j}' for j in narrow)}, narrow in the run, over their limits)"
    return region, within


def side_paths(out: str | Path) -> dict[str, Path]:
    """The plan's JSON and Markdown beside its poses ``out``: its name with ``.plan.json`` and ``.plan.md``."""
    stem = Path(out).with_suffix("")
    return {ext: Path(f"{stem}.plan.{ext}") for ext in ("json", "md")}


def write_plan(
    out: str | Path,
    plan: Plan,
    *,
    robot_name: str,
    source: str,
    loads: dict[str, Tensor] | None = None,
    payload_levels=None,
    poses_label: str | None = None,
    written_by: str = "torchcal plan",
) -> dict[str, Path]:
    """Write the planned poses to ``out`` (with the candidates' ``loads`` columns at the chosen poses, or
    ``payload_levels`` [kg] in turn, which replace a payload the candidates had) and the plan's JSON and Markdown
    beside it (:func:`side_paths`, returned). ``source`` says where the candidates came from; ``poses_label`` is how
    the JSON names the poses file (default ``out``)."""
    from torchcal.data import write_measurements

    side = side_paths(out)
    index = plan.index.detach().cpu()
    extra = {k: v.detach().cpu()[index] for k, v in (loads or {}).items()}
    if payload_levels is not None:
        extra = {k: v for k, v in extra.items() if not k.startswith("payload")}
        extra["payload"] = plan_loads(len(index), payload_levels)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"robot": Path(str(robot_name)).name, "planned_from": source}
    write_measurements(out, Measurements(q=plan.q.detach().cpu(), extra=extra), meta=meta, written_by=written_by)
    summary = {"written_by": written_by, "poses": str(out if poses_label is None else poses_label)}
    summary |= {"candidates": source} | plan.to_dict()
    if "payload" in extra:
        summary["loads"] = loads_summary(extra["payload"])
    side["json"].write_text(json.dumps(summary, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    side["md"].write_text(f"# written_by: {written_by}\n\n" + plan.markdown(), encoding="utf-8")
    return side
