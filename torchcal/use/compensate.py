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
the exact derivative of the model by autograd (a backward pass per residual component over the batch, or one
over copies of a few rows, :data:`ONE_PASS_ROWS`; a Gaussian process's own in closed form), except for
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

Orientation (a 6-D solve, ``orientations``): the residual stacks the position error [m] over ``orientation_weight``
[m/rad] times the rotation vector from the model's probe frame to the target's, and the steps solve both (module
:func:`compensate`'s argument docs say what the weight decides). A row whose full pose is not reached on the start's
branch (next to a singularity the pose may need a move across it) is solved again for its position alone and, where
that converges, commanded by it; its status still says the pose was not reached (``position_only`` marks it).

Context: effects may read the time ``t``, the temperature and the direction of motion; they are taken
per row from ``context`` (the CLI takes them from the targets file's ``t`` and ``temperature``
columns, and the direction of motion from the start joints when the run was a trajectory).

Frames: targets are in the instrument (tracker) frame or the robot base frame. Instrument-frame targets
are turned into base-frame points with the calibrated ``T_tracker_base``; instrument effects (a drift of
the tracker) move the instrument, not the robot, and are not compensated.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from torchcal import _console
from torchcal._threads import torch_threads
from torchcal.data.measurements import Measurements
from torchcal.effects.base import Context, motion_direction
from torchcal.effects.model import MeasurementModel
from torchcal.errors import MeasurementFileError, OptionError, ShapeError
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
        miss_angle: remaining angle between the model's probe orientation and the target orientation ``(N,)`` [rad],
            or None for a position-only solve.
        position_only: ``(N,)`` bool in a 6-D solve, the rows whose full pose was not reached (status ``limit`` or
            ``unreachable``) and which are commanded by the position-only solution instead (its ``miss`` reached,
            ``miss_angle`` the tool's remaining turn); None for a position-only solve.
    """

    q: Tensor
    miss: Tensor
    status: list[Status]
    q_start: Tensor
    iterations: int
    branch_kept: Tensor
    miss_angle: Tensor | None = None
    position_only: Tensor | None = None

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
    unknown = set(ctx) - {"t", "temperature", "direction", "payload", "tau"}
    if unknown:
        raise OptionError(f"context keys {sorted(unknown)} unknown; valid: t, temperature, direction, payload, tau")
    n = q.shape[0]
    for key in ("t", "temperature", "payload"):
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
    return Context(
        q=q,
        t=ctx.get("t"),
        temperature=ctx.get("temperature"),
        direction=ctx.get("direction"),
        payload=ctx.get("payload"),  # the program's payload per row [kg]: the compliance carries it
        # the torques the program's poses hold [N m]: a command differs from its pose by a fraction of a mrad, whose
        # change of the static torque is far below a controller's torque noise
        tau=ctx.get("tau"),
    )


def probe_in_base(model: MeasurementModel, ctx: Context) -> Tensor:
    """Probe position in the robot base frame ``(N, 3)`` [m] with joint and Cartesian effects."""
    return model.probe_in_base(ctx)


#: rows times residual components up to which the Jacobian is one backward pass over as many copies of the rows as
#: the residual has components, each copy differentiated by its own component, instead of one pass per component:
#: a pass over a few rows costs its graph's overhead, not its rows, and the solver's last iterations run on the few
#: rows that converge slowly
ONE_PASS_ROWS = 24


def _residual_and_jacobian(
    f: Callable[[Context, Tensor | None], Tensor], ctx: Context, m: int
) -> tuple[Tensor, Tensor]:
    """A residual ``r = f(ctx, None) (N, m)`` and the model's Jacobian ``-dr/dq (N, m, dof)`` by reverse mode; ``f``
    also takes a context of copies of the rows with the index of each copy's row (:data:`ONE_PASS_ROWS`)."""
    n = ctx.q.shape[0]
    with torch.enable_grad():
        if 0 < n * m <= ONE_PASS_ROWS:
            idx = torch.arange(n, device=ctx.q.device).repeat(m)
            q = ctx.q.detach()[idx].requires_grad_(True)
            t, temperature, direction, payload, tau = (
                None if v is None else v[idx] for v in (ctx.t, ctx.temperature, ctx.direction, ctx.payload, ctx.tau)
            )
            copies = Context(q=q, t=t, temperature=temperature, direction=direction, payload=payload, tau=tau)
            r = f(copies, idx)  # (m n, m)
            own = r.reshape(m, n, m).diagonal(dim1=0, dim2=2)  # (n, m): copy k's component k
            (g,) = torch.autograd.grad(own.sum(), q)
            return r[:n].detach(), -g.reshape(m, n, -1).transpose(0, 1)
        q = ctx.q.detach().requires_grad_(True)
        whole = dataclasses.replace(ctx, q=q)
        r = f(whole, None)
        rows = [-torch.autograd.grad(r[:, k].sum(), q, retain_graph=k < m - 1)[0] for k in range(m)]
    return r.detach(), torch.stack(rows, dim=-2)


def rotation_in_base(model: MeasurementModel, ctx: Context) -> Tensor:
    """The probe frame's orientation in the robot base frame ``(N, 3, 3)``: ``R_base_flange(q + dq) R_flange_probe``
    with the joint effects ``dq`` (Cartesian effects move the probe, they do not turn it)."""
    return model.robot.probe_rotation(ctx.q + model.joint_offsets(ctx))


def _vee(A: Tensor) -> Tensor:
    """``(a32, a13, a21)`` of ``(N, 3, 3)`` matrices ``(N, 3)``."""
    return torch.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], dim=-1)


def _rotation_vector(E: Tensor) -> Tensor:
    """The rotation vector ``(N, 3)`` [rad] of rotations ``E (N, 3, 3)``, differentiable at the identity too: the
    factor ``angle / sin(angle)`` is 1 + O(angle^2) there, and ``sin`` is kept off zero for its derivative."""
    v = 0.5 * _vee(E - E.transpose(-1, -2))
    sin = (v * v).sum(-1).clamp(min=1e-300).sqrt()
    cos = 0.5 * (E.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    return v * (torch.atan2(sin, cos) / sin).unsqueeze(-1)


def rotation_miss(R_target: Tensor, R: Tensor) -> Tensor:
    """The angle ``(N,)`` [rad] of the rotation from ``R`` to ``R_target`` (both ``(N, 3, 3)``)."""
    E = R_target @ R.transpose(-1, -2)
    sin = 0.5 * _vee(E - E.transpose(-1, -2)).norm(dim=-1)
    cos = 0.5 * (E.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    return torch.atan2(sin, cos)


@dataclass
class _Goal:
    """What the solver drives the model to: positions ``(N, 3)`` [m] in the base frame and, for a 6-D solve,
    orientations ``R (N, 3, 3)`` there, an orientation error weighing ``weight`` [m/rad] against a position error."""

    p: Tensor
    R: Tensor | None = None
    weight: float = 0.1

    def residual(self, model: MeasurementModel, ctx: Context) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """The residual ``r (N, m)`` (target minus model; m = 3, or 6 with the orientation), the model's Jacobian
        ``-dr/dq (N, m, dof)`` by autograd, and the position and orientation misses ``(N,)`` [m, rad].

        The orientation residual is ``weight`` times the rotation vector of ``E = R_target R^T`` (the rotation still
        needed, in the base frame): ``v angle / sin(angle)`` with ``v = vee(E - E^T) / 2``, which grows with the angle
        up to half a turn (``v`` alone, ``sin(angle)`` times the axis, would pull a start more than a quarter turn off
        towards the half turn)."""
        if self.R is None:

            def position(c: Context, idx: Tensor | None) -> Tensor:
                return (self.p if idx is None else self.p[idx]) - model.probe_in_base(c)

            r, J = _residual_and_jacobian(position, ctx, 3)
            return r, J, r.norm(dim=-1), None
        turned = {}  # the model's orientation, kept for the miss

        def chain(robot: RobotModel, q: Tensor) -> Tensor:
            # the position and the rotation from one pass along the chain at the joints with their effects
            p, turned["R"] = robot.probe_pose(q)
            return p

        def pose(c: Context, idx: Tensor | None) -> Tensor:
            p_target, R_target = (self.p, self.R) if idx is None else (self.p[idx], self.R[idx])
            p = model.probe_in_base(c, fk=chain)
            R = turned["R"]
            return torch.cat([p_target - p, self.weight * _rotation_vector(R_target @ R.transpose(-1, -2))], dim=-1)

        r, J = _residual_and_jacobian(pose, ctx, 6)
        R = turned["R"][: len(r)].detach()
        return r, J, r[:, :3].norm(dim=-1), rotation_miss(self.R, R)

    def subset(self, rows: Tensor) -> _Goal:
        return _Goal(self.p[rows], None if self.R is None else self.R[rows], self.weight)

    def error(self, miss: Tensor, angle: Tensor | None) -> Tensor:
        """The solver's error ``(N,)`` [m]: the position miss, with the weighted orientation miss beyond
        :data:`ANGLE_RESOLUTION` in quadrature."""
        if angle is None:
            return miss
        return torch.sqrt(miss.square() + (self.weight * (angle - ANGLE_RESOLUTION).clamp(min=0.0)).square())


#: [rad] an orientation miss a 6-D solve cannot resolve further: a rotation vector through a chain of float64
#: rotations carries about 1e-15 rad of rounding. Below it an orientation counts as met, whatever the weight: with
#: ``orientation_weight`` 1e6 the rounding alone (1e6 x 1e-16 m) was near the 1e-10 m tolerance, and 0 of 40 rows
#: converged, each 'unreachable' by 0.0000 mm and 0.0000 deg.
ANGLE_RESOLUTION = 1e-12


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
    model: MeasurementModel, goal: _Goal, q0: Tensor, context: dict | None, *, tol: float, max_iter: int, lam0: float
) -> tuple[Tensor, Tensor, Tensor | None, int]:
    """Batched LM on the goal's residual; returns ``q``, the position miss ``(N,)`` [m], the orientation miss ``(N,)``
    [rad] (None without orientation targets) and the iterations. Each iteration evaluates the rows still above
    ``tol`` only: a few rows next to a singularity then cost their own steps, not the whole batch's."""
    q = q0.clone()
    ctx_of = _context_factory(model, context, q0.shape[0])
    r, J, miss, angle = goal.residual(model, ctx_of(q))
    err = goal.error(miss, angle)
    lam = torch.full((q.shape[0],), lam0, dtype=F64, device=q.device)
    # the steps see the orientation rows at a weight of at most 1 m/rad: the undamped step solves the same linear
    # system whatever the rows' scale, but a weight of 1e6 made the damped system's condition 1e12 and the damping
    # (relative to the Jacobian's mean square) swamp the position rows, and 0 of 40 rows converged; the steps are
    # still accepted on the weighted error
    rows_scale = torch.ones(r.shape[-1], dtype=F64, device=q.device)
    if goal.R is not None and goal.weight > 1.0:
        rows_scale[3:] = 1.0 / goal.weight
    it = 0
    for it in _console.progress(range(1, max_iter + 1), desc=f"compensate: {q.shape[0]} rows"):
        rows = torch.nonzero(err > tol).flatten()
        if not len(rows):
            it -= 1
            break
        q_new = _step(model, q[rows], r[rows] * rows_scale, J[rows] * rows_scale[:, None], lam[rows])
        r_new, J_new, miss_new, angle_new = goal.subset(rows).residual(model, ctx_of(q_new, rows))
        err_new = goal.error(miss_new, angle_new)
        better = err_new < err[rows]
        up = rows[better]
        q[up], r[up], J[up], err[up], miss[up] = (
            q_new[better],
            r_new[better],
            J_new[better],
            err_new[better],
            miss_new[better],
        )
        if angle is not None:
            angle[up] = angle_new[better]
        lam[rows] = torch.where(better, (lam[rows] / 10.0).clamp(min=1e-12), lam[rows] * 10.0)
        # a row whose damping exploded makes no more progress: stop spending steps on it
        if bool((lam[rows] > 1e8).all()):
            break
    return q, miss, angle, it


def _step(model: MeasurementModel, q: Tensor, r: Tensor, J: Tensor, lam: Tensor) -> Tensor:
    """One damped minimum-norm step ``dq = J^T (J J^T + lambda I)^-1 r`` from ``q (n, dof)``, clipped to the limits.

    Active set: a joint on a limit that the step pushes outward is frozen and the step recomputed."""
    lo, hi = model.robot.limits[:, 0], model.robot.limits[:, 1]
    m = r.shape[-1]
    eye = torch.eye(m, dtype=F64, device=q.device)
    # damping scaled by the Jacobian's size keeps lambda dimensionless across robots
    scale = (J * J).sum(dim=(-1, -2)) / m
    free = torch.ones_like(q, dtype=torch.bool)
    for _ in range(2):
        Jf = J * free.unsqueeze(-2)
        A = Jf @ Jf.transpose(-1, -2) + (lam * scale)[:, None, None] * eye
        dq = (Jf.transpose(-1, -2) @ torch.linalg.solve(A, r.unsqueeze(-1))).squeeze(-1)
        push = ((q <= lo + 1e-12) & (dq < 0)) | ((q >= hi - 1e-12) & (dq > 0))
        if not bool((push & free).any()):
            break
        free = free & ~push
    return torch.minimum(torch.maximum(q + dq, lo), hi)


def _context_factory(model: MeasurementModel, context: dict | None, n: int):
    """Context for the current joints of all ``n`` rows or of ``rows``; checks the context (the effects'
    variables)."""
    base = dict(context or {})

    def make(q: Tensor, rows: Tensor | None = None) -> Context:
        return _context(model, q, base if rows is None else {k: _subset(v, rows, n) for k, v in base.items()})

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
    orientations: Tensor | None = None,
    orientation_weight: float = 0.1,
) -> Tensor:
    """Joints that put the probe of ``robot``'s current geometry on base-frame targets, for input without joints.

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
        orientations: ``(N, 3, 3)`` probe orientations in the base frame to reach too (None: positions only).
        orientation_weight: [m/rad], as :func:`compensate`'s.

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
    R = None if orientations is None else orientations.repeat(seeds, 1, 1)
    goal = _Goal(targets_base.repeat(seeds, 1), R, orientation_weight)
    q, miss, angle, _ = _solve(model, goal, q0, None, tol=tol, max_iter=max_iter, lam0=1e-3)
    err = goal.error(miss, angle)
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
    orientations: Tensor | None = None,
    orientation_weight: float = 0.1,
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
        context: per-row ``t`` ``(N,)`` [s], ``temperature`` ``(N,)`` [degC], ``payload`` ``(N,)`` [kg],
            ``tau`` ``(N, dof)`` [N m] (the torques the program's poses hold), ``direction`` ``(N, dof)`` for effects
            that read them (module docstring).
        orientations: desired probe orientations ``R_frame_probe (N, 3, 3)`` in ``frame`` (a 6-D solve; the model's
            robot must carry the probe's orientation, :meth:`~torchcal.robot.model.RobotModel.enable_orientation`),
            or None (positions only: the tool is free to turn).
        orientation_weight: [m/rad] how much an orientation error weighs against a position error in the solve: an
            angle ``a`` counts as a position error of ``orientation_weight * a`` (the default 0.1: as a point 100 mm
            from the probe moves). Where both targets are reachable (a 6-joint arm, inside its limits) the solution
            meets both exactly and the weight only shapes the path there; it decides the compromise where they are
            not (a joint on its limit, an arm of fewer joints) and, with more than six joints, which joints move.
        tol: a row converges when its miss is at most this [m] (with orientations: the position miss and the
            weighted orientation miss together, in quadrature).
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
    _check_targets(targets, orientations, robot)
    with torch_threads(threads) if threads is not None else contextlib.nullcontext():
        goal = _goal_in_base(model, targets, orientations, orientation_weight, frame)
        q0 = _start(robot, goal, q_seed, targets.shape[0])
        ctx = dict(context or {})
        if ctx.get("direction") is None and ctx.pop("trajectory", False):
            ctx["direction"] = motion_direction(q0)
        ctx.pop("trajectory", None)
        opts = dict(
            tol=tol, max_iter=max_iter, damping=damping, branch_tol=branch_tol, max_joint_change=max_joint_change
        )
        q, miss, angle, kept, status, it = _solve_on_branch(model, goal, q0, ctx, **opts)
        fallback = None
        if angle is not None:
            fallback = _position_fallback(model, goal, q0, ctx, (q, miss, angle, kept, status), **opts)
    return CompensationResult(
        q=q.detach(),
        miss=miss.detach(),
        status=status,
        q_start=q0,
        iterations=it,
        branch_kept=kept,
        miss_angle=None if angle is None else angle.detach(),
        position_only=fallback,
    )


def _solve_on_branch(
    model: MeasurementModel,
    goal: _Goal,
    q0: Tensor,
    ctx: dict,
    *,
    tol: float,
    max_iter: int,
    damping: float,
    branch_tol: float,
    max_joint_change: float,
) -> tuple[Tensor, Tensor, Tensor | None, Tensor, list[Status], int]:
    """:func:`_solve` from ``q0``, then the configuration check: a row that left the start's branch keeps its start.

    Returns:
        ``q``, the position and orientation misses, ``kept`` (the branch check), each row's status and the iterations.
    """
    robot = model.robot
    q, miss, angle, it = _solve(model, goal, q0, ctx, tol=tol, max_iter=max_iter, lam0=damping)
    kept = _branch_kept(robot, q0, q, branch_tol=branch_tol, max_joint_change=max_joint_change)
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    at_limit = ((q <= lo + 1e-9) | (q >= hi - 1e-9)).any(dim=-1)
    q = torch.where(kept.unsqueeze(-1), q, q0)
    if not bool(kept.all()):  # those rows keep their start: their miss is the start's
        _, _, miss0, angle0 = goal.residual(model, _context(model, q0, ctx))
        miss = torch.where(kept, miss, miss0)
        angle = None if angle is None else torch.where(kept, angle, angle0)
    err = goal.error(miss, angle)
    status = []
    for i in range(q.shape[0]):
        if bool(kept[i]) and float(err[i]) <= tol:
            status.append(Status.CONVERGED)
        elif bool(kept[i]) and bool(at_limit[i]):
            status.append(Status.LIMIT)
        else:
            status.append(Status.UNREACHABLE)
    return q, miss, angle, kept, status, it


#: the fallback's price of a joint move against the orientation it buys, [rad^2 / rad^2]: 0.1 rad of joint motion
#: counts as 1 mrad of orientation error (the configuration check allows 0.3 rad)
SINGULAR_DAMPING = 1e-4


def _position_fallback(model: MeasurementModel, goal: _Goal, q0: Tensor, ctx: dict, solved: tuple, **opts) -> Tensor:
    """The rows of a 6-D solve not reached, solved for their position first and their orientation as far as the
    position and a short joint move allow (:func:`_prioritised`, else the position alone); where the position
    converges on the branch, those joints replace the 6-D compromise (in place in ``solved``: ``q``, the misses,
    ``kept``) and the status stays (the pose is not reached). Next to a singularity (a stretched elbow, a wrist near
    zero) the full pose may need a move across it, while the position, with three joints to spare, does not.

    Returns:
        ``(N,)`` bool, the rows commanded by a position-first solution.
    """
    q, miss, angle, kept, status = solved
    fallback = torch.zeros(len(status), dtype=torch.bool, device=q.device)
    rows = torch.tensor(
        [i for i, s in enumerate(status) if s is not Status.CONVERGED], dtype=torch.long, device=q.device
    )
    if not len(rows):
        return fallback
    sub_ctx = {k: _subset(v, rows, len(status)) for k, v in ctx.items()}
    sub = goal.subset(rows)
    position = _Goal(sub.p)
    plain = _solve_on_branch(model, position, q0[rows], sub_ctx, **opts)[0]
    # from the position's solution: the position steps then stay small next to a singularity; the position is
    # polished last (next to a stretched elbow the orientation steps push it off by more than the tolerance)
    turned = _prioritised(model, sub, q0[rows], plain, sub_ctx)
    best_q, best_angle = None, None
    for q1 in (plain, _solve_on_branch(model, position, turned, sub_ctx, **opts)[0]):
        miss1, angle1 = goal_misses(model, sub, q1, sub_ctx)
        ok = (miss1 <= opts["tol"]) & _branch_kept(model.robot, q0[rows], q1, **_branch_opts(opts))
        angle1 = torch.where(ok, angle1, torch.full_like(angle1, math.inf))
        if best_q is None:
            best_q, best_angle = q1, angle1
        else:
            better = angle1 < best_angle
            best_q, best_angle = torch.where(better[:, None], q1, best_q), torch.where(better, angle1, best_angle)
    won = torch.isfinite(best_angle)
    up = rows[won]
    q[up], angle[up], kept[up] = best_q[won], best_angle[won], True
    miss[up] = goal_misses(model, sub, best_q, sub_ctx)[0][won]
    fallback[up] = True
    return fallback


def _branch_opts(opts: dict) -> dict:
    return {"branch_tol": opts["branch_tol"], "max_joint_change": opts["max_joint_change"]}


def goal_misses(model: MeasurementModel, goal: _Goal, q: Tensor, ctx: dict) -> tuple[Tensor, Tensor]:
    """The position and orientation misses ``(N,)`` [m, rad] of joints ``q`` against a 6-D goal."""
    with torch.no_grad():
        c = _context(model, q, ctx)
        miss = (goal.p - model.probe_in_base(c)).norm(dim=-1)
        return miss, rotation_miss(goal.R, rotation_in_base(model, c))


def _prioritised(model: MeasurementModel, goal: _Goal, q0: Tensor, q1: Tensor, ctx: dict, *, iters: int = 20) -> Tensor:
    """Joints ``(N, dof)`` that reach the goal's positions and come as near its orientations as a short move from the
    start ``q0`` allows, iterated from ``q1``.

    Each step solves the position (Gauss-Newton, minimum norm) and, in the position's null space, the orientation
    error plus ``SINGULAR_DAMPING`` times the squared distance from the start ``q0``: next to a singularity, where the
    exact orientation lies far along a direction the arm barely turns in, the step stops at a short move instead."""
    lo, hi = model.robot.limits[:, 0], model.robot.limits[:, 1]
    q = q1.clone()
    eye = torch.eye(q.shape[1], dtype=F64, device=q.device)
    for _ in range(iters):
        r, J, _, _ = goal.residual(model, _context(model, q, ctx))
        Jp, Jw, e = J[:, :3], J[:, 3:] / goal.weight, r[:, 3:] / goal.weight
        A = Jp @ Jp.transpose(-1, -2)
        A = A + 1e-12 * A.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=F64, device=q.device)
        pinv = torch.linalg.solve(A, Jp).transpose(-1, -2)  # (N, dof, 3): J^T (J J^T)^-1
        dq1 = (pinv @ r[:, :3, None]).squeeze(-1)
        N = eye - pinv @ Jp
        Jn = Jw @ N
        rhs = Jn.transpose(-1, -2) @ (e - (Jw @ dq1[..., None]).squeeze(-1))[..., None]
        rhs = rhs - SINGULAR_DAMPING * (N @ (q - q0)[..., None])
        dq2 = N @ torch.linalg.solve(Jn.transpose(-1, -2) @ Jn + SINGULAR_DAMPING * eye, rhs)
        q = torch.minimum(torch.maximum(q + dq1 + dq2.squeeze(-1), lo), hi)
    return q


def _check_targets(targets: Tensor, orientations: Tensor | None, robot: RobotModel) -> None:
    """Refuse targets that are not float64 ``(N, 3)``, orientations that are not ``(N, 3, 3)``, non-finite rows, and
    orientations for a robot without the probe's orientation."""
    if not isinstance(targets, Tensor) or targets.dtype != F64 or targets.ndim != 2 or targets.shape[1] != 3:
        raise ShapeError(
            f"targets must be a float64 tensor (N, 3) [m], got {getattr(targets, 'shape', targets)} "
            f"{getattr(targets, 'dtype', '')}"
        )
    if not bool(torch.isfinite(targets).all()):
        row = int((~torch.isfinite(targets)).any(dim=-1).nonzero()[0])
        raise ShapeError(f"targets row {row} is not finite: {targets[row].tolist()}")
    if orientations is None:
        return
    n = targets.shape[0]
    if not isinstance(orientations, Tensor) or orientations.dtype != F64 or orientations.shape != (n, 3, 3):
        raise ShapeError(
            f"orientations must be a float64 tensor ({n}, 3, 3), got {getattr(orientations, 'shape', orientations)}"
        )
    if not bool(torch.isfinite(orientations).all()):
        row = int((~torch.isfinite(orientations)).flatten(1).any(dim=-1).nonzero()[0])
        raise ShapeError(f"orientations row {row} is not finite")
    if not robot.has_orientation:
        raise OptionError(
            f"robot '{robot.name}' carries no probe orientation: it was calibrated from positions only, so "
            "orientation targets cannot be compensated (solve positions only: orientations=None)"
        )


def _goal_in_base(
    model: MeasurementModel, targets: Tensor, orientations: Tensor | None, weight: float, frame: str
) -> _Goal:
    """The targets (and orientations) in the robot base frame."""
    p = targets_in_base(model, targets, frame)
    if orientations is None:
        return _Goal(p)
    if not weight > 0 or not math.isfinite(weight):
        raise OptionError(f"orientation_weight must be a positive number [m/rad], got {weight!r}")
    R = orientations
    if frame == "instrument":
        with torch.no_grad():
            R = tf.invert(model.robot.T_tracker_base().detach())[:3, :3] @ R
    return _Goal(p, R, float(weight))


def _start(robot: RobotModel, goal: _Goal, q_seed: Tensor | None, n: int) -> Tensor:
    """The start joints ``(N, dof)``: ``q_seed``, or the nominal IK of the goal; inside the limits."""
    if q_seed is None:
        q0 = nominal_ik(robot, goal.p, orientations=goal.R, orientation_weight=goal.weight)
    else:
        if not isinstance(q_seed, Tensor) or q_seed.shape != (n, robot.dof):
            raise ShapeError(f"q_seed must have shape ({n}, {robot.dof}), got {getattr(q_seed, 'shape', q_seed)}")
        q0 = q_seed.to(F64)
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    return torch.minimum(torch.maximum(q0, lo), hi)


def _branch_kept(robot: RobotModel, q0: Tensor, q: Tensor, *, branch_tol: float, max_joint_change: float) -> Tensor:
    """``(N,)`` bool: the solution stays on the start's configuration branch (the module docstring's check)."""
    sign0 = configuration_sign(robot, q0)
    sign1 = configuration_sign(robot, q)
    moved = (q - q0).abs().max(dim=-1).values
    return ((sign0 == sign1) | (moved <= branch_tol)) & (moved <= max_joint_change)


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
    calibration where the run's model's sigma is far above it: :func:`torchcal.use.rundir.row_trust`)."""
    if not len(rows):
        return
    n = len(res.q)
    sub_ctx = {
        k: (v[rows] if isinstance(v, Tensor) and v.ndim >= 1 and len(v) == n else v) for k, v in (context or {}).items()
    }
    if kw.get("orientations") is not None:
        kw = {**kw, "orientations": kw["orientations"][rows]}
    sub = compensate(model, targets[rows], res.q_start[rows], context=sub_ctx, **kw)
    res.q[rows], res.miss[rows], res.branch_kept[rows] = sub.q, sub.miss, sub.branch_kept
    if sub.miss_angle is not None:
        res.miss_angle[rows], res.position_only[rows] = sub.miss_angle, sub.position_only
    for k, i in enumerate(rows.tolist()):
        res.status[i] = sub.status[k]


def row_groups(
    model: MeasurementModel, data: Measurements, station: str | None = None, probe: str | None = None
) -> tuple[Tensor, Tensor]:
    """Each row's station and probe index in ``model``'s order ``(N,)`` int64, from the file's ``station`` and
    ``probe`` columns and the ``--station`` / ``--probe`` options (names; None: not given).

    A row takes its column's name; a file without the column takes the option's, or the run's first. A run of one
    station (probe) ignores the column, as ``predict`` does.

    Raises:
        OptionError: an option names a station (probe) the run lacks.
        MeasurementFileError: a row names a station (probe) the run lacks, or one other than the option's (file, line
            and column named).
    """
    out = []
    for key, option, known in (("station", station, model.robot.stations), ("probe", probe, model.robot.probes)):
        if option is not None and option not in known:
            have = f"the run's {key}s are {', '.join(known)}" if known else f"the run has a single {key}"
            raise OptionError(f"{key} {option!r} is not one of the run's: {have}")
        index = torch.full(
            (data.n,), known.index(option) if option is not None else 0, dtype=torch.long, device=data.q.device
        )
        column, names = getattr(data, key), getattr(data, f"{key}_names")
        if column is not None and known:
            for k, name in enumerate(names):
                rows = torch.nonzero(column.cpu() == k).flatten()
                if not len(rows):
                    continue
                line = data.lines[int(rows[0])] if data.lines else int(rows[0]) + 1
                if name not in known:
                    message = f"{key} {name!r} is not one of the run's {key}s ({', '.join(known)})"
                    raise MeasurementFileError(data.source or "the targets", message, line=line, column=key)
                if option is not None and name != option:
                    message = f"{key} {name!r} conflicts with --{key} {option}"
                    raise MeasurementFileError(data.source or "the targets", message, line=line, column=key)
                index[rows] = known.index(name)
        out.append(index.to(data.q.device))
    return out[0], out[1]


def _subset(value, rows: Tensor, n: int):
    """``value[rows]`` for a per-row tensor of ``n`` rows; anything else as it is."""
    return value[rows] if isinstance(value, Tensor) and value.ndim >= 1 and len(value) == n else value


def _merge(n: int, parts: list[tuple[Tensor, CompensationResult, Tensor, Tensor]]) -> tuple:
    """One result of ``n`` rows from each group's rows and (result, extrapolation, plain rows)."""
    first = parts[0][1]
    dof = first.q.shape[1]
    q, q0 = first.q.new_zeros(n, dof), first.q.new_zeros(n, dof)
    miss, ext = first.miss.new_zeros(n), parts[0][2].new_zeros(n)
    kept, plain = q.new_zeros(n, dtype=torch.bool), q.new_zeros(n, dtype=torch.bool)
    status: list[Status] = [Status.UNREACHABLE] * n
    angle = None if first.miss_angle is None else first.miss_angle.new_zeros(n)
    fallback = None if first.position_only is None else q.new_zeros(n, dtype=torch.bool)
    for rows, res, e, p in parts:
        q[rows], q0[rows], miss[rows], ext[rows] = res.q, res.q_start, res.miss, e
        if angle is not None:
            angle[rows], fallback[rows] = res.miss_angle, res.position_only
        kept[rows], plain[rows] = res.branch_kept.cpu(), p.cpu()
        for k, i in enumerate(rows.tolist()):
            status[i] = res.status[k]
    it = max(r.iterations for _, r, _, _ in parts)
    res = CompensationResult(
        q=q,
        miss=miss,
        status=status,
        q_start=q0,
        iterations=it,
        branch_kept=kept,
        miss_angle=angle,
        position_only=fallback,
    )
    return res, ext, plain


def compensate_groups(
    full: MeasurementModel,
    station: Tensor,
    probe: Tensor,
    targets_of: Callable[[MeasurementModel, Tensor], tuple[Tensor, Tensor | None]],
    q_seed: Tensor | None = None,
    *,
    at: Callable,
    context: dict | None = None,
    **kw,
) -> tuple[CompensationResult, Tensor, Tensor]:
    """:func:`compensate_in_region` of each row in its own station's frame, with its own probe's lever arm and that
    pair's learned correction (a run of several stations or probes).

    Args:
        full: the run's model, of every station and probe.
        station, probe: each row's index ``(N,)`` int64 (:func:`row_groups`).
        targets_of: ``(model, rows) -> (p, R)``, the targets of ``rows`` in the instrument frame of ``model``, the
            run's model at the rows' station and probe (a program's point depends on the probe's lever arm): positions
            ``(n, 3)`` [m] and orientations ``(n, 3, 3)`` or None (positions only).
        q_seed: start joints ``(N, dof)`` [rad] or None.
        at: ``(model, station name or None, probe name or None) -> (model, ...)``, the run's model in one station's
            frame with one probe (:func:`torchcal.use.rundir.at_station`, passed in: the run directory's module
            imports this one).
        context: per-row context (as :func:`compensate`'s); on a trajectory the direction of motion is taken from the
            whole start before the rows are split.

    Returns:
        As :func:`compensate_in_region`, every row in the input's order.
    """
    n = len(station)
    robot = full.robot
    pairs = sorted({(int(s), int(p)) for s, p in zip(station.tolist(), probe.tolist(), strict=True)})
    context = dict(context or {})
    if q_seed is not None and context.get("direction") is None and context.pop("trajectory", False):
        context["direction"] = motion_direction(q_seed)
    parts = []
    for s, p in pairs:
        rows = torch.nonzero((station == s) & (probe == p)).flatten()
        model, *_ = at(full, robot.stations[s] if robot.stations else None, robot.probes[p] if robot.probes else None)
        sub_ctx = {k: _subset(v, rows, n) for k, v in context.items()}
        seed = None if q_seed is None else q_seed[rows]
        p, R = targets_of(model, rows)
        res, ext, plain = compensate_in_region(model, p, seed, context=sub_ctx, orientations=R, **kw)
        parts.append((rows.cpu(), res, ext, plain))
    if not parts:
        empty = torch.zeros(0, robot.dof, dtype=F64, device=robot.device)
        res = CompensationResult(
            q=empty, miss=empty[:, 0], status=[], q_start=empty, iterations=0, branch_kept=empty[:, 0] > 0
        )
        return res, empty[:, 0], empty[:, 0] > 0
    return _merge(n, parts)


def _nominal(robot: RobotModel, nominal: RobotModel | None) -> RobotModel:
    """``nominal``, or a copy of ``robot`` with its geometry corrections zeroed: the robot a program was written for."""
    if nominal is not None:
        return nominal
    import copy

    out = copy.deepcopy(robot)
    out.geometry.reset()
    return out


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
    nominal = _nominal(robot, nominal)
    with torch.no_grad():
        p = tf.transform_points(nominal.forward(q_program), robot.t_flange_probe().detach())
        if frame == "instrument":
            p = tf.transform_points(robot.T_tracker_base().detach(), p)
        elif frame != "base":
            raise OptionError(f"frame must be one of {FRAMES}, got {frame!r}")
    return p


def program_orientations(
    model: MeasurementModel, q_program: Tensor, *, nominal: RobotModel | None = None, frame: str = "instrument"
) -> Tensor:
    """The probe orientations a robot program means ``(N, 3, 3)``: the nominal model's flange orientation for its
    joints turned by the calibrated probe frame ``R_flange_probe`` (and, for ``frame="instrument"``, seen from the
    calibrated ``T_tracker_base``), as :func:`program_targets` takes the calibrated lever arm.

    Args:
        model: the calibrated model; its robot must carry the probe's orientation.
        q_program: ``(N, dof)`` nominal joint targets [rad].
        nominal: the nominal robot (default: the model's robot with its geometry corrections zeroed).
        frame: frame of the returned orientations.
    """
    robot = model.robot
    nominal = _nominal(robot, nominal)
    with torch.no_grad():
        R = nominal.forward(q_program)[..., :3, :3] @ robot.tool_rotation.matrix().detach()
        if frame == "instrument":
            R = robot.T_tracker_base().detach()[:3, :3] @ R
        elif frame != "base":
            raise OptionError(f"frame must be one of {FRAMES}, got {frame!r}")
    return R


def orientation_mode(robot: RobotModel, data: Measurements, position_only: bool = False) -> tuple[bool, str]:
    """Whether a targets file is compensated in 6-D (position and orientation) and why (or why positions only).

    Orientation targets are the file's ``rx, ry, rz``, or, for rows of nominal joints alone (a robot program), the
    orientation the nominal model gives them. They are solved where the run's model carries the probe's orientation
    (a run calibrated with ``rx, ry, rz``) and the robot has six joints or more.

    Returns:
        ``(six_d, text)``: the choice and a sentence that says it (for the output's header and the log).
    """
    has_target = data.r is not None or (data.p is None and data.dof > 0)
    if position_only:
        return False, "position only (--position-only)"
    if not has_target:
        return False, "position only (the targets have no orientation: no rx,ry,rz columns, no program joints alone)"
    if not robot.has_orientation:
        return False, "position only (the run has no orientation model: it was calibrated without rx,ry,rz)"
    if robot.dof < 6:
        return False, f"position only (a robot of {robot.dof} joints cannot reach a full pose)"
    source = "the targets' rx,ry,rz" if data.r is not None else "the orientation the nominal model gives the program"
    return True, f"position and orientation ({source})"


def file_units(joint_types: Sequence[str], length_unit: str = "m", angle_unit: str = "rad") -> tuple[Tensor, float]:
    """Factors from SI to a file's units: per joint ``(dof,)`` (a revolute joint's angle unit, a prismatic joint's
    length unit) and for lengths (``compensate`` writes in the units it read)."""
    from torchcal.data.measurements import ANGLE_UNITS, LENGTH_UNITS

    length = LENGTH_UNITS[length_unit]
    angle = 1.0 / ANGLE_UNITS[angle_unit]
    return torch.tensor([length if k == "prismatic" else angle for k in joint_types], dtype=F64), length


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
    "compensate_groups",
    "row_groups",
    "geometry_and_physics",
    "nominal_ik",
    "program_targets",
    "program_orientations",
    "orientation_mode",
    "file_units",
    "rotation_miss",
    "model_miss",
    "configuration_sign",
    "full_jacobian",
)


def _cells(v) -> list[str]:
    """A column's cells: numbers with ``repr`` (read back bit-identical), names as they are."""
    if isinstance(v, Tensor):
        return [repr(float(x)) for x in v.detach().to(F64).tolist()]
    return [str(x) for x in v]


def write_joints(
    path,
    result: CompensationResult,
    *,
    targets: Tensor | None = None,
    t: Tensor | None = None,
    temperature: Tensor | None = None,
    labels: dict[str, Sequence[str]] | None = None,
    extra: dict[str, Tensor | Sequence[str]] | None = None,
    meta: dict[str, str] | None = None,
    written_by: str | None = None,
) -> None:
    """Write the compensated joints as CSV, atomically:
    ``q1..qN[,x,y,z][,t][,temperature][,labels...][,extra...],miss[,miss_angle],status``.

    Numbers as given (the command line scales joints, positions and ``miss`` to the targets file's units first,
    :func:`file_units`; ``miss_angle`` is in rad), every number with ``repr`` (reads back bit-identical);
    ``labels`` are text columns (each row's ``station`` and ``probe`` name), an ``extra`` column of names (``model``)
    is written as text where it stands; ``status`` is
    ``converged``, ``limit`` or ``unreachable``. Every input row gets one output row, in order.
    ``written_by``: the command, written first as ``# written_by: ...`` (how ``--out`` knows torchcal's files).
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
    text: list[tuple[str, list[str]]] = [(c, [repr(float(x)) for x in v.detach().to(F64).tolist()]) for c, v in cols]
    text += [(k, [str(x) for x in v]) for k, v in (labels or {}).items()]
    extra_cols = [(k, v) for k, v in (extra or {}).items() if k not in ("miss", "miss_angle", "status")]
    extra_cols.append(("miss", result.miss))
    if result.miss_angle is not None:
        extra_cols.append(("miss_angle", result.miss_angle))
    text += [(c, _cells(v)) for c, v in extra_cols]
    lines = [f"# written_by: {written_by}\n"] if written_by is not None else []  # first: the --out mark
    lines += [f"# {k}: {v}\n" for k, v in (meta or {}).items() if k != "written_by"]
    lines.append(",".join([c for c, _ in text] + ["status"]) + "\n")
    for i, st in enumerate(result.status):
        lines.append(",".join(v[i] for _, v in text) + f",{st.value}\n")
    path.parent.mkdir(parents=True, exist_ok=True)  # as predict, plan and export make theirs: at the end, on success
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
