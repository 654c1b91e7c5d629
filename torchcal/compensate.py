"""Compensation: the joint commands that put the probe where it is wanted, by the full calibrated model.

A calibration predicts where the probe goes for given joints; a robot is used the other way round. For
desired probe positions (targets) :func:`compensate` finds joints ``q`` with ``model(q) = target``, where
``model`` is everything the run learned: geometry, instrument pose, lever arm, named effects and the learned
correction. Only the controller's nominal kinematics then run on the robot; the corrections live in the
commanded joints.

Method: damped Gauss-Newton (Levenberg-Marquardt, one damping factor per row), batched over all targets.
Each step is the minimum-norm solution of the damped linearised problem,
``dq = J^T (J J^T + lambda I)^-1 r``, so a position target, which leaves a 6-joint arm three redundant
directions, ends at (to first order) the solution nearest the start. The Jacobian ``J (N, 3, dof)`` is
the exact derivative of the model by autograd (three backward passes over the batch), except for
effects whose regressors are computed without gradients (compliance's gravity torque): their derivative
is left out, which only slows convergence by a factor of the order of the effect's relative size.

Prismatic joints take steps, limits and the tolerances below in metres (their Jacobian columns are m/m, of the
size of a revolute joint's at a 1 m lever, so one damping serves both).

Joint limits: a step is clipped to the limits, and a joint that sits on a limit and whose step pushes
outward is frozen (active set) for the next step. A row whose target needs a joint beyond its limit
ends with status ``limit``.

Configuration branch: the start fixes the arm configuration (shoulder, elbow, wrist). The solver never
leaves it because steps are small and damped; it is checked afterwards: the sign of the determinant of
the full 6 x 6 geometric Jacobian (it changes only across a singularity, the boundary between IK
branches) must equal the start's unless the solution lies within ``branch_tol`` of the start (next to a
singularity the branches meet), and no joint may move more than ``max_joint_change`` from its start.
A row that fails the check keeps its start joints and gets status ``unreachable`` (on the start's branch).

Context: effects may read the time ``t``, the temperature and the direction of motion; they are taken
per row from ``context`` (the CLI takes them from the targets file's ``t`` and ``temperature``
columns, and the direction of motion from the start joints when the run was a trajectory).

Frames: targets are in the instrument (tracker) frame or the robot base frame. Instrument-frame targets
are turned into base-frame points with the calibrated ``T_tracker_base``; instrument effects (a drift of
the tracker) move the instrument, not the robot, and are not compensated.
"""

from __future__ import annotations

import contextlib
import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from torchcal._threads import torch_threads
from torchcal.effects.base import Context, motion_direction
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError, ShapeError
from torchcal.robot import transforms as tf
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor
F64 = torch.float64

FRAMES = ("instrument", "base")


class Status(enum.Enum):
    """Outcome of one target.

    CONVERGED: the model puts the probe on the target within ``tol``.
    LIMIT: not reached, and a joint sits on its limit (the target needs it beyond).
    UNREACHABLE: not reached on the start's configuration branch (out of reach, or only reachable
        through a singularity / on another branch); the start joints are returned.
    """

    CONVERGED = "converged"
    LIMIT = "limit"
    UNREACHABLE = "unreachable"


@dataclass
class CompensationResult:
    """What :func:`compensate` returns.

    Attributes:
        q: joint commands ``(N, dof)`` [rad].
        miss: remaining distance between the model's probe position and the target ``(N,)`` [m].
        status: one :class:`Status` per row.
        q_start: the start joints ``(N, dof)`` [rad].
        iterations: Gauss-Newton iterations used (the batch's maximum).
        branch_kept: ``(N,)`` bool, the configuration check of the module docstring.
    """

    q: Tensor
    miss: Tensor
    status: list[Status]
    q_start: Tensor
    iterations: int
    branch_kept: Tensor

    def rows(self, status: Status) -> list[int]:
        """0-based indices of the rows with ``status``."""
        return [i for i, s in enumerate(self.status) if s is status]

    def counts(self) -> dict[str, int]:
        return {s.value: len(self.rows(s)) for s in Status}


# ------------------------------------------------------------------------------------------------ helpers
def _as_model(model) -> MeasurementModel:
    if isinstance(model, MeasurementModel):
        return model
    if isinstance(model, RobotModel):
        return MeasurementModel(model, [])
    raise OptionError(f"compensate expects a MeasurementModel or RobotModel, got {type(model).__name__}")


def _context(model: MeasurementModel, q: Tensor, context: dict | None) -> Context:
    ctx = dict(context or {})
    unknown = set(ctx) - {"t", "temperature", "direction"}
    if unknown:
        raise OptionError(f"context keys {sorted(unknown)} unknown; valid: t, temperature, direction")
    n = q.shape[0]
    for key in ("t", "temperature"):
        v = ctx.get(key)
        if v is not None and (not isinstance(v, Tensor) or v.shape != (n,)):
            raise ShapeError(f"context['{key}'] must be a tensor of shape ({n},), got {getattr(v, 'shape', v)}")
    for e in model.effects:
        var = getattr(e, "variable", None)
        if var in ("t", "temperature") and e.acts_on != "instrument" and ctx.get(var) is None:
            raise OptionError(
                f"the model has a {e.label()} in '{var}': give the targets a '{var}' column "
                f"(context['{var}']) so that compensation knows its value per row"
            )
    return Context(q=q, t=ctx.get("t"), temperature=ctx.get("temperature"), direction=ctx.get("direction"))


def probe_in_base(model: MeasurementModel, ctx: Context) -> Tensor:
    """Probe position in the robot base frame ``(N, 3)`` [m] with joint and Cartesian effects."""
    return model.probe_in_base(ctx)


def _value_and_jacobian(model: MeasurementModel, ctx: Context) -> tuple[Tensor, Tensor]:
    """``p (N, 3)`` and ``dp/dq (N, 3, dof)``: rows are independent, so three backward passes suffice."""
    q = ctx.q.detach().requires_grad_(True)
    c = Context(q=q, t=ctx.t, temperature=ctx.temperature, direction=ctx.direction)
    with torch.enable_grad():
        p = model.probe_in_base(c)
        rows = [torch.autograd.grad(p[:, k].sum(), q, retain_graph=k < 2)[0] for k in range(3)]
    return p.detach(), torch.stack(rows, dim=-2)


def full_jacobian(robot: RobotModel, q: Tensor) -> Tensor:
    """The geometric Jacobian of the flange by the joint readings ``(N, 6, dof)``: linear (flange origin) over angular
    rows (``J_joints A`` with a readings map)."""
    F, T = robot.joint_frames(q)
    z = (F[..., :3, :3] @ robot.geometry.axes.unsqueeze(-1)).squeeze(-1)
    lin = torch.linalg.cross(z, T[..., None, :3, 3] - F[..., :3, 3])
    J = torch.cat([lin, z], dim=-1).transpose(-1, -2)
    return J @ robot.readings.matrix().detach() if robot.has_readings_map else J


def configuration_sign(robot: RobotModel, q: Tensor) -> Tensor:
    """Sign of ``det J`` of the 6 x 6 geometric Jacobian per row ``(N,)``; zeros where dof != 6.

    For a 6R arm the IK branches (shoulder left/right, elbow up/down, wrist flip) are separated by
    singular configurations, where this determinant changes sign.
    """
    if robot.dof != 6:
        return torch.zeros(q.shape[0], dtype=q.dtype, device=q.device)
    with torch.no_grad():
        return torch.sign(torch.linalg.det(full_jacobian(robot, q)))


def targets_in_base(model: MeasurementModel, targets: Tensor, frame: str) -> Tensor:
    if frame not in FRAMES:
        raise OptionError(f"frame must be one of {FRAMES}, got {frame!r}")
    if frame == "base":
        return targets
    with torch.no_grad():
        T_base_tracker = tf.invert(model.robot.T_tracker_base().detach())
    return tf.transform_points(T_base_tracker, targets)


# ------------------------------------------------------------------------------------------------ solver
def _solve(
    model: MeasurementModel, target: Tensor, q0: Tensor, context: dict | None, *, tol: float, max_iter: int, lam0: float
) -> tuple[Tensor, Tensor, int]:
    """Batched LM on ``probe_in_base(q) = target``; returns ``q``, the miss ``(N,)`` and the iterations."""
    lo, hi = model.robot.limits[:, 0], model.robot.limits[:, 1]
    q = q0.clone()
    ctx_of = _context_factory(model, context)
    p, J = _value_and_jacobian(model, ctx_of(q))
    r = target - p
    err = r.norm(dim=-1)
    lam = torch.full((q.shape[0],), lam0, dtype=F64, device=q.device)
    eye = torch.eye(3, dtype=F64, device=q.device)
    it = 0
    for it in range(1, max_iter + 1):
        active = err > tol
        if not bool(active.any()):
            it -= 1
            break
        # damping scaled by the Jacobian's size keeps lambda dimensionless across robots
        scale = (J * J).sum(dim=(-1, -2)) / 3.0
        free = torch.ones_like(q, dtype=torch.bool)
        for _ in range(2):  # active set: freeze joints on a limit that the step pushes outward
            Jf = J * free.unsqueeze(-2)
            A = Jf @ Jf.transpose(-1, -2) + (lam * scale)[:, None, None] * eye
            dq = (Jf.transpose(-1, -2) @ torch.linalg.solve(A, r.unsqueeze(-1))).squeeze(-1)
            push = ((q <= lo + 1e-12) & (dq < 0)) | ((q >= hi - 1e-12) & (dq > 0))
            if not bool((push & free).any()):
                break
            free = free & ~push
        q_new = torch.where(active.unsqueeze(-1), torch.minimum(torch.maximum(q + dq, lo), hi), q)
        p_new, J_new = _value_and_jacobian(model, ctx_of(q_new))
        r_new = target - p_new
        err_new = r_new.norm(dim=-1)
        better = active & (err_new < err)
        q = torch.where(better.unsqueeze(-1), q_new, q)
        r = torch.where(better.unsqueeze(-1), r_new, r)
        J = torch.where(better[:, None, None], J_new, J)
        err = torch.where(better, err_new, err)
        lam = torch.where(better, (lam / 10.0).clamp(min=1e-12), torch.where(active, lam * 10.0, lam))
        # a row whose damping exploded makes no more progress: stop spending steps on it
        if bool((~active | (lam > 1e8)).all()):
            break
    return q, err, it


def _context_factory(model: MeasurementModel, context: dict | None):
    """Context for the current joints; checks the context once (the effects' variables)."""
    base = dict(context or {})

    def make(q: Tensor) -> Context:
        return _context(model, q, base)

    return make


# ------------------------------------------------------------------------------------------------ public
def nominal_ik(
    robot: RobotModel,
    targets_base: Tensor,
    *,
    reference: Tensor | None = None,
    seeds: int = 16,
    seed: int = 0,
    tol: float = 1e-9,
    max_iter: int = 100,
) -> Tensor:
    """Joints that put the probe of ``robot``'s current geometry on base-frame targets, for x,y,z-only input.

    A position has many solutions; every target is solved from the same deterministic set of start
    configurations (``reference`` and ``seeds - 1`` draws inside the limits) and the converged solution
    nearest to ``reference`` (default: the middle of the joint limits) is kept, so that neighbouring
    targets of a path land on the same branch.

    Args:
        robot: the robot (its geometry, lever arm; the instrument is not used).
        targets_base: ``(N, 3)`` [m] in the robot base frame.
        reference: ``(dof,)`` [rad] preferred configuration.
        seeds: number of start configurations.
        seed: seed of the start draws.

    Returns:
        ``(N, dof)`` joints [rad]; rows with no converged start keep the best one.
    """
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    ref = (0.5 * (lo + hi)) if reference is None else torch.as_tensor(reference, dtype=F64, device=lo.device)
    g = torch.Generator().manual_seed(seed)
    # draws from the middle half of each range: ranges of +-2 pi would otherwise start on wrapped twins
    starts = [ref] + [
        ref + (torch.rand(robot.dof, generator=g, dtype=F64).to(lo.device) - 0.5) * (hi - lo).clamp(max=2 * math.pi)
        for _ in range(seeds - 1)
    ]
    n = targets_base.shape[0]
    model = MeasurementModel(robot, [])
    starts_t = torch.stack(starts).clamp(lo, hi)  # (S, dof)
    q0 = starts_t.repeat_interleave(n, dim=0) if n else starts_t[:0]
    tgt = targets_base.repeat(seeds, 1)
    q, err, _ = _solve(model, tgt, q0, None, tol=tol, max_iter=max_iter, lam0=1e-3)
    q = q.reshape(seeds, n, robot.dof)
    err = err.reshape(seeds, n)
    dist = (q - ref).norm(dim=-1)
    score = torch.where(err <= max(tol * 10, 1e-8), dist, 1e6 + err)
    best = score.argmin(dim=0)
    return q[best, torch.arange(n)]


def compensate(
    model: MeasurementModel | RobotModel,
    targets: Tensor,
    q_seed: Tensor | None = None,
    *,
    frame: str = "instrument",
    context: dict | None = None,
    tol: float = 1e-10,
    max_iter: int = 30,
    max_joint_change: float = 0.3,
    branch_tol: float = 0.05,
    damping: float = 1e-6,
    threads: int | None = 1,
) -> CompensationResult:
    """Joint commands that make the full calibrated model put the probe on each target.

    Args:
        model: the calibrated :class:`MeasurementModel` (a :class:`RobotModel` means geometry only).
        targets: desired probe positions ``(N, 3)`` [m] in ``frame``.
        q_seed: start joints ``(N, dof)`` [rad] (the program's nominal joints); None: :func:`nominal_ik`
            on the model's geometry without effects.
        frame: ``"instrument"`` (tracker frame, the default) or ``"base"``.
        context: per-row ``t`` ``(N,)`` [s], ``temperature`` ``(N,)`` [degC], ``direction`` ``(N, dof)``
            for effects that read them (module docstring).
        tol: a row converges when its miss is at most this [m].
        max_iter: Gauss-Newton iterations at most.
        max_joint_change: the largest move of any joint from its start [rad] before a solution counts
            as a different configuration.
        branch_tol: a solution within this distance of its start [rad, max over joints] keeps the start's
            branch even where the Jacobian's determinant changes sign: next to a singularity (a stretched
            elbow) the branches meet, and a tiny move across it is the same arm configuration.
        damping: initial Levenberg-Marquardt damping (relative to the Jacobian's size).
        threads: torch threads for the batched solve (None: leave the caller's).

    Returns:
        :class:`CompensationResult`.
    """
    model = _as_model(model)
    robot = model.robot
    if not isinstance(targets, Tensor) or targets.dtype != F64 or targets.ndim != 2 or targets.shape[1] != 3:
        raise ShapeError(
            f"targets must be a float64 tensor (N, 3) [m], got {getattr(targets, 'shape', targets)} "
            f"{getattr(targets, 'dtype', '')}"
        )
    if not bool(torch.isfinite(targets).all()):
        row = int((~torch.isfinite(targets)).any(dim=-1).nonzero()[0])
        raise ShapeError(f"targets row {row} is not finite: {targets[row].tolist()}")
    with torch_threads(threads) if threads is not None else contextlib.nullcontext():
        tgt = targets_in_base(model, targets, frame)
        if q_seed is None:
            q0 = nominal_ik(robot, tgt)
        else:
            if not isinstance(q_seed, Tensor) or q_seed.shape != (targets.shape[0], robot.dof):
                raise ShapeError(
                    f"q_seed must have shape ({targets.shape[0]}, {robot.dof}), got {getattr(q_seed, 'shape', q_seed)}"
                )
            q0 = q_seed.to(F64)
        lo, hi = robot.limits[:, 0], robot.limits[:, 1]
        q0 = torch.minimum(torch.maximum(q0, lo), hi)
        ctx = dict(context or {})
        if ctx.get("direction") is None and ctx.pop("trajectory", False):
            ctx["direction"] = motion_direction(q0)
        ctx.pop("trajectory", None)
        q, err, it = _solve(model, tgt, q0, ctx, tol=tol, max_iter=max_iter, lam0=damping)
        sign0 = configuration_sign(robot, q0)
        sign1 = configuration_sign(robot, q)
        moved = (q - q0).abs().max(dim=-1).values
        kept = ((sign0 == sign1) | (moved <= branch_tol)) & (moved <= max_joint_change)
        at_limit = ((q <= lo + 1e-9) | (q >= hi - 1e-9)).any(dim=-1)
        q = torch.where(kept.unsqueeze(-1), q, q0)
        if not bool(kept.all()):
            with torch.no_grad():
                p0 = model.probe_in_base(_context(model, q0, ctx))
            err = torch.where(kept, err, (tgt - p0).norm(dim=-1))
    status = []
    for i in range(q.shape[0]):
        if bool(kept[i]) and float(err[i]) <= tol:
            status.append(Status.CONVERGED)
        elif bool(kept[i]) and bool(at_limit[i]):
            status.append(Status.LIMIT)
        else:
            status.append(Status.UNREACHABLE)
    return CompensationResult(
        q=q.detach(), miss=err.detach(), status=status, q_start=q0, iterations=it, branch_kept=kept
    )


def geometry_and_physics(model: MeasurementModel) -> MeasurementModel:
    """A copy of ``model`` without its learned corrections (kind ``learned``): the geometry and the named effects,
    whose laws (or fades, for the open forms) say how they continue beyond the calibrated region."""
    import copy

    plain = copy.deepcopy(model)
    plain.effects = torch.nn.ModuleList([e for e in plain.effects if e.kind != "learned"])
    plain.set_region(None)
    return plain


def compensate_in_region(
    model: MeasurementModel, targets: Tensor, q_seed: Tensor | None = None, *, context: dict | None = None, **kw
) -> tuple[CompensationResult, Tensor, Tensor]:
    """:func:`compensate` that trusts the learned corrections only inside the calibrated region.

    Rows whose command from the full model lies outside the region (:meth:`MeasurementModel.extrapolation` > 0)
    are solved again, from the same start, with the geometry and physical effects alone
    (:func:`geometry_and_physics`): a learned correction says nothing there, and a robot must not be driven by it.

    Returns:
        The result (those rows replaced), the extrapolation of every row's command ``(N,)`` [rad or m], and a
        boolean mask ``(N,)`` of the rows solved without the learned corrections.
    """
    model = _as_model(model)
    res = compensate(model, targets, q_seed, context=context, **kw)
    ext = model.extrapolation(res.q)
    plain_rows = torch.zeros(len(ext), dtype=torch.bool, device=ext.device)
    if not bool((ext > 0).any()) or not model.has_learned:
        return res, ext, plain_rows
    rows = torch.nonzero(ext > 0)[:, 0]
    solve_rows_with(geometry_and_physics(model), res, rows, targets, context=context, **kw)
    plain_rows[rows] = True
    return res, model.extrapolation(res.q), plain_rows


def solve_rows_with(
    model: MeasurementModel, res: CompensationResult, rows: Tensor, targets: Tensor, *, context=None, **kw
) -> None:
    """Solve the ``rows`` of ``res`` again with ``model``, from the same start, in place: beyond the calibrated
    region another model than the run's may be the one to trust (:func:`compensate_in_region`, and the kinematic
    calibration where the run's model's sigma is far above it: :func:`torchcal.report.rundir.row_trust`)."""
    if not len(rows):
        return
    n = len(res.q)
    sub_ctx = {
        k: (v[rows] if isinstance(v, Tensor) and v.ndim >= 1 and len(v) == n else v) for k, v in (context or {}).items()
    }
    sub = compensate(model, targets[rows], res.q_start[rows], context=sub_ctx, **kw)
    res.q[rows], res.miss[rows], res.branch_kept[rows] = sub.q, sub.miss, sub.branch_kept
    for k, i in enumerate(rows.tolist()):
        res.status[i] = sub.status[k]


def program_targets(
    model: MeasurementModel, q_program: Tensor, *, nominal: RobotModel | None = None, frame: str = "instrument"
) -> Tensor:
    """The points a robot program means: where the nominal model puts the probe for its joints ``(N, 3)``.

    Args:
        model: the calibrated model: its lever arm and (for ``frame="instrument"``) its ``T_tracker_base``
            are used, so that the program's point is the one its author meant with this tool.
        q_program: ``(N, dof)`` nominal joint targets [rad].
        nominal: the nominal robot (default: the model's robot with its geometry corrections zeroed).
        frame: frame of the returned points.
    """
    robot = model.robot
    if nominal is None:
        import copy

        nominal = copy.deepcopy(robot)
        nominal.geometry.reset()
    with torch.no_grad():
        p = tf.transform_points(nominal.forward(q_program), robot.t_flange_probe().detach())
        if frame == "instrument":
            p = tf.transform_points(robot.T_tracker_base().detach(), p)
        elif frame != "base":
            raise OptionError(f"frame must be one of {FRAMES}, got {frame!r}")
    return p


def model_miss(
    model: MeasurementModel, q: Tensor, targets: Tensor, *, frame: str = "instrument", context: dict | None = None
) -> Tensor:
    """Distance ``(N,)`` [m] between where ``model`` puts the probe for ``q`` and the targets."""
    model = _as_model(model)
    with torch.no_grad():
        p = model.probe_in_base(_context(model, q, context))
    return (targets_in_base(model, targets, frame) - p).norm(dim=-1)


__all__: Sequence[str] = (
    "Status",
    "solve_rows_with",
    "CompensationResult",
    "compensate",
    "compensate_in_region",
    "geometry_and_physics",
    "nominal_ik",
    "program_targets",
    "model_miss",
    "configuration_sign",
    "full_jacobian",
)


def write_joints(
    path,
    result: CompensationResult,
    *,
    targets: Tensor | None = None,
    t: Tensor | None = None,
    temperature: Tensor | None = None,
    extra: dict[str, Tensor] | None = None,
    meta: dict[str, str] | None = None,
    written_by: str | None = None,
    labels: dict[str, tuple[str, ...]] | None = None,
) -> None:
    """Write the compensated joints as CSV, atomically: ``q1..qN[,x,y,z][,t][,temperature][,extra...],miss,status``.

    Joints in rad, positions and ``miss`` in m, every number with ``repr`` (reads back bit-identical);
    ``status`` is ``converged``, ``limit`` or ``unreachable``. Every input row gets one output row, in order.
    ``written_by``: the command, written first as ``# written_by: ...`` (how ``--out`` knows torchcal's files).
    ``labels``: extra columns written as names (``extra[key]`` holds each row's index into ``labels[key]``).
    """
    import os
    import tempfile
    from pathlib import Path

    path = Path(path)
    cols: list[tuple[str, Tensor]] = [(f"q{k + 1}", result.q[:, k]) for k in range(result.q.shape[1])]
    if targets is not None:
        cols += [(c, targets[:, k]) for k, c in enumerate("xyz")]
    if t is not None:
        cols.append(("t", t))
    if temperature is not None:
        cols.append(("temperature", temperature))
    cols += [(k, v) for k, v in (extra or {}).items() if k not in ("miss", "status")]
    cols.append(("miss", result.miss))
    lines = [f"# written_by: {written_by}\n"] if written_by is not None else []  # first: the --out mark
    lines += [f"# {k}: {v}\n" for k, v in (meta or {}).items() if k != "written_by"]
    lines.append(",".join([c for c, _ in cols] + ["status"]) + "\n")
    table = torch.stack([v.detach().to(F64) for _, v in cols], dim=1).tolist()
    names = [(labels or {}).get(c) for c, _ in cols]
    for row, st in zip(table, result.status, strict=True):
        cells = (repr(float(x)) if n is None else n[int(x)] for x, n in zip(row, names))
        lines.append(",".join(cells) + f",{st.value}\n")
    if not path.parent.is_dir():
        raise OptionError(f"{path}: cannot write, directory '{path.parent}' does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.writelines(lines)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# ------------------------------------------------------------------------------ what the URDF leaves out
def urdf_left_out(model: MeasurementModel) -> list[str]:
    """Labels of the model's parts that a URDF (geometry, lever arm, tracker pose only) cannot carry."""
    return [e.label() for e in _as_model(model).effects]


def urdf_gap(model: MeasurementModel, ctx: Context) -> dict:
    """How far the geometry-only part of ``model`` (what a URDF carries) is from the full model on ``ctx``'s poses.

    Returns:
        ``{"n_poses", "rms_mm", "max_mm", "left_out": [labels]}``: distances between the full model's
        prediction and the geometry-only FK (same geometry, lever arm and tracker pose) in the tracker frame.
    """
    model = _as_model(model)
    with torch.no_grad():
        full = model(ctx)
        geo = MeasurementModel(model.robot, [])(ctx)
    d = (full - geo).norm(dim=-1)
    return {
        "n_poses": int(d.shape[0]),
        "rms_mm": float(d.square().mean().sqrt()) * 1e3 if len(d) else 0.0,
        "max_mm": float(d.max()) * 1e3 if len(d) else 0.0,
        "left_out": urdf_left_out(model),
    }


def urdf_fk_difference(path, model: MeasurementModel, ctx: Context) -> dict:
    """RMS and max difference between FK of a written URDF (base link to its ``probe`` frame, placed in the
    tracker frame with the model's ``T_tracker_base``) and the full model's prediction ``(N, 3)`` on ``ctx``.

    The URDF is read back with :func:`torchcal.robot.load_robot` (float64), so this measures the file itself, not
    the model it was written from; from its XML elements (``reader="elements"``, the numbers yourdfpy reads, without
    importing yourdfpy's mesh library: this check runs after every calibration).
    """
    from torchcal.robot import load_robot

    model = _as_model(model)
    urdf = load_robot(path, base_link=model.robot.base_link, tip_link="probe", reader="elements").to(model.robot.device)
    with torch.no_grad():
        p_base = urdf(ctx.q)[..., :3, 3]
        p = tf.transform_points(model.robot.T_tracker_base(), p_base)
        d = (model(ctx) - p).norm(dim=-1)
    return {
        "n_poses": int(d.shape[0]),
        "rms_mm": float(d.square().mean().sqrt()) * 1e3,
        "max_mm": float(d.max()) * 1e3,
        "left_out": urdf_left_out(model),
    }


def urdf_notes(gap: dict) -> list[str]:
    """Header lines for the calibrated URDF: what it leaves out and what that costs on the training poses."""
    if not gap["left_out"]:
        return ["The calibration found no effect beyond geometry: this URDF carries the whole calibrated model."]
    return [
        f"NOT in this URDF: {', '.join(gap['left_out'])} (non-geometric effects a URDF cannot express).",
        f"On the {gap['n_poses']} training poses, FK of this URDF differs from the full calibrated model by "
        f"RMS {gap['rms_mm']:.4f} mm, max {gap['max_mm']:.4f} mm.",
        "To reach targets with the full model, command the joints from 'torchcal compensate RUN TARGETS.csv'.",
    ]


def urdf_markdown(gap: dict) -> str:
    """A report.md section on what ``robot_calibrated.urdf`` carries and leaves out."""
    lines = ["", "## The calibrated URDF", ""]
    if not gap["left_out"]:
        lines.append(
            "`robot_calibrated.urdf` carries the whole calibrated model (geometry, lever arm as the "
            "`probe` frame, tracker pose as the `tracker` frame): the run found no other effect."
        )
    else:
        lines += [
            f"`robot_calibrated.urdf` carries the geometry, the lever arm (`probe` frame) and the tracker pose "
            f"(`tracker` frame). It leaves out: {', '.join(gap['left_out'])}.",
            "",
            f"On the {gap['n_poses']} training poses its forward kinematics differs from the full model's "
            f"prediction by RMS {gap['rms_mm']:.4f} mm, max {gap['max_mm']:.4f} mm. To use the full model on the "
            "robot, compensate the joint commands: `torchcal compensate RUN TARGETS.csv --out JOINTS.csv`.",
        ]
    return "\n".join(lines) + "\n"
