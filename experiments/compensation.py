"""Does compensation close the gap on the robot? A closed simulation experiment (issue 15 item 3).

1. Simulate a laser-tracker campaign whose robot has effects the nominal model does not declare
   (:func:`torchcal.sim.simulate`; by default joint-2 compliance and a smooth field, as the demo).
2. Calibrate it (the default closed-loop method). Its stages give three models: ``nominal`` (nominal
   geometry, fitted tracker pose and lever arm), ``geometric`` (the kinematic calibration) and the final
   model (geometry + the effects found).
3. Command fresh targets, never seen in calibration, in the tracker frame: static poses and a program of
   targets along a continuous path. The targets are where the nominal controller, with the true tool
   centre point, would put the probe for a program's joints, as seen by the real (true) tracker. Each
   model turns them into joint commands with :func:`torchcal.use.compensate.compensate`, started from the
   program's joints.
4. Send the commands to the *simulated true robot* (the simulator's truth model: true geometry, tracker
   pose, lever arm and effects; no measurement noise) and measure how far its probe lands from the target.

Along the path the corrections must be smooth: the largest change of the correction between neighbouring
samples is compared with the largest correction.

With a 6-D probe (``orientation_deg``: the campaign measures the probe frame's orientation with that noise, and the
calibration fits it), the program also means a tool orientation: the nominal controller's flange orientation turned
by the true probe frame, seen by the true tracker. The full model then compensates twice, positions only (the tool
free to turn) and position with orientation (``compensate(..., orientations=...)``), and each row reports the true
robot's orientation error beside its position error (``orientation``: RMS and largest angle [deg]). A third 6-D
row gives the solver the simulator's true model instead: what no calibration can beat on these targets. Next to a
singularity (a stretched or folded elbow, a wrist or shoulder near its singular pose) the pose the nominal robot
reaches may lie out of the true robot's reach on the program's configuration; there the true model too commands the
position first, and its cut (:func:`six_d_summary`) bounds the full model's.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch

from torchcal.effects.base import Context, motion_direction
from torchcal.effects.model import MeasurementModel
from torchcal.robot import load_robot
from torchcal.robot import transforms as tf
from torchcal.sim import EffectSpec, SimConfig, simulate
from torchcal.sim.poses import Scene, random_poses, trajectory
from torchcal.use.compensate import Status, compensate, configuration_sign, rotation_miss

F64 = torch.float64
DEFAULT_EFFECTS = ("compliance:2=60um", "field=0.05mm")
POSITION_ROW, SIX_D_ROW = "full-model compensation", "full-model 6-D compensation"
TRUE_MODEL_ROW = "true-model 6-D compensation"


@dataclass
class ExperimentConfig:
    robot: str = "ur5"
    seed: int = 0
    poses: int = 800
    test_poses: int = 200
    effects: tuple[str, ...] = DEFAULT_EFFECTS
    static_targets: int = 500
    path_targets: int = 1000
    method: str | None = None  # calibration method (None: the default)
    orientation_deg: float | None = None  # a 6-D probe's orientation noise [deg] (None: a reflector, positions only)
    orientation_weight: float = 0.1  # the 6-D solve's [m/rad] (compensate's orientation_weight)
    extra: dict = field(default_factory=dict)


def _errors_mm(e: torch.Tensor) -> dict:
    return {"rmse_mm": float(e.square().mean().sqrt()) * 1e3, "max_mm": float(e.max()) * 1e3}


def true_errors(truth: MeasurementModel, q: torch.Tensor, targets: torch.Tensor, ctx_kw: dict) -> torch.Tensor:
    """Distance ``(N,)`` [m] from each target to where the true robot puts the probe for the commands ``q``."""
    with torch.no_grad():
        return (truth(Context(q=q, **ctx_kw)) - targets).norm(dim=-1)


def true_turns(truth: MeasurementModel, q: torch.Tensor, R_target: torch.Tensor, ctx_kw: dict) -> torch.Tensor:
    """Angle ``(N,)`` [rad] between each target orientation and the true robot's probe frame for the commands ``q``."""
    with torch.no_grad():
        return rotation_miss(R_target, truth.orientation(Context(q=q, **ctx_kw)))


def _angles_deg(a: torch.Tensor) -> dict:
    return {"rms_deg": math.degrees(float(a.square().mean().sqrt())), "max_deg": math.degrees(float(a.max()))}


def _row(
    truth: MeasurementModel,
    nominal,
    model: MeasurementModel | None,
    targets: torch.Tensor,
    q_prog: torch.Tensor,
    path: bool,
    R_target: torch.Tensor | None = None,
    six_d: bool = False,
    weight: float = 0.1,
) -> tuple[dict, dict]:
    """Where the true robot puts the probe for the commands of ``model``'s compensation of ``targets`` (None: the
    program's own joints ``q_prog``); with the compensation's status, time and branch, and on a path its smoothness.
    With ``R_target`` (the program's tool orientations in the tracker frame ``(N, 3, 3)``) also how far the true
    robot turns the probe from them; ``six_d`` compensates them too, an orientation error weighing ``weight`` [m/rad].

    Returns:
        The row's entry, and per target: ``turns`` ``(N,)`` [rad] (None without ``R_target``) and, for ``six_d``,
        ``reached`` ``(N,)`` bool (the model reaches the full pose on the program's branch; else None).
    """
    ctx_kw = {"direction": motion_direction(q_prog)} if path else {}
    if model is None:
        entry = _errors_mm(true_errors(truth, q_prog, targets, ctx_kw))
        turns = None if R_target is None else true_turns(truth, q_prog, R_target, ctx_kw)
        if turns is not None:
            entry["orientation"] = _angles_deg(turns)
        return entry, {"turns": turns, "reached": None}
    t1 = time.perf_counter()
    R = R_target if six_d else None
    res = compensate(model, targets, q_prog, context={"trajectory": path}, orientations=R, orientation_weight=weight)
    secs = time.perf_counter() - t1
    q_cmd = res.q
    s0 = configuration_sign(nominal, q_prog)
    branch = int(((configuration_sign(nominal, q_cmd) != s0) & ((q_cmd - q_prog).abs().max(-1).values > 0.05)).sum())
    entry = _errors_mm(true_errors(truth, q_cmd, targets, ctx_kw))
    turns, reached = None, None
    if R_target is not None:
        turns = true_turns(truth, q_cmd, R_target, ctx_kw)
        entry["orientation"] = _angles_deg(turns)
        if six_d:  # the rows whose full pose the model reaches; those next to a singularity go position first
            reached = torch.tensor([s is Status.CONVERGED for s in res.status])
            entry["orientation_reached_rows"] = _angles_deg(turns[reached]) if bool(reached.any()) else None
            entry["position_first_rows"] = int(res.position_only.sum())
    entry.update(
        {
            "status": res.counts(),
            "seconds": secs,
            "wrong_branch": branch,
            "model_miss_max_mm": float(res.miss.max()) * 1e3,
        }
    )
    if path:
        corr = q_cmd - q_prog
        entry["largest_correction_rad"] = float(corr.abs().max())
        entry["largest_correction_jump_rad"] = float(torch.diff(corr, dim=0).abs().max())
        entry["smooth"] = entry["largest_correction_jump_rad"] <= entry["largest_correction_rad"]
        entry["largest_joint_step_rad"] = float(torch.diff(q_cmd, dim=0).abs().max())
        entry["program_largest_joint_step_rad"] = float(torch.diff(q_prog, dim=0).abs().max())
    return entry, {"turns": turns, "reached": reached}


def _rows(truth, nominal, models: dict, targets, q_prog, path: bool, R_target, weight: float) -> tuple[dict, dict]:
    """:func:`_row` of each of ``models`` (name: (model, six_d)): the entries and the per-target values by name."""
    rows, per_target = {}, {}
    for name, (model, six) in models.items():
        rows[name], per_target[name] = _row(truth, nominal, model, targets, q_prog, path, R_target, six, weight)
    return rows, per_target


def run(cfg: ExperimentConfig) -> dict:
    """Run the experiment (module docstring); returns the table and checks as plain numbers."""
    from torchcal import pipeline as C

    sim = SimConfig(
        robot=cfg.robot,
        poses=cfg.poses,
        test_poses=cfg.test_poses,
        seed=cfg.seed,
        effects=[EffectSpec.parse(e) for e in cfg.effects],
        orientation_sigma_deg=cfg.orientation_deg,
    )
    campaign = simulate(sim)
    truth = campaign.model
    t0 = time.perf_counter()
    calib = C.calibrate(
        cfg.robot, campaign.train, C.Options(seed=cfg.seed, **({"method": cfg.method} if cfg.method else {}))
    )
    t_cal = time.perf_counter() - t0
    stages = {s.name: s.model for s in calib.stages}
    models = {
        "nominal commands": (None, False),
        "geometry-only compensation": (stages["geometric"], False),
        POSITION_ROW: (calib.model, False),
    }
    six_d = cfg.orientation_deg is not None
    if six_d:
        models[SIX_D_ROW] = (calib.model, True)
        # the same solver given the simulator's own model: the cut no calibration can beat on these targets
        models[TRUE_MODEL_ROW] = (truth, True)
    with torch.no_grad():
        pred = calib.model(Context.from_measurements(campaign.test, trajectory=False))
    held_out = (pred - campaign.test.p).norm(dim=-1)

    nominal = load_robot(cfg.robot)
    T_true = truth.robot.T_tracker_base().detach()
    tracker_in_base = tf.invert(T_true)[:3, 3]
    lever_nominal = torch.tensor(sim.lever_arm, dtype=F64)
    # the program's tool centre point is the real probe: the nominal baseline then errs by the geometry and
    # the effects only, not by a mis-measured tool
    lever_true = truth.robot.t_flange_probe().detach()
    g = torch.Generator().manual_seed(cfg.seed + 7919)  # fresh poses, independent of the campaign's
    scene = Scene(nominal, tracker_in_base, lever_nominal, sim.sight)
    programs = {
        "static": random_poses(scene, cfg.static_targets, g),
        "path": trajectory(scene, cfg.path_targets, g),
    }
    out = {
        "config": {
            "robot": cfg.robot,
            "seed": cfg.seed,
            "effects": list(cfg.effects),
            "calibration_poses": cfg.poses,
            "method": calib.options.method,
            "orientation_weight": cfg.orientation_weight if six_d else None,
        },
        "calibration_seconds": t_cal,
        "effects_found": [{"kind": e["kind"], "joint": e["joint"]} for e in calib.effects_report],
        "held_out_prediction": _errors_mm(held_out),
        "targets": {},
    }
    for kind, q_prog in programs.items():
        # the point the program means: the nominal controller's probe position, in the true tracker frame (and its
        # tool orientation: the nominal flange turned by the true probe frame)
        with torch.no_grad():
            T_prog = nominal.forward(q_prog)
            targets = tf.transform_points(T_true, tf.transform_points(T_prog, lever_true))
            R_target = T_true[:3, :3] @ T_prog[..., :3, :3] @ truth.robot.tool_rotation.matrix() if six_d else None
        rows, per_target = _rows(
            truth, nominal, models, targets, q_prog, kind == "path", R_target, cfg.orientation_weight
        )
        out["targets"][kind] = {"n": len(q_prog), "rows": rows}
        if six_d:
            out.setdefault("six_d", {})[kind] = _six_d(
                truth, rows, per_target, targets, R_target, q_prog, kind == "path"
            )
    full = [out["targets"][k]["rows"][POSITION_ROW]["rmse_mm"] for k in programs]
    out["ratio_to_held_out"] = {k: v / out["held_out_prediction"]["rmse_mm"] for k, v in zip(programs, full)}
    out["branch_check"] = branch_check(calib.model, campaign)
    return out


def _six_d(truth, rows: dict, per_target: dict, targets, R_target, q_prog, path: bool) -> dict:
    """:func:`six_d_summary` of one program, with :func:`true_pose_nearby` of the targets the true model misses."""
    out = six_d_summary(rows, per_target)
    missed = torch.nonzero(~per_target[TRUE_MODEL_ROW]["reached"]).flatten()
    out["true_pose_within_check"] = true_pose_nearby(truth, targets, R_target, q_prog, missed, path)
    return out


def six_d_summary(rows: dict, per_target: dict) -> dict:
    """6-D against position-only compensation by the full model on one program, and what bounds it.

    ``position_ratio``: the true robot's position RMSE, 6-D / position-only (issue 38 asks at most 1.1);
    ``orientation_cut``: its orientation RMS, position-only / 6-D (issue 38 asks at least 5). The bound: the same
    6-D solve given the simulator's true model (``true_model_cut``, the cut no calibration can beat with this solver);
    ``true_model_reaches``, the targets whose full pose the true robot reaches on the program's branch (the others lie
    next to a singularity, where the pose the nominal robot reaches is out of the true robot's reach there); and
    ``cut_where_true_model_reaches``, the full model's cut on those targets alone.

    Args:
        rows: a program's rows by name (:func:`_row`'s entries).
        per_target: the same names' per-target ``turns`` and ``reached`` (:func:`_row`).
    """
    pos, six, best = rows[POSITION_ROW], rows[SIX_D_ROW], rows[TRUE_MODEL_ROW]
    reach = per_target[TRUE_MODEL_ROW]["reached"]
    turns_pos, turns_six = per_target[POSITION_ROW]["turns"], per_target[SIX_D_ROW]["turns"]
    out = {
        "position_ratio": six["rmse_mm"] / pos["rmse_mm"],
        "orientation_cut": pos["orientation"]["rms_deg"] / six["orientation"]["rms_deg"],
        "true_model_cut": pos["orientation"]["rms_deg"] / best["orientation"]["rms_deg"],
        "true_model_reaches": int(reach.sum()),
        "cut_where_true_model_reaches": None,
    }
    if bool(reach.any()):
        out["cut_where_true_model_reaches"] = _rms(turns_pos[reach]) / _rms(turns_six[reach])
    return out


def true_pose_nearby(
    truth: MeasurementModel,
    targets: torch.Tensor,
    R_target: torch.Tensor,
    q_prog: torch.Tensor,
    rows: torch.Tensor,
    path: bool,
    starts: int = 32,
    reach: float = 0.3,
) -> int:
    """How many of ``rows`` (targets whose full pose the true model's 6-D compensation misses) have one the true robot
    reaches within :func:`compensate`'s configuration check of the program's joints after all: a solve that misses
    only because it stalls is told apart from a pose that is not there.

    Each row is solved with the true model from ``starts`` random joints within ``reach`` [rad] of the program's (no
    check on the way, up to 100 iterations); a solution counts where it converged, lies within ``reach`` of the
    program's joints and on their branch (the sign of ``det J``, or a move of at most 0.05 rad).
    """
    if not len(rows):
        return 0
    g = torch.Generator().manual_seed(len(rows))
    q0 = q_prog[rows].repeat(starts, 1)
    q0 = q0 + (torch.rand(q0.shape, generator=g, dtype=F64) - 0.5) * 2 * reach
    context = {"direction": motion_direction(q_prog)[rows].repeat(starts, 1)} if path else None
    res = compensate(
        truth,
        targets[rows].repeat(starts, 1),
        q0,
        context=context,
        orientations=R_target[rows].repeat(starts, 1, 1),
        max_iter=100,
        max_joint_change=math.inf,
        branch_tol=math.inf,
    )
    q_start = q_prog[rows].repeat(starts, 1)
    moved = (res.q - q_start).abs().max(-1).values
    same = configuration_sign(truth.robot, res.q) == configuration_sign(truth.robot, q_start)
    converged = torch.tensor([s is Status.CONVERGED for s in res.status])
    found = converged & (moved <= reach) & (same | (moved <= 0.05))
    return int(found.reshape(starts, len(rows)).any(dim=0).sum())


def _rms(a: torch.Tensor) -> float:
    return float(a.square().mean().sqrt())


def branch_check(model: MeasurementModel, campaign, n: int = 1000) -> dict:
    """Compensate the campaign's own measured points from their joints: wrong-branch solutions and timing.

    Wrong branch: the elbow (sign of sin q3), wrist (sign of sin q5) or shoulder (side of the wrist centre
    relative to the base axis) of a UR-type arm differs from the start's where the start is not at that
    singularity, or the 6 x 6 Jacobian's determinant changes sign with a move larger than 0.05 rad.
    """
    q0 = torch.cat([campaign.train.q, campaign.test.q])[:n]
    p = torch.cat([campaign.train.p, campaign.test.p])[:n]
    t1 = time.perf_counter()
    res = compensate(model, p, q0)
    secs = time.perf_counter() - t1
    robot = model.robot
    moved = (res.q - q0).abs().max(-1).values
    det_flip = (configuration_sign(robot, res.q) != configuration_sign(robot, q0)) & (moved > 0.05)
    wrong = det_flip.clone()
    if robot.dof == 6:
        for j in (2, 4):
            s0, s1 = torch.sin(q0[:, j]), torch.sin(res.q[:, j])
            wrong |= (torch.sign(s0) != torch.sign(s1)) & (s0.abs() > 1e-2)
    return {
        "n": len(q0),
        "seconds": secs,
        "status": res.counts(),
        "wrong_branch": int(wrong.sum()),
        "largest_joint_move_rad": float(moved.max()),
        "converged_fraction": len(res.rows(Status.CONVERGED)) / len(q0),
    }
