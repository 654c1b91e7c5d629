"""A calibration as a least-squares problem: free parameters <-> flat vector, whitened residuals.

Stochastic model per pose ``i``: ``Sigma_i = diag(s_x^2, s_y^2, s_z^2) + sigma_q^2 J_q,i J_q,i^T``, the
tracker's own precision plus the joint noise propagated to the probe (``J_q = dp/dq``, tracker
frame). Residuals are whitened with ``L_i^-1`` (``Sigma_i = L_i L_i^T``), so the variance factor
of a correct model is 1.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import nn

from torchcal import _dual
from torchcal.effects.base import Context
from torchcal.effects.model import MeasurementModel
from torchcal.errors import EstimationError
from torchcal.robot import transforms as tf

Tensor = torch.Tensor


@dataclass
class _Entry:
    name: str  # qualified parameter name in the module
    index: Tensor  # flat indices of the free elements
    shape: torch.Size


class FreeParameters:
    """The free elements of selected parameters of a module, as one flat vector.

    Args:
        module: the module owning the parameters (e.g. a :class:`MeasurementModel`).
        selection: qualified parameter name -> boolean mask of the same shape (True = free).
        labels: qualified parameter name -> list of element names (flat order), for reports.
    """

    def __init__(self, module: nn.Module, selection: dict[str, Tensor], labels: dict[str, list[str]] | None = None):
        self.module = module
        params = dict(module.named_parameters())
        self.entries: list[_Entry] = []
        self.names: list[str] = []
        labels = labels or {}
        for name, mask in selection.items():
            if name not in params:
                raise KeyError(f"no parameter '{name}'; parameters: {', '.join(params)}")
            p = params[name]
            mask = torch.as_tensor(mask, dtype=torch.bool, device=p.device).reshape(p.shape)
            idx = torch.nonzero(mask.flatten()).flatten()
            if len(idx) == 0:
                continue
            self.entries.append(_Entry(name, idx, p.shape))
            lab = labels.get(name) or [f"{name}[{i}]" for i in range(p.numel())]
            self.names += [lab[int(i)] for i in idx]

    def __len__(self) -> int:
        return len(self.names)

    def vector(self) -> Tensor:
        params = dict(self.module.named_parameters())
        parts = [params[e.name].detach().flatten()[e.index] for e in self.entries]
        return torch.cat(parts) if parts else next(iter(params.values())).new_zeros(0)

    def params(self, x: Tensor) -> dict[str, Tensor]:
        """Full parameter tensors with ``x`` put into the free places (differentiable in ``x``)."""
        current = dict(self.module.named_parameters())
        out, k = {}, 0
        for e in self.entries:
            base = current[e.name].detach().flatten()
            n = len(e.index)
            out[e.name] = base.index_put((e.index,), x[k : k + n]).reshape(e.shape)
            k += n
        return out

    def assign(self, x: Tensor) -> None:
        """Write ``x`` into the module's parameters."""
        params = dict(self.module.named_parameters())
        with torch.no_grad():
            for name, value in self.params(x.detach()).items():
                params[name].copy_(value)


def probe_joint_jacobian(model: MeasurementModel, ctx: Context) -> Tensor:
    """``dp_tracker / dq`` per pose ``(N, 3, dof)`` of the geometric model (the effects' share is negligible)."""
    with torch.no_grad():
        robot = model.robot
        if robot.stations or robot.probes:
            _, J = robot.probe_jacobian(ctx.q, ctx.probe if robot.probes else None)
            return station_rotation(robot, ctx) @ J
        _, J = robot.probe_jacobian(ctx.q)
        return robot.T_tracker_base()[:3, :3] @ J


def station_rotation(robot, ctx: Context) -> Tensor:
    """The rotation of the instrument pose that measured each row: ``(3, 3)`` for a single station, else
    ``(N, 3, 3)`` by ``ctx.station``."""
    T = robot.instrument.rows(ctx.station) if robot.stations else robot.T_tracker_base()
    return T[..., :3, :3]


def whitening(
    model: MeasurementModel, ctx: Context, sigma: Tensor | None, sigma_tracker: float, sigma_joint: float
) -> Tensor:
    """Per-pose whitening matrices ``L_i^-1 (N, 3, 3)`` of the stochastic model (module docstring).

    Args:
        sigma: per-pose tracker standard deviations ``(N, 3)`` [m], or None to use ``sigma_tracker``.
        sigma_joint: joint reading noise [rad].
    """
    jac = (lambda: probe_joint_jacobian(model, ctx)) if sigma_joint > 0 else None
    return _whitening_of(ctx, sigma, sigma_tracker, sigma_joint, jac, "observation")


def _whitening_of(
    ctx: Context, sigma: Tensor | None, default: float, sigma_joint: float, jacobian, what: str
) -> Tensor:
    """``L_i^-1 (N, 3, 3)`` of ``C_i = diag(sigma_i^2) + sigma_joint^2 J_i J_i^T``: ``sigma (N, 3)`` or ``default``
    per axis, ``jacobian()`` the ``(N, 3, dof)`` joint Jacobian of the observed quantity (None: no joint noise)."""
    n = ctx.q.shape[0]
    s = torch.full((n, 3), float(default), dtype=ctx.q.dtype, device=ctx.q.device) if sigma is None else sigma
    C = torch.diag_embed(s.square())
    if jacobian is not None:
        J = jacobian()
        C = C + sigma_joint**2 * J @ J.transpose(1, 2)
    L, info = torch.linalg.cholesky_ex(C)
    if bool((info != 0).any()):
        bad = int(torch.nonzero(info).flatten()[0])
        raise EstimationError(f"{what} covariance of pose {bad} is not positive definite")
    eye = torch.eye(3, dtype=C.dtype, device=C.device).expand_as(C)
    return torch.linalg.solve_triangular(L, eye, upper=False)


#: residual functions differentiated by ``torch.func.jacfwd`` do so in chunks of this many poses: ``jacfwd`` keeps
#: one copy of every intermediate of the forward pass per parameter, so its memory grows with poses x parameters
JACOBIAN_CHUNK = 1024
#: the tangents JACOBIAN_CHUNK is sized for (a 6-axis arm's free parameters); a pass that pushes fewer takes
#: proportionally more poses per chunk, in the same memory (the orientation rows': its fixed cost per call is most of
#: a chunk's time there)
JACOBIAN_TANGENTS = 32

_ROBOT_GROUPS = {
    "robot.geometry.delta": "geometry",
    "robot.instrument.delta": "instrument",
    "robot.tool.delta": "tool",
    "robot.readings.delta": "readings",
}


def residual_function(
    model: MeasurementModel,
    free: FreeParameters,
    ctx: Context,
    p: Tensor,
    W: Tensor,
    prior_sigma: Tensor | None = None,
    chunk: int = JACOBIAN_CHUNK,
    linear: bool = True,
):
    """``x -> r(x)``: whitened residuals ``W_i (f_i(x) - p_i)`` flattened to ``(3N,)``.

    With ``prior_sigma (u,)`` the a-priori information ``x_j ~ N(0, prior_sigma_j^2)`` is appended as
    pseudo-observations ``x_j / prior_sigma_j`` for every finite entry (inf: no prior).

    The returned function carries its Jacobian ``fun.jacobian: x -> J (3N [+ priors], u)`` (used by
    :func:`~torchcal.estimate.lm.levenberg_marquardt` and :func:`jacobian_of`): analytic
    (:meth:`~torchcal.robot.model.RobotModel.tracker_jacobian`) when the model has no effects and only
    the robot's groups are free; with effects, ``torch.func.jacfwd`` of the model with its kinematics replaced by
    their tangent at ``x`` (:func:`linear_kinematics`: the same derivatives, without pushing every parameter's
    tangent through the chain of every pose; what effects compute from the robot under ``no_grad`` stays constant,
    as in reverse-mode autograd); with ``linear=False`` ``jacfwd`` of the whole model over ``chunk`` poses at a time
    (which also differentiates through ``no_grad``).
    """
    prior = _prior_pseudo_observations(prior_sigma)

    def residuals(x: Tensor, c: Context, pp: Tensor, WW: Tensor) -> Tensor:
        pred = torch.func.functional_call(model, free.params(x), (c,))
        return (WW @ _dual.sub(pred, pp).unsqueeze(-1)).reshape(-1)

    def fun(x: Tensor) -> Tensor:
        r = residuals(x, ctx, p, W)
        return torch.cat([r, x[prior.idx] * prior.inv]) if prior else r

    plan = _jacobian_plan(model, free, ctx.q.device)

    def jacobian(x: Tensor) -> Tensor:
        x = x.detach()
        if plan.analytic:
            J = _analytic_jacobian(model, free, plan, ctx, W, x)
        elif linear:
            J = _linearised_jacobian(model, free, plan, x, ctx, W)
        else:
            J = _chunked_jacobian(residuals, ctx, p, W, x, chunk)
        return torch.cat([J, prior.rows(x)]) if prior else J

    fun.jacobian = jacobian
    return fun


@dataclass
class _Prior:
    """The finite entries of a prior's sigmas: ``idx`` (which columns of x) and ``inv`` (1 / sigma there)."""

    idx: Tensor
    inv: Tensor

    def rows(self, x: Tensor) -> Tensor:
        """The pseudo-observations' Jacobian rows: ``inv`` on each one's own column."""
        rows = torch.zeros(len(self.idx), len(x), dtype=x.dtype, device=x.device)
        rows[torch.arange(len(self.idx), device=x.device), self.idx] = self.inv
        return rows


def _prior_pseudo_observations(prior_sigma: Tensor | None) -> _Prior | None:
    """The prior as pseudo-observations, or None where it constrains nothing (absent or all inf)."""
    if prior_sigma is None or not bool(torch.isfinite(prior_sigma).any()):
        return None
    idx = torch.nonzero(torch.isfinite(prior_sigma)).flatten()
    return _Prior(idx, 1.0 / prior_sigma[idx])


@dataclass
class _JacobianPlan:
    """Which columns of x each way of computing the Jacobian fills, fixed once per residual function."""

    analytic: bool  # no effects and only the robot's groups free: tracker_jacobian gives every column
    columns: list  # analytic: (group, index) of each moved column
    unmoved: list  # the probe frame's rotation: zero columns (it does not move the probe's position)
    moved: Tensor  # the other columns
    kin_cols: Tensor  # geometry and lever-arm columns of x ...
    kin_d: Tensor  # ... and where each sits in _corrections' flat vector (host indices: linear_kinematics reads them)
    inst: list  # (column of x, index in the instrument pose) where the closed form applies
    inst_cols: Tensor
    inst_d: list
    rest: Tensor  # the columns jacfwd differentiates


def _jacobian_plan(model: MeasurementModel, free: FreeParameters, dev) -> _JacobianPlan:
    """Sort the free columns by how :func:`residual_function`'s Jacobian computes them."""
    unmoved = [j for j, e, _ in _columns(free) if e.name == _TOOL_ROTATION]
    analytic = len(model.effects) == 0 and all(
        e.name in _ROBOT_GROUPS or e.name == _TOOL_ROTATION for e in free.entries
    )
    columns = (
        [(_ROBOT_GROUPS[e.name], int(i)) for e in free.entries if e.name != _TOOL_ROTATION for i in e.index]
        if analytic
        else []
    )
    moved = torch.tensor([j for j in range(len(free)) if j not in set(unmoved)], dtype=torch.long, device=dev)

    # the free columns of the geometry and the lever arm, and where each sits in the flat corrections of
    # _corrections: they reach the prediction through the kinematics' tangent alone (linearised)
    offsets, k = {}, 0
    for name in _kinematic(model.robot):
        offsets[name] = k
        k += dict(model.named_parameters())[name].numel()
    kin = [(j, offsets[e.name] + int(i)) for j, e, i in _columns(free) if e.name in offsets]
    # the instrument pose's columns: the prediction is T(d) q' with q' the base-frame point it transforms, so
    # they are dT/dd q' (Instrument.point_jacobian) from the plain prediction, which spares every Jacobian six more
    # tangents through the transform's exponential map (jacfwd's way). Not where an effect reads the pose itself
    # (Effect.reads_instrument): then q' depends on it too, and jacfwd takes them
    closed = not any(e.reads_instrument for e in model.effects)
    inst = [(j, int(i)) for j, e, i in _columns(free) if e.name == _INSTRUMENT] if closed else []
    fixed = {j for j, _ in kin} | {j for j, _ in inst} | set(unmoved)
    return _JacobianPlan(
        analytic=analytic,
        columns=columns,
        unmoved=unmoved,
        moved=moved,
        kin_cols=torch.tensor([j for j, _ in kin], dtype=torch.long, device=dev),
        kin_d=torch.tensor([i for _, i in kin], dtype=torch.long),
        inst=inst,
        inst_cols=torch.tensor([j for j, _ in inst], dtype=torch.long, device=dev),
        inst_d=[i for _, i in inst],
        rest=torch.tensor([j for j in range(len(free)) if j not in fixed], dtype=torch.long, device=dev),
    )


def _analytic_jacobian(model, free, plan: _JacobianPlan, ctx: Context, W: Tensor, x: Tensor) -> Tensor:
    """The whitened Jacobian from :meth:`~torchcal.robot.model.RobotModel.tracker_jacobian` (no effects)."""
    n = ctx.q.shape[0]
    values = {_ROBOT_GROUPS[k]: v for k, v in free.params(x).items() if k != _TOOL_ROTATION}
    _, Jp = model.robot.tracker_jacobian(ctx.q, plan.columns, values, **_rows(model.robot, ctx))
    if plan.unmoved:
        Jp = Jp.new_zeros(n, 3, len(x)).index_copy_(2, plan.moved.to(x.device), Jp)
    return (W @ Jp).reshape(3 * n, len(x))


def _chunked_jacobian(residuals, ctx: Context, p: Tensor, W: Tensor, x: Tensor, chunk: int) -> Tensor:
    """``jacfwd`` of the whole model, ``chunk`` poses at a time (its memory grows with poses x parameters)."""
    n = ctx.q.shape[0]
    parts = []
    for lo in range(0, n, max(1, int(chunk))):
        sl = slice(lo, min(n, lo + max(1, int(chunk))))
        part = functools.partial(residuals, c=ctx.subset(sl), pp=p[sl], WW=W[sl])
        parts.append(torch.func.jacfwd(part)(x).detach())
    return torch.cat(parts) if parts else torch.zeros(0, len(x), dtype=x.dtype, device=x.device)


def _linearised_jacobian(model, free, plan: _JacobianPlan, x: Tensor, c: Context, WW: Tensor) -> Tensor:
    """Exact first derivatives at x: the kinematics replaced by its tangent there, the rest differentiated; the
    whitening (constant) applied to the (N, 3, u) prediction Jacobian after it.

    The geometry and the lever arm reach the prediction through fk only: the module sees their plain values, so
    what an effect computes from the robot under no_grad (a compliance's gravity torque) stays a constant, as
    reverse-mode autograd has it (forward-mode transforms ignore no_grad and would push every tangent through the
    torque's chain too). Their columns are then the chain rule G_i J_d,i with G_i = d prediction_i / d p_base,i
    (3 x 3 per pose: Cartesian effects and the tracker act pose by pose): jacfwd pushes 3 tangents for G instead of
    one per geometric parameter, and the model's other parameters as before.
    """
    at = free.params(x)
    fk = linear_kinematics(model, c, at, columns=plan.kin_d)
    rest = plan.rest.to(x.device)
    x_rest = x[rest]

    def pred(z: Tensor) -> Tensor:
        y = x.index_put((rest,), z[3:])
        params = free.params(y)
        kinematic = _kinematic(model.robot)
        plain = {k: at[k] if k in kinematic or (k == _INSTRUMENT and plan.inst) else v for k, v in params.items()}
        shifted = lambda rb, q: _dual.add(fk(rb, q), z[:3])  # noqa: E731 (fk's may be constant)
        return torch.func.functional_call(model, plain, (c,), {"fk": shifted})

    Jz = torch.func.jacfwd(pred)(torch.cat([x.new_zeros(3), x_rest])).detach()  # (N, 3, 3 + len(rest))
    Jp = x.new_zeros(Jz.shape[0], 3, len(x))
    Jp[..., rest] = Jz[..., 3:]
    if len(plan.kin_cols):
        Jp[..., plan.kin_cols.to(x.device)] = Jz[..., :3] @ fk.jd
    if plan.inst:
        Jp[..., plan.inst_cols.to(x.device)] = _instrument_columns(model, plan, c, fk.prediction, at)
    return (WW @ Jp).reshape(-1, len(x))


def _instrument_columns(model, plan: _JacobianPlan, c: Context, prediction: Tensor, at: dict) -> Tensor:
    """The instrument pose's columns in closed form: dT/dd q' with q' = T^-1 p the base-frame point."""
    instrument = model.robot.instrument
    if instrument.stations:  # each row's station: q' = T_s^-1 p, the columns of other stations zero
        T = instrument.rows(c.station, at.get(_INSTRUMENT)).detach()
        base = ((prediction - T[:, :3, 3]).unsqueeze(1) @ T[:, :3, :3]).squeeze(1)
        return instrument.rows_point_jacobian(base, c.station, plan.inst_d, at.get(_INSTRUMENT))
    T = instrument.matrix(at.get(_INSTRUMENT)).detach()
    base = (prediction - T[:3, 3]) @ T[:3, :3]  # q' = T^-1 p
    return instrument.point_jacobian(base, plan.inst_d, at.get(_INSTRUMENT))


def linear_kinematics(
    model: MeasurementModel, ctx: Context, params: dict[str, Tensor] | None = None, columns: Tensor | None = None
):
    """The robot's kinematics linearised at the model's current joint angles: ``fk(robot, q) -> (N, 3)`` for
    :meth:`MeasurementModel.forward <torchcal.effects.model.MeasurementModel.forward>`.

    ``fk(robot, q[, d]) = p0 + J_q (q - q0) + J_d (d - d0)``: ``q0 (N, dof)`` the joint angles with the joint
    effects applied, ``p0 (N, 3)`` the probe in the base frame there, ``J_q (N, 3, dof)`` the joint Jacobian, ``d``
    the geometry and lever-arm corrections (flat; read from ``robot`` when not given) and ``J_d (N, 3, k)`` their
    base-frame Jacobian
    (:meth:`~torchcal.robot.model.RobotModel.tracker_jacobian`). Its value and first derivatives at the
    current point equal the kinematics', so ``jacfwd`` of a model with ``fk`` in place gives the exact Jacobian;
    the chain of rotations, the costly part, is evaluated twice instead of once per parameter.

    Args:
        model: the measurement model.
        ctx: the samples.
        params: parameter values to linearise at (qualified name -> tensor, as for ``functional_call``);
            default the model's own.
        columns: flat indices into ``d`` of the corrections that may move; the others are held at ``d0`` and
            their Jacobian is not computed. ``fk.jd`` is ``J_d``'s columns ``(N, 3, len(columns))``, and
            ``fk.prediction`` the model's prediction ``(N, 3)`` [m] at ``params``.
    """
    out: dict[str, Tensor] = {}

    def record(rb, q: Tensor) -> Tensor:
        q = q.detach()
        cols = [(g.split(".")[1], i) for g in _kinematic(rb) for i in range(rb.groups()[g.split(".")[1]].delta.numel())]
        if columns is not None:
            cols = [cols[int(i)] for i in columns]
        if rb.stations or rb.probes:
            p_tr, J = rb.tracker_jacobian(q, cols, **_rows(rb, ctx))
            R = station_rotation(rb, ctx)
            pb, Jq = rb.probe_jacobian(q, ctx.probe if rb.probes else None)
        else:
            p_tr, J = rb.tracker_jacobian(q, cols)
            R = rb.T_tracker_base()[:3, :3]
            pb, Jq = rb.probe_jacobian(q)
        out.update(q=q, p=pb, Jq=Jq, Jd=R.transpose(-1, -2) @ J, d=_corrections(rb))
        return pb

    with torch.no_grad():
        prediction = torch.func.functional_call(model, params or {}, (ctx,), {"fk": record})
    q0, p0, Jq, Jd, d0 = out["q"], out["p"], out["Jq"], out["Jd"], out["d"]
    if columns is not None:
        d0 = d0[columns.to(d0.device)]

    def fk(rb, q: Tensor, d: Tensor | None = None) -> Tensor:
        # under torch.func these become one batched product over the poses and one plain matrix product (matrix
        # kernels, faster than elementwise products and sums, or einsum). The constants of the linearisation meet the
        # differentiated q and d through torchcal._dual: torch's Python path (and an import of torch._dynamo)
        # otherwise, in every Jacobian
        dq = (Jq @ _dual.sub(q, q0).unsqueeze(-1)).squeeze(-1)
        d = _corrections(rb) if d is None else d
        if columns is not None and len(d) != len(d0):
            d = d[columns.to(d.device)]
        # explicit rows: with no kinematic column free (a re-stationing moves the instrument only) Jd is (N, 3, 0)
        shift = (Jd.reshape(p0.numel(), Jd.shape[-1]) @ _dual.sub(d, d0)).reshape(p0.shape)
        return _dual.add(_dual.add(p0, dq), shift)

    fk.jd = Jd
    fk.prediction = prediction
    return fk


#: the parameters :func:`linear_kinematics` carries: geometry and lever-arm corrections (and the readings map's, where
#: the robot calibrates one: :func:`_kinematic`)
_KINEMATIC = ("robot.geometry.delta", "robot.tool.delta")


def _kinematic(robot) -> tuple[str, ...]:
    """The parameters the kinematics' linearisation carries for ``robot``: :data:`_KINEMATIC`, then the readings
    map's correction where the robot has free ratios (they reach the prediction through the chain alone)."""
    return _KINEMATIC + (("robot.readings.delta",) if "readings" in robot.groups() else ())


#: the probe frame's rotation in the flange frame (a 6-D probe: RobotModel.enable_orientation)
_TOOL_ROTATION = "robot.tool_rotation.delta"

#: the instrument pose's correction, whose Jacobian columns :func:`residual_function` computes in closed form
_INSTRUMENT = "robot.instrument.delta"

#: the lever arm's correction (the probe's position in the flange frame: no part in its orientation)
_LEVER_ARM = "robot.tool.delta"


def _corrections(robot, params: dict[str, Tensor] | None = None) -> Tensor:
    """The geometry and lever-arm corrections of ``robot`` as one flat vector (``params``' values where given)."""
    params = params or {}
    parts = [params.get(k, getattr(robot, k.split(".")[1]).delta) for k in _kinematic(robot)]
    return torch.cat([v.reshape(-1) for v in parts])


def _columns(free: FreeParameters):
    """``(column of x, entry, flat index in the entry's parameter)`` for every free element, in ``x``'s order."""
    j = 0
    for e in free.entries:
        for i in e.index.tolist():
            yield j, e, i
            j += 1


def _rows(robot, ctx: Context) -> dict[str, Tensor | None]:
    """The station and probe indices :meth:`~torchcal.robot.model.RobotModel.tracker_jacobian` needs for ``robot``."""
    return {"station": ctx.station if robot.stations else None, "probe": ctx.probe if robot.probes else None}


def jacobian_of(fun):
    """The Jacobian function of a residual function: its own ``fun.jacobian`` when it has one
    (:func:`residual_function`), else ``torch.func.jacfwd(fun)``."""
    return getattr(fun, "jacobian", None) or torch.func.jacfwd(fun)


def prior_sigmas(
    free: FreeParameters,
    units: dict[str, str],
    sigma_length: float | None,
    sigma_angle: float | None,
    by_name: dict[str, float] | None = None,
) -> Tensor:
    """Prior standard deviations per free element: ``by_name``'s where it names one (the instrument pose and
    the lever arm), else by unit (``units``: geometry), inf (no prior) elsewhere."""
    out = torch.full((len(free),), float("inf"), dtype=torch.float64, device=free.vector().device)
    by_name = by_name or {}
    for i, name in enumerate(free.names):
        unit = units.get(name)
        if name in by_name:
            out[i] = by_name[name]
        elif unit == "m" and sigma_length is not None:
            out[i] = sigma_length
        elif unit == "rad" and sigma_angle is not None:
            out[i] = sigma_angle
    return out


# ----------------------------------------------------------------------------- orientation (6-D probes)


def orientation_error(R_pred: Tensor, R_meas: Tensor) -> Tensor:
    """The small rotation that takes the measured orientation to the predicted one, in the tracker frame
    ``(N, 3)`` [rad]: the axial vector of ``E = R_pred R_meas^T`` (``sin(angle) * axis``, the rotation vector of
    ``E`` to third order in the angle, smooth everywhere, so its Jacobian is exact where the angle is 0).
    A 6-D probe's orientation error after calibration is a fraction of a degree, where the two agree to 1e-7."""
    E = R_pred @ R_meas.transpose(-1, -2)
    w = torch.stack([E[..., 2, 1] - E[..., 1, 2], E[..., 0, 2] - E[..., 2, 0], E[..., 1, 0] - E[..., 0, 1]], -1)
    return _dual.mul_scalar(w, 0.5)  # not w * 0.5: under jacfwd that imports torch._dynamo (torchcal._dual)


def orientation_angle(R_pred: Tensor, R_meas: Tensor) -> Tensor:
    """The angle between the predicted and the measured orientation ``(N,)`` [rad], accurate at every angle
    (``atan2(|sin|, cos)`` of ``E = R_pred R_meas^T``)."""
    E = R_pred @ R_meas.transpose(-1, -2)
    cos = (E[..., 0, 0] + E[..., 1, 1] + E[..., 2, 2] - 1.0) * 0.5
    return torch.atan2(orientation_error(R_pred, R_meas).norm(dim=-1), cos)


def orientation_joint_jacobian(model: MeasurementModel, ctx: Context) -> Tensor:
    """``d e / d q`` per pose ``(N, 3, dof)`` [rad/rad]: how a joint reading turns the probe frame, in the tracker
    frame (the geometric model's). The geometric Jacobian's angular rows: a revolute joint turns the frame about
    its axis ``z_j`` (in the base frame, from the joint frames), a prismatic one not at all; with a readings map
    the derivative is by the readings (``J A``). Exact, and no forward-mode pass: ``torch.func.jvp`` through the
    chain imports ``torch._dynamo`` (:mod:`torchcal._dual`)."""
    robot = model.robot
    if ctx.q.shape[1] == 0:
        return ctx.q.new_zeros(len(ctx.q), 3, 0)
    R_tb = robot.T_tracker_base()[:3, :3]
    with torch.no_grad():
        F, _ = robot.joint_frames(ctx.q)  # (N, n_joints, 4, 4)
        z = (F[..., :3, :3] @ robot.geometry.axes.unsqueeze(-1)).squeeze(-1)  # (N, n_joints, 3)
        z = torch.where(robot.geometry.prismatic.unsqueeze(-1), torch.zeros_like(z), z)
        J = (z @ R_tb.T).transpose(-1, -2)  # (N, 3, n_joints)
        return J if robot.readings.is_identity else J @ robot.readings.matrix()


def orientation_whitening(
    model: MeasurementModel, ctx: Context, sigma_r: Tensor | None, sigma_orientation: float, sigma_joint: float
) -> Tensor:
    """Per-pose whitening ``L_i^-1 (N, 3, 3)`` of the orientation residuals: ``Sigma_i = diag(s_r^2) +
    sigma_q^2 J_w J_w^T``, the probe's own orientation precision (``sigma_r (N, 3)`` [rad], else
    ``sigma_orientation`` per axis) plus the joint noise turning the probe (``J_w``,
    :func:`orientation_joint_jacobian`). The cross-covariance with the position that the joint noise makes is left
    out: each row's position and orientation are whitened separately."""
    jac = (lambda: orientation_joint_jacobian(model, ctx)) if sigma_joint > 0 else None
    return _whitening_of(ctx, sigma_r, sigma_orientation, sigma_joint, jac, "orientation")


def orientation_function(
    model: MeasurementModel,
    free: FreeParameters,
    ctx: Context,
    R_meas: Tensor,
    W: Tensor,
    chunk: int = JACOBIAN_CHUNK,
    linear: bool = True,
):
    """``x -> r(x)``: whitened orientation residuals ``W_i e_i(x)`` flattened to ``(3N,)`` with
    ``e_i = orientation_error(R_pred,i(x), R_meas,i)`` (:func:`orientation_error`), and their Jacobian
    ``fun.jacobian``: ``torch.func.jacfwd`` of the model's :meth:`~torchcal.effects.model.MeasurementModel.
    orientation` over ``chunk`` poses at a time, with the chain's ``R_base_flange`` replaced by its tangent at ``x``
    (:func:`linear_rotation`: the same value and first derivatives, without pushing every parameter's tangent through
    the chain of every pose). The geometry reaches the rotation through that tangent only: the effects see its plain
    value, so what they compute from the robot under no_grad (a compliance's gravity torque) stays a constant, as in
    the position rows (:func:`_linearised_jacobian`) and in reverse-mode autograd; forward mode ignores no_grad and
    would push the geometry's tangents through the torque's chain. Of the tangents, the geometry's are three: a
    small turn of that rotation, each element's column the turn's times its axis (``dR/dd = [w_d]x R``); the instrument
    pose's columns are in closed form from the prediction (:func:`_instrument_turns`, unless an effect reads the
    pose) and the lever arm's are zero; so a chunk holds ``chunk * JACOBIAN_TANGENTS // tangents`` poses. A robot with
    a readings map, or ``linear=False``, differentiates the chain itself.

    Args:
        R_meas: measured orientations ``(N, 3, 3)`` (tracker frame).
        W: whitening ``(N, 3, 3)`` (:func:`orientation_whitening`).
    """

    def residuals(x: Tensor, c: Context, Rm: Tensor, WW: Tensor, rot=None) -> Tensor:
        R = torch.func.functional_call(model, free.params(x), (c,), {"orientation": True, "rot": rot})
        return (WW @ orientation_error(R, Rm).unsqueeze(-1)).reshape(-1)

    def fun(x: Tensor) -> Tensor:
        return residuals(x, ctx, R_meas, W)

    linear = linear and model.robot.readings.is_identity and "readings" not in model.robot.groups()

    plan = _orientation_plan(model, free)

    def _chunked(make, z: Tensor, size: int, finish=None) -> Tensor:
        return _chunked_jacfwd(make, ctx, R_meas, W, z, size, len(free), finish)

    def jacobian(x: Tensor) -> Tensor:
        x = x.detach()
        if not linear:
            return _chunked(lambda c, Rm, WW, sl: functools.partial(residuals, c=c, Rm=Rm, WW=WW), x, chunk)
        lin, at = linear_rotation(model, free, ctx, x), free.params(x)
        # the geometry turns the chain's rotation about an axis per pose (dR/dd = [w_d]x R): three tangents, a small
        # turn of R_base_flange, take its columns as d e / d turn @ w_d, where one tangent per element went before;
        # the instrument pose's columns are in closed form from the plain prediction, the lever arm's are zero
        z0 = torch.cat([x.new_zeros(3), x[plan.rest.to(x.device)]])
        inst = _instrument_turns(model, plan, at)
        rows = max(1, int(chunk)) * max(1, JACOBIAN_TANGENTS // len(z0))
        return _chunked(
            lambda c, Rm, WW, sl: functools.partial(_turned, at=at, x=x, c=c, Rm=Rm, WW=WW, rot=lin, sl=sl),
            z0,
            rows,
            lambda Jz, R, sl: _columns_of_turn(Jz, R, lin.spin(sl), x, plan, inst, ctx.subset(sl), R_meas[sl], W[sl]),
        )

    def _turned(z: Tensor, at, x: Tensor, c: Context, Rm: Tensor, WW: Tensor, rot, sl: slice):
        """The residuals of the parameters but the geometry, the instrument pose and the lever arm (``z[3:]``) with
        the chain's rotation turned by ``z[:3]``, and the predicted orientation; those held at their values at x
        (plain), so the effects' computations from the robot stay constants."""
        params = free.params(x.index_put((plan.rest.to(x.device),), z[3:]))
        plain = {k: at[k] if k in plan.held else v for k, v in params.items()}
        R = torch.func.functional_call(model, plain, (c,), {"orientation": True, "rot": rot(sl, z[:3])})
        return (WW @ orientation_error(R, Rm).unsqueeze(-1)).reshape(-1), R

    fun.jacobian = jacobian
    return fun


def _chunked_jacfwd(make, ctx: Context, R_meas: Tensor, W: Tensor, z: Tensor, size: int, u: int, finish=None):
    """``jacfwd`` of ``make(c, Rm, WW, sl)`` (a function of ``z``) over ``size`` poses of ``ctx`` at a time; where
    ``finish`` is given, ``make``'s function also returns the predicted orientation ``R`` and each part is
    ``finish(J, R, sl)``. ``u``: the columns of an empty result."""
    n, parts, size = ctx.q.shape[0], [], max(1, int(size))
    for lo in range(0, n, size):
        sl = slice(lo, min(n, lo + size))
        f = make(ctx.subset(sl), R_meas[sl], W[sl], sl)
        if finish is None:
            parts.append(torch.func.jacfwd(f)(z).detach())
            continue
        J, R = torch.func.jacfwd(f, has_aux=True)(z)
        parts.append(finish(J.detach(), R.detach(), sl))
    return torch.cat(parts) if parts else z.new_zeros(0, u)


@dataclass(frozen=True)
class _OrientationPlan:
    """How the orientation rows' Jacobian computes each free column (:func:`orientation_function`)."""

    geo: Tensor  # the geometry's columns: through a turn of the chain's rotation
    inst: Tensor  # the instrument pose's, in closed form (empty where an effect reads the pose)
    inst_d: list  # their flat indices in the instrument's correction
    rest: Tensor  # the columns jacfwd differentiates (the lever arm's, which no orientation sees, are in none)
    held: frozenset  # the parameters held at their values in that pass


def _orientation_plan(model: MeasurementModel, free: FreeParameters) -> _OrientationPlan:
    closed = not any(e.reads_instrument for e in model.effects)
    cols = list(_columns(free))
    geo = [j for j, e, _ in cols if e.name == _GEOMETRY]
    inst = [(j, i) for j, e, i in cols if e.name == _INSTRUMENT] if closed else []
    out = set(geo) | {j for j, _ in inst} | {j for j, e, _ in cols if e.name == _LEVER_ARM}
    held = {_GEOMETRY, _LEVER_ARM} | ({_INSTRUMENT} if closed else set())
    dev = free.vector().device
    return _OrientationPlan(
        geo=torch.tensor(geo, dtype=torch.long, device=dev),
        inst=torch.tensor([j for j, _ in inst], dtype=torch.long, device=dev),
        inst_d=[i for _, i in inst],
        rest=torch.tensor([j for j, _, _ in cols if j not in out], dtype=torch.long, device=dev),
        held=frozenset(held),
    )


def _instrument_turns(model: MeasurementModel, plan: _OrientationPlan, at: dict) -> Tensor | None:
    """The instrument columns' turns of every predicted orientation (:meth:`~torchcal.robot.model.Instrument.
    rotation_turns`) at the values ``at``; None without such columns."""
    if not plan.inst_d:
        return None
    instrument = model.robot.instrument
    return instrument.rotation_turns(plan.inst_d, at.get(_INSTRUMENT, instrument.delta))


def _columns_of_turn(
    Jz: Tensor, R: Tensor, w: Tensor, x: Tensor, plan: _OrientationPlan, inst, c: Context, Rm: Tensor, WW: Tensor
) -> Tensor:
    """The orientation rows' Jacobian by ``x`` from that by a turn of the chain's rotation and the columns
    ``plan.rest``, ``Jz (3n, 3 + len(rest))``: the geometry's are ``d e / d turn @ w``, ``w (n, 3, k)`` the axes by
    which they turn it (:func:`linear_rotation`'s ``spin``); the instrument pose's ``W d e`` with ``dE = N_k E``,
    ``E = R Rm^T`` (:func:`_instrument_turns`, ``R`` the predicted orientations)."""
    n = w.shape[0]
    J = x.new_zeros(3 * n, len(x))
    J[:, plan.rest.to(x.device)] = Jz[:, 3:]
    if len(plan.geo):
        J[:, plan.geo.to(x.device)] = (Jz[:, :3].reshape(n, 3, 3) @ w).reshape(3 * n, -1)
    if inst is not None:
        # (n or 1, k, 3, 3): each row's station's (no station column: the first station measured every row)
        N = inst[c.station] if inst.dim() == 4 and c.station is not None else inst.reshape(-1, *inst.shape[-3:])[:1]
        F = N @ (R @ Rm.transpose(-1, -2)).unsqueeze(1)  # (n, k, 3, 3)
        de = 0.5 * torch.stack(
            [F[..., 2, 1] - F[..., 1, 2], F[..., 0, 2] - F[..., 2, 0], F[..., 1, 0] - F[..., 0, 1]], -1
        )
        J[:, plan.inst.to(x.device)] = (WW @ de.transpose(1, 2)).reshape(3 * n, -1)
    return J


def linear_rotation(model: MeasurementModel, free: FreeParameters, ctx: Context, x: Tensor):
    """The chain's rotation ``R_base_flange`` linearised at ``x``, for :meth:`MeasurementModel.orientation
    <torchcal.effects.model.MeasurementModel.orientation>`: returns ``(rows, turn) -> rot``, with ``rot(robot, q) =
    R0 + [t]x R0``, ``t = sum_j z_j (q_j - q0_j) + turn`` over the poses ``rows`` (a slice), ``q0`` the joint angles
    with the joint effects applied at ``x`` and ``z_j`` the joints' axes
    (:meth:`~torchcal.robot.model.RobotModel.flange_rotation_axes`). Its value and first derivatives by the joints
    at ``x`` are the chain's; the geometry's elements turn it about the axes ``rows.spin(rows) (n, 3, k)``
    (``dR/dd_k = [w_k]x R``), so ``jacfwd`` of the model with ``rot`` in place, by ``turn`` and the other
    parameters, gives the chain's Jacobian."""
    at = free.params(x)
    geo = [e for e in free.entries if e.name == _GEOMETRY]
    idx = geo[0].index if geo else torch.zeros(0, dtype=torch.long, device=x.device)
    out: dict[str, Tensor] = {}

    def record(rb, q: Tensor) -> Tensor:
        q = q.detach()
        R, z, w = rb.flange_rotation_axes(q, idx.tolist())
        out.update(q=q, R=R, z=z, w=w)
        return R

    with torch.no_grad():
        torch.func.functional_call(model, at, (ctx,), {"orientation": True, "rot": record})

    def rows(sl: slice, turn: Tensor):
        R0, q0, zt = out["R"][sl], out["q"][sl], out["z"][sl].transpose(1, 2)  # zt (n, 3, dof)
        n = R0.shape[0]
        # [t]x R0 = sum_a t_a [e_a]x R0: linear in t
        A = (tf.skew(torch.eye(3, dtype=R0.dtype, device=R0.device)).unsqueeze(1) @ R0).permute(1, 2, 3, 0)
        A = A.reshape(n, 9, 3)  # once: a copy (A is permuted), not one per evaluation

        def rot(rb, q: Tensor) -> Tensor:
            # the constants meet the differentiated q and turn through torchcal._dual (as in linear_kinematics)
            t = _dual.add((zt @ _dual.sub(q, q0).unsqueeze(-1)).squeeze(-1), turn)
            return _dual.add(R0, (A @ t.unsqueeze(-1)).reshape(n, 3, 3))

        return rot

    rows.spin = lambda sl: out["w"][sl].transpose(1, 2)
    return rows


#: the geometry's correction (the free elements :func:`linear_rotation` carries)
_GEOMETRY = "robot.geometry.delta"


def stack_functions(*funs):
    """One residual function of several (their residuals and Jacobians stacked): a 6-D probe's position and
    orientation rows, each whitened by its own covariance."""

    def fun(x: Tensor) -> Tensor:
        return torch.cat([f(x) for f in funs])

    fun.jacobian = lambda x: torch.cat([jacobian_of(f)(x) for f in funs])
    return fun
