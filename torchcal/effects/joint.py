"""Effects that act on one joint angle: compliance, backlash, cyclic transmission errors, couplings."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from torchcal import _dual
from torchcal.effects.base import Context, Effect, register_range

Tensor = torch.Tensor

#: the largest size [rad] a fitted joint-angle error function may reach anywhere on its joint's range (half its
#: peak-to-peak there: a constant part is the joint's offset, which the geometry carries). Harmonic drives and
#: gearboxes of industrial arms have transmission errors of a few arcminutes at most (1 arcmin = 0.29 mrad); 5 mrad
#: (17 arcmin, 5 mm at a 1 m lever) is loose for a real one and rules out what only cancelling terms can make.
#: A prismatic joint moves the probe by its own error (a lever of 1 m per m), so the same number bounds it in metres:
#: 5 mm, the same displacement at the probe (:func:`joint_bound_scale`), and far beyond a track's or a ball screw's
#: error. Settable per run (``Options.max_joint_error``, ``--max-joint-error``).
MAX_JOINT_ERROR = 5e-3

#: the fade length [rad or m] of an open joint-angle form beyond the range its joint covered in the fit: the
#: function is held at its value at the edge and multiplied by ``exp(-d^2 / (2 FADE_LENGTH^2))``, ``d`` the
#: distance beyond the edge: 0.05 rad out 97 % of it is left (a pose just beyond the fitted ones, where a real
#: effect still holds), 0.3 rad out 32 %, 0.6 rad out 1 %. The learned corrections fade the same way beyond the
#: calibrated region (:meth:`torchcal.effects.MeasurementModel.set_region`).
FADE_LENGTH = 0.2


class RegionForm(Effect):
    """An open joint-angle form (a harmonic sum, a polynomial): a shape fitted to the range its joint covered,
    with no law that says how it continues. Beyond that range it fades to zero, i.e. to the geometry
    (:data:`FADE_LENGTH`), so that terms which the range did not determine cannot add up outside it.

    ``region``: ``(lo, hi)`` of the joint's fitted range [rad], its calibrated region; None (the default, and runs
    written before the fade existed): the form is applied as it is everywhere. Runs written before the name
    ``region`` saved it as ``support`` (:attr:`renamed`).
    """

    renamed = {"support": "region"}

    def _init_region(self, region) -> None:
        register_range(self, "region", region, f"{self.kind} region")

    def set_region(self, q: Tensor) -> None:
        """Record the range of this effect's joint in ``q`` ``(N, dof)`` as the fitted range."""
        qj = q[:, self.j].detach()
        self.region = torch.stack([qj.min(), qj.max()]).to(torch.float64)

    def _unbounded(self) -> bool:
        """Whether the fitted range makes the form determined everywhere (a full period of a harmonic sum)."""
        return False

    def _faded(self, ctx: Context) -> tuple[Tensor, Tensor | None]:
        """The joint's reading clamped to the fitted range ``(N, 1)``, and the fade weight ``(N, 1)`` (None: 1)."""
        qj = ctx.q[:, self.j : self.j + 1]
        if self.region is None or self._unbounded():
            return qj, None
        lo, hi = self.region[0], self.region[1]
        c = torch.minimum(torch.maximum(qj, lo), hi)
        d = (qj - c).abs()
        return c, torch.exp(-0.5 * (d / FADE_LENGTH) ** 2)

    def function(self, qj: Tensor) -> Tensor:
        """The form's value ``(M,)`` [rad] at the joint readings ``qj`` ``(M,)`` as fitted, without the fade."""
        dof = self.j + 1
        q = torch.zeros(len(qj), dof, dtype=qj.dtype, device=qj.device)
        q[:, self.j] = qj
        return self._terms(q, fade=False).sum(-1)

    def _coef(self) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def _basis(self, qj: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def _terms(self, q: Tensor, fade: bool = True) -> Tensor:
        """Each term's value ``(N, k)`` [rad]."""
        with torch.no_grad():
            return self._regressor(Context(q=q), fade) * self._coef()

    def _regressor(self, ctx: Context, fade: bool = True) -> Tensor:
        if not fade:
            return self._basis(ctx.q[:, self.j : self.j + 1])
        c, w = self._faded(ctx)
        X = self._basis(c)
        return X if w is None else X * w

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The form's basis at the (clamped) readings times the fade ``(N, k)``: the term the coefficients multiply."""
        return self._regressor(ctx)

    def forward(self, robot, ctx: Context) -> Tensor:
        return self._joint_delta(ctx, self.regressor(robot, ctx) @ self._coef())

    def _region_config(self) -> dict:
        return {} if self.region is None else {"region": [float(v) for v in self.region]}


class Compliance(Effect):
    """Joint compliance under gravity.

    A harmonic drive and its bearings twist elastically under load: the gravity torque
    of the links beyond joint j (from the masses and centres of mass of the robot
    description, plus an optional payload at the probe) deflects the joint by
    ``dq_j = k * tau_j(q)``, with ``k`` the joint's compliance [rad / (N m)]. The encoder
    sits on the motor side, so the reading misses this twist and the arm sags.

    Args:
        joint: 1-based joint.
        k: compliance [rad/(N m)].
        payload: mass at the probe [kg].
    """

    kind = "compliance"

    def __init__(self, joint: int, k: float = 0.0, payload: float = 0.0):
        super().__init__(joint)
        self.k = nn.Parameter(torch.tensor(float(k), dtype=torch.float64))
        self.payload = float(payload)

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The gravity torque at this joint ``(N,)`` [N m]: the term multiplied by ``k`` (held constant in
        derivatives: :meth:`~torchcal.robot.model.RobotModel.static_torques`). Rows that carry their payload
        (``ctx.payload``, the file's ``payload`` column) are loaded with it; else with ``payload``."""
        if ctx.payload is not None:
            return robot.static_torques(ctx.q, payload=ctx.payload, payload_com=ctx.payload_com)[:, self.j]
        return robot.static_torques(ctx.q, payload=self.payload)[:, self.j]

    def forward(self, robot, ctx: Context) -> Tensor:
        # the torque is a constant of the estimators' forward-mode Jacobians: torchcal._dual keeps the product in C++
        return self._joint_delta(ctx, _dual.mul(self.k, self.regressor(robot, ctx)))

    def param_units(self, robot) -> dict:
        # the joint error per unit of its gravity torque (a prismatic joint: per newton of its gravity force)
        return {"k": "rad/(N m)" if self.joint_unit(robot) == "rad" else "m/N"}

    def config(self) -> dict:
        return {"joint": self.joint, "payload": self.payload}

    def describe(self) -> dict:
        return {"k_rad_per_Nm": float(self.k.detach()), "payload_kg": self.payload}


#: the smallest share of a unit mass-moment column's probe displacement, beyond what the geometry already moves,
#: that makes a direction of a lumped compliance one of its modes (:func:`lumped_basis`): the gravity regressor of a
#: joint has exact null directions (moments along an axis that stays vertical, masses of links whose frames share an
#: origin) and directions only the geometry's columns reach; 1e-3 keeps what a tracker can tell from them and drops
#: what only round-off separates
LUMPED_TOL = 1e-3
#: the form a lumped compliance reports (``report.json`` ``params["form"]``)
LUMPED_FORM = "lumped (no link masses)"


class LumpedCompliance(Effect):
    """Joint compliance under gravity for a robot whose description has no link masses.

    A joint of stiffness ``K_j`` twists by ``dq_j = tau_j(q) / K_j``, and the gravity torque is linear in the links'
    unknown mass moments ``pi`` through the gravity regressor (:meth:`~torchcal.robot.model.RobotModel.
    gravity_regressor`): ``dq_j = Y_j(q) . beta`` with the lumped parameters ``beta = pi / K_j`` [kg rad/(N m) and
    kg m rad/(N m), four per link]. Most of them cannot be told apart from the joint's torque over a set of poses
    (nor from the geometry), so the effect is parameterised in the identifiable directions only:
    ``dq_j = Y_j(q) B m`` with ``B (4 dof, r)`` a fixed basis (:func:`lumped_basis`) and ``m (r,)`` the modes [rad]:
    with the basis scaled to unit RMS deflection on the poses it was made from, mode ``i`` is the RMS twist it
    gives there. Where masses are known :class:`Compliance` (one stiffness per joint) is the physical form.

    Args:
        joint: 1-based joint.
        basis: ``B (4 dof, r)``, columns per link ``k`` ordered ``(m_k, m_k c_k,x, m_k c_k,y, m_k c_k,z)``.
        mode: the modes ``(r,)`` [rad] (default zero).
    """

    kind = "compliance"

    def __init__(self, joint: int, basis, mode=None, load: bool = False, k: float = 0.0):
        super().__init__(joint)
        # with rows at several loads the joint's compliance shows in the payload's own torque, which the
        # description's kinematics give without link masses: dq_j += k * tau_payload,j (k [rad/(N m)])
        self.load = bool(load)
        self.k = nn.Parameter(torch.tensor(float(k), dtype=torch.float64)) if self.load else None
        B = torch.as_tensor(basis, dtype=torch.float64)
        if B.ndim != 2 or B.shape[0] % 4 or B.shape[0] // 4 < joint:
            from torchcal.errors import OptionError

            raise OptionError(
                f"a lumped compliance of joint {joint} needs a basis of shape (4 dof, r), got {tuple(B.shape)}"
            )
        self.register_buffer("basis", B.clone())
        m = torch.zeros(B.shape[1], dtype=torch.float64) if mode is None else torch.as_tensor(mode, dtype=torch.float64)
        self.mode = nn.Parameter(m.reshape(B.shape[1]).clone())

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The modes' deflection shapes ``(N, r)`` [rad per rad of mode]: ``Y_j(q) B`` (held constant in
        derivatives, as :class:`Compliance` holds its torque)."""
        Y = robot.static_gravity_regressor(ctx.q)[:, self.j]  # (N, 4 dof)
        if Y.shape[-1] != self.basis.shape[0]:
            from torchcal.errors import ShapeError

            raise ShapeError(
                f"lumped compliance of joint {self.joint}: its basis has {self.basis.shape[0]} rows, the robot's "
                f"gravity regressor {Y.shape[-1]} columns (4 per joint)"
            )
        return Y @ self.basis

    def forward(self, robot, ctx: Context) -> Tensor:
        # the shapes are constants of the estimators' forward-mode Jacobians: torchcal._dual keeps the product in C++
        dq = _dual.mul(self.regressor(robot, ctx), self.mode).sum(-1)
        if self.k is not None:
            dq = dq + _dual.mul(self.k, self.payload_regressor(robot, ctx))
        return self._joint_delta(ctx, dq)

    def payload_regressor(self, robot, ctx: Context) -> Tensor:
        """The payload's own torque at this joint ``(N,)`` [N m] (zero where the rows carry no payload)."""
        if ctx.payload is None:
            return torch.zeros_like(ctx.q[:, self.j])
        with torch.no_grad():
            return robot.payload_torques(ctx.q, ctx.payload, ctx.payload_com)[:, self.j]

    def deflection(self, robot, q: Tensor) -> Tensor:
        """The twist ``dq_j (N,)`` [rad] at the joints ``q`` ``(N, dof)``."""
        with torch.no_grad():
            return self.regressor(robot, Context(q=q)) @ self.mode

    def param_units(self, robot) -> dict:
        return {"mode": self.joint_unit(robot)}

    def config(self) -> dict:
        out = {"joint": self.joint, "basis": self.basis.tolist()}
        return {**out, "load": True} if self.load else out

    def describe(self) -> dict:
        load = {} if self.k is None else {"k_rad_per_Nm": float(self.k.detach())}
        return {
            **load,
            "form": LUMPED_FORM + (" + payload torque" if self.load else ""),
            "mode_rad": self.mode.detach().tolist(),
            # beta = B m: the mass moments over the stiffness [kg rad/(N m), kg m rad/(N m)], per link (m, mc_x..z)
            "moments_over_stiffness": (self.basis @ self.mode.detach()).reshape(-1, 4).tolist(),
        }


#: the form a compliance driven by the measured torques reports (``report.json`` ``params["form"]``)
TORQUE_FORM = "measured torques"


class TorqueCompliance(Effect):
    """Joint compliance read from the joint torques the controller measured: ``dq_j = -k tau_j`` [rad] with
    ``tau_j`` the row's ``tau<j>`` column [N m], the torque the drive applies to hold the arm (the weight's moment
    with the opposite sign, :mod:`torchcal.data.load`), and ``k > 0`` the joint's compliance [rad/(N m)].

    It needs neither link masses nor the payload: the torque the drive holds is the load, whatever carries it, so a
    campaign at one load identifies ``k`` from the arm's own weight and the model carries it to any other load.

    Args:
        joint: 1-based joint.
        k: compliance [rad/(N m)] (or [m/N] for a prismatic joint).
    """

    kind = "compliance"

    def __init__(self, joint: int, k: float = 0.0):
        super().__init__(joint)
        self.k = nn.Parameter(torch.tensor(float(k), dtype=torch.float64))

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The measured torque at this joint ``(N,)`` [N m]: the term multiplied by ``k``."""
        if ctx.tau is None:
            from torchcal.errors import OptionError

            raise OptionError(
                f"the compliance of joint {self.joint} is driven by the measured torques: the rows need the "
                f"columns tau1..tauN (N m)"
            )
        return ctx.tau[:, self.j]

    def forward(self, robot, ctx: Context) -> Tensor:
        # the drive's torque holds the weight's moment, so the twist runs against it: dq = -k tau with k > 0 the
        # same compliance as :class:`Compliance`'s (whose torque is the weight's moment)
        return self._joint_delta(ctx, _dual.mul(-self.k, self.regressor(robot, ctx)))

    def describe(self) -> dict:
        return {"k_rad_per_Nm": float(self.k.detach()), "form": TORQUE_FORM}


def geometric_span(robot, q: Tensor) -> Tensor:
    """An orthonormal basis ``(3N, u)`` of the probe displacements in the tracker frame that the robot's free
    calibration parameters (geometry, instrument, lever arm) make at the poses ``q``."""
    columns = [
        (g, int(i)) for g, grp in robot.groups().items() for i in torch.nonzero(grp.mask.flatten()).flatten().tolist()
    ]
    _, G = robot.tracker_jacobian(q, columns)
    G = G.reshape(-1, len(columns))
    G = G / G.norm(dim=0).clamp(min=1e-300)
    U, S, _ = torch.linalg.svd(G, full_matrices=False)
    return U[:, S > 1e-10 * S.max()]


def lumped_basis(robot, q: Tensor, joint: int, tol: float = LUMPED_TOL, span: Tensor | None = None) -> Tensor:
    """The identifiable directions of a lumped compliance of ``joint`` (1-based) on the poses ``q`` ``(N, dof)``:
    ``B (4 dof, r)``, ``r`` possibly 0.

    Method: the probe displacement (tracker frame) of each mass-moment column, ``J_j(q) Y_jc(q)``, stacked over the
    poses ``(3N, 4 dof)`` and each scaled to unit norm, is projected off the span of the geometry's, instrument's and
    lever arm's columns (``span``, default :func:`geometric_span`: what the joint refit absorbs anyway, the joint's
    own offset among it); the right singular vectors of the rest whose singular value exceeds ``tol`` are the
    directions (largest first). Each is scaled so that its deflection ``Y_j B_i`` has unit RMS over the poses, so a
    mode is the RMS twist [rad] it gives there.
    """
    j = joint - 1
    with torch.no_grad():
        Y = robot.gravity_regressor(q)[:, j]  # (N, 4 dof)
        _, Jq = robot.probe_jacobian(q)
        Jt = Jq[:, :, j] @ robot.T_tracker_base()[:3, :3].T  # (N, 3): the joint's column in the tracker frame
        M = (Jt[:, :, None] * Y[:, None, :]).reshape(-1, Y.shape[1])
        norm = M.norm(dim=0)
        live = norm > 1e-12 * float(norm.max()) if float(norm.max()) > 0 else norm > 0
        scale = torch.where(live, 1.0 / norm.clamp(min=1e-300), torch.zeros_like(norm))
        Mn = M * scale
        U = geometric_span(robot, q) if span is None else span
        for _ in range(2):  # projected twice for round-off
            Mn = Mn - U @ (U.T @ Mn)
        _, S, Vh = torch.linalg.svd(Mn, full_matrices=False)
        keep = S > tol
        B = scale[:, None] * Vh[keep].T  # (4 dof, r)
        rms = (Y @ B).square().mean(0).sqrt()
        return B / rms.clamp(min=1e-300)


class Backlash(Effect):
    """Gear backlash: a dead zone of width ``b`` between the gear flanks.

    The joint rests on one flank or the other, so its angle is offset by ``+b/2`` or
    ``-b/2`` depending on which way the load pushes it: the sign of the gravity torque
    for static poses, the direction of motion along a trajectory (``source="motion"``),
    or the motion where it is known and the torque otherwise (``source="auto"``).

    Args:
        joint: 1-based joint.
        b: backlash width [rad].
        source: "torque", "motion" or "auto".
    """

    kind = "backlash"
    SOURCES = ("torque", "motion", "auto")

    def __init__(self, joint: int, b: float = 0.0, source: str = "auto"):
        super().__init__(joint)
        if source not in self.SOURCES:
            from torchcal.errors import OptionError

            raise OptionError(f"backlash source '{source}' is not one of {self.SOURCES}")
        self.b = nn.Parameter(torch.tensor(float(b), dtype=torch.float64))
        self.source = source

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The flank sign ``(N,)`` in {-1, +1} (the term multiplied by ``b / 2``)."""
        if self.source != "torque" and ctx.direction is not None:
            s = ctx.direction[:, self.j]
        elif self.source == "motion":
            from torchcal.errors import EstimationError

            raise EstimationError("backlash with source='motion' needs a trajectory (a 't' column)")
        else:
            s = torch.sign(robot.static_torques(ctx.q)[:, self.j])
        return torch.where(s == 0, torch.ones_like(s), s)

    def forward(self, robot, ctx: Context) -> Tensor:
        # constants of the estimators' forward-mode Jacobians meet b through torchcal._dual (same values)
        half_b = _dual.mul_scalar(self.b, 0.5)
        return self._joint_delta(ctx, _dual.mul(half_b, self.regressor(robot, ctx)))

    def param_units(self, robot) -> dict:
        return {"b": self.joint_unit(robot)}

    def config(self) -> dict:
        return {"joint": self.joint, "source": self.source}

    def describe(self) -> dict:
        return {"b_rad": float(self.b.detach()), "source": self.source}


class Cyclic(RegionForm):
    """Cyclic transmission errors: ``dq_j = sum_k a_k sin(k q_j) + b_k cos(k q_j)``.

    Eccentric gears, encoders mounted off-centre and the flexspline's two-lobe wave
    make the true joint angle run ahead and behind the reading periodically, once or
    twice per revolution of the output; gear tooth and bearing patterns add higher orders
    (3rd to about 10th) at the output, and the gear ratio's multiples on the motor side
    are too fast to see at the flange. Any set of orders is allowed; the default (1, 2)
    is the classic pair, and order selection (:mod:`torchcal.diagnose.forms`) picks others.

    Args:
        joint: 1-based joint.
        harmonics: the orders k, distinct positive integers (default 1 and 2).
        a, b: sine and cosine amplitudes [rad], one per harmonic.
        region: the joint's fitted range ``(lo, hi)`` [rad]: beyond it the sum fades to zero, unless the range
            covers a whole period of the sum (``2 pi / gcd(orders)``), which determines it everywhere.
    """

    kind = "cyclic"

    def __init__(self, joint: int, harmonics: Sequence[int] = (1, 2), a=None, b=None, region=None):
        super().__init__(joint)
        orders = [int(k) for k in harmonics]
        if not orders or min(orders) < 1 or len(set(orders)) != len(orders):
            from torchcal.errors import OptionError

            raise OptionError(f"cyclic harmonics must be distinct positive integers, got {list(harmonics)}")
        h = torch.tensor(orders, dtype=torch.float64)
        self.register_buffer("harmonics", h)
        n = len(harmonics)

        def init(v):
            return torch.zeros(n, dtype=torch.float64) if v is None else torch.as_tensor(v, dtype=torch.float64)

        self.a = nn.Parameter(init(a).clone())
        self.b = nn.Parameter(init(b).clone())
        self.period = 2 * math.pi / math.gcd(*orders)
        self._init_region(region)

    def _unbounded(self) -> bool:
        return float(self.region[1] - self.region[0]) >= self.period

    def _basis(self, qj: Tensor) -> Tensor:
        arg = qj * self.harmonics
        return torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1)

    def _coef(self) -> Tensor:
        return torch.cat([self.a, self.b])

    def param_units(self, robot) -> dict:
        return {"a": self.joint_unit(robot), "b": self.joint_unit(robot)}

    def config(self) -> dict:
        return {"joint": self.joint, "harmonics": [int(k) for k in self.harmonics], **self._region_config()}

    def describe(self) -> dict:
        return {
            "harmonics": [int(k) for k in self.harmonics],
            "a_rad": self.a.detach().tolist(),
            "b_rad": self.b.detach().tolist(),
        }


class Transmission(RegionForm):
    """A joint-angle error polynomial in the joint's reading: ``dq_j = sum_{d=1..D} c_d q_j^d``.

    A transmission ratio that differs from the controller's value scales the angle
    (degree 1: ``dq_j = c_1 q_j``, ``c_1`` the relative ratio error); a slightly
    non-linear encoder or a cam-like drive adds degrees 2 and 3. The constant term is
    the joint offset, which the geometry already carries, so degrees start at 1. On a
    prismatic joint the reading is a length and degree 1 is its scale error (``c`` in m/m).

    Args:
        joint: 1-based joint.
        degree: highest degree D (>= 1).
        c: coefficients ``(D,)`` [rad / rad^d].
        region: the joint's fitted range ``(lo, hi)`` [rad]: beyond it the polynomial fades to zero.
    """

    kind = "transmission"

    def __init__(self, joint: int, degree: int = 1, c=None, region=None):
        super().__init__(joint)
        if int(degree) < 1:
            from torchcal.errors import OptionError

            raise OptionError(f"transmission degree must be >= 1, got {degree}")
        self.degree = int(degree)
        c0 = torch.zeros(self.degree, dtype=torch.float64) if c is None else torch.as_tensor(c, dtype=torch.float64)
        self.c = nn.Parameter(c0.reshape(self.degree).clone())
        self._init_region(region)

    def _basis(self, qj: Tensor) -> Tensor:
        return qj ** torch.arange(1, self.degree + 1, dtype=qj.dtype, device=qj.device)

    def _coef(self) -> Tensor:
        return self.c

    def param_units(self, robot) -> dict:
        u = self.joint_unit(robot)
        return {"c": [f"{u}/{u}" if d == 1 else f"{u}/{u}^{d}" for d in range(1, self.degree + 1)]}

    def config(self) -> dict:
        return {"joint": self.joint, "degree": self.degree, **self._region_config()}

    def describe(self) -> dict:
        return {"degree": self.degree, "c": self.c.detach().tolist()}


class Coupling(Effect):
    """One joint's reading error proportional to another joint's reading: ``dq_j = c q_k``.

    A cable or belt routed through joint ``k`` to joint ``j``'s drive, or a wrist differential whose ratio the
    controller does not compensate exactly, turns joint ``j`` when joint ``k`` moves while ``j``'s encoder (on the
    motor) reads nothing. A physical law (linear in the other joint's reading), so it needs no fade beyond the data.
    A coupling the description declares in its ``readings:`` block is a ratio of the readings map and calibrated with
    the geometry; this effect is the one the description does not declare.

    Args:
        joint: 1-based joint whose reading errs.
        source: 1-based joint whose reading drives the error (``!= joint``; the same joint is a
            :class:`Transmission` of degree 1).
        c: the coupling ratio [rad/rad].
    """

    kind = "coupling"

    def __init__(self, joint: int, source: int, c: float = 0.0):
        super().__init__(joint)
        if int(source) == int(joint):
            from torchcal.errors import OptionError

            raise OptionError(f"a coupling joins two joints, got joint {joint} from itself (that is a transmission)")
        self.source = int(source)
        self.c = nn.Parameter(torch.tensor(float(c), dtype=torch.float64))

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The source joint's reading ``(N,)`` [rad]: the term multiplied by ``c``."""
        return ctx.q[:, self.source - 1]

    def forward(self, robot, ctx: Context) -> Tensor:
        return self._joint_delta(ctx, _dual.mul(self.c, self.regressor(robot, ctx)))

    def param_units(self, robot) -> dict:
        source = "m" if robot.joint_types[self.source - 1] == "prismatic" else "rad"
        return {"c": f"{self.joint_unit(robot)}/{source}"}

    def config(self) -> dict:
        return {"joint": self.joint, "source": self.source}

    def describe(self) -> dict:
        return {"source": self.source, "c": float(self.c.detach())}

    def label(self) -> str:
        return f"coupling(joint {self.joint} <- {self.source})"


# A joint-angle function fitted on poses whose joint covers a narrow range can be a sum of large terms that cancel
# there (harmonics of 10-250 rad summing to 1e-4 rad): it fits the poses and explodes just beyond them. The bound is
# loose for a well-determined function: its terms add up (ratio near 1; a few where two harmonics partly cancel).
# A smooth function that is small on the poses and large just beyond them has such cancelling terms, so the ratio
# is the test (a search over random cubics and harmonic pairs found none that grew threefold within a tenth of the
# range beyond the poses without a ratio above this bound).
CANCELLATION_RATIO = 20.0  # largest allowed sum of |term| over |sum of terms|, both at their peak on the poses


def joint_range(robot, joint: int) -> tuple[float, float]:
    """The range a joint can reach [rad or m]: its limits, where finite, else one turn either side of zero."""
    lo, hi = (float(v) for v in robot.limits[joint - 1]) if robot is not None else (-math.inf, math.inf)
    turn = 2 * math.pi
    return (lo if math.isfinite(lo) else -turn), (hi if math.isfinite(hi) else turn)


def joint_function_size(effect: Effect, robot, q: Tensor, reach: tuple[float, float]) -> float:
    """The size [rad] of a joint-angle effect: half the peak-to-peak of its function over the joint's whole range
    ``reach`` for an open form (:class:`Cyclic`, :class:`Transmission`: the constant part is the joint offset the
    geometry carries), the largest ``|dq|`` on the poses ``q`` for a physical one (compliance, backlash), whose law
    says how it continues."""
    with torch.no_grad():
        if isinstance(effect, RegionForm):
            lo, hi = reach
            grid = torch.linspace(lo, hi, 4001, dtype=torch.float64, device=q.device)
            f = effect.function(grid)
            return float(f.max() - f.min()) / 2
        if isinstance(effect, Backlash):
            return abs(float(effect.b)) / 2
        if isinstance(effect, Compliance):
            return abs(float(effect.k)) * float(effect.regressor(robot, Context(q=q)).abs().max())
        if isinstance(effect, LumpedCompliance):
            return float(effect.deflection(robot, q).abs().max())
        if isinstance(effect, TorqueCompliance):
            return 0.0  # the rows' torques are not known here: its size is judged by its fit
        if isinstance(effect, Coupling):  # linear in the source's reading: half its swing over the source's range
            lo, hi = joint_range(robot, effect.source)
            return abs(float(effect.c)) * (hi - lo) / 2
    return 0.0


def joint_function_check(effect: Effect, q: Tensor, robot=None, max_size: float | None = MAX_JOINT_ERROR) -> str | None:
    """Whether a fitted joint-angle function is determined by the poses and of a physical size.

    Args:
        effect: the fitted effect; kinds that do not act on one joint's angle pass (``None``).
        q: the joints of the poses it was fitted on ``(N, dof)`` [rad].
        robot: the robot (its joint limits are the range an open form is judged on; a compliance's torques); None:
            the size is not checked.
        max_size: the largest size allowed (:func:`joint_function_size`) [rad]; None: no bound.

    Returns:
        ``None`` when the function is well determined and not larger than ``max_size``, else the reason: its terms
        cancel on the poses (the sum of the terms' peaks exceeds ``CANCELLATION_RATIO`` times the function's peak),
        so that the poses do not determine them and the function explodes beyond them; or it exceeds the bound
        somewhere on its joint's range.
    """
    if not isinstance(
        effect, (Cyclic, Transmission, Compliance, LumpedCompliance, TorqueCompliance, Backlash, Coupling)
    ):
        return None
    qj = q[:, effect.j]
    seen = f"{float(qj.min()):.3f} to {float(qj.max()):.3f}"
    if isinstance(effect, RegionForm):
        terms = effect._terms(q, fade=False)
        peak = float(terms.sum(-1).abs().max())
        peak_terms = float(terms.abs().max(0).values.sum())
        if peak_terms > CANCELLATION_RATIO * max(peak, 1e-15):
            unit = "m" if robot is not None and robot.joint_types[effect.joint - 1] == "prismatic" else "rad"
            return (
                f"its terms cancel on the fitting poses (sum of |terms| {peak_terms:.3g} {unit} against a function of "
                f"{peak:.3g} {unit}): the range of joint {effect.joint} seen ({seen} {unit}) does not determine them, "
                "and beyond it the function would explode"
            )
    stiffness = _load_stiffness_check(effect)
    if stiffness is not None:
        return stiffness
    if robot is None or max_size is None:
        return None
    if isinstance(effect, Coupling):
        return _coupling_check(effect, robot)
    reach = joint_range(robot, effect.joint)
    size = joint_function_size(effect, robot, q, reach)
    bound = max_size * joint_bound_scale(robot, q, effect.joint)
    if size <= bound:
        return None
    # a prismatic joint's error is a length: the same bound read in metres (the probe moves 1 m per m)
    unit, small = ("m", "mm") if robot.joint_types[effect.joint - 1] == "prismatic" else ("rad", "mrad")
    if isinstance(effect, RegionForm):
        where = f"over joint {effect.joint}'s range {reach[0]:.3f} to {reach[1]:.3f} {unit} (fitted on {seen})"
    else:
        where = "on the fitting poses"
    scaled = "" if bound == max_size else f" ({max_size * 1e3:.3g} mrad at a 1 m lever arm, scaled to this joint's)"
    return (
        f"its size {size * 1e3:.3g} {small} {where} exceeds the physical bound of {bound * 1e3:.3g} {small}"
        f"{scaled} (max_joint_error): a joint error that large is not a transmission error, and it is only the sum "
        "of terms the joint range does not determine"
    )


#: the largest ratio [rad/rad] an undeclared coupling may take: a mechanism that joins two joints (a belt through a
#: hollow wrist, a differential) is declared in the readings map with its ratio, and what the calibration finds
#: beyond it is that ratio's error or a cable's pull, tenths of a percent; 1 % is a readings map declared wrong, which
#: the description should say. A coupling is a linear law with one parameter (no terms that cancel), so its size over
#: the source joint's range (several turns of a wrist multiply a 0.2 % error into tens of mrad) is not bounded by
#: ``max_joint_error``, which bounds the open forms' transmission errors.
MAX_COUPLING = 1e-2


def _coupling_check(effect: Coupling, robot) -> str | None:
    """A coupling's ratio is within :data:`MAX_COUPLING` (its size over the source's range is said beside it)."""
    c = float(effect.c.detach())
    if abs(c) <= MAX_COUPLING:
        return None
    lo, hi = joint_range(robot, effect.source)
    size = abs(c) * (hi - lo) / 2
    return (
        f"its ratio {c:.3g} rad/rad exceeds the physical bound of {MAX_COUPLING:g} (it would turn joint "
        f"{effect.joint} by {size * 1e3:.3g} mrad over joint {effect.source}'s range {lo:.3f} to {hi:.3f}, which "
        "drives it): a coupling that large is a readings map declared wrong, or the fit is confounded with another "
        "effect"
    )


#: the largest compliance [rad/(N m)] a load-driven form may take: 1e-4 is a twist of 0.1 rad under 1 kN m, ten
#: times softer than the softest harmonic drive of a collaborative arm (about 1e-5); the load forms carry their
#: compliance to loads never measured, so a value beyond it is a confounded fit, not a joint
MAX_COMPLIANCE = 1e-4


def _load_stiffness_check(effect: Effect) -> str | None:
    """A load-driven compliance (measured torques, the lumped form's payload term) is positive and below
    :data:`MAX_COMPLIANCE`; else the reason."""
    if isinstance(effect, TorqueCompliance):
        k = float(effect.k.detach())
    elif isinstance(effect, LumpedCompliance) and effect.k is not None:
        k = float(effect.k.detach())
    else:
        return None
    if 0.0 < k <= MAX_COMPLIANCE:
        return None
    return (
        f"its compliance k = {k:.3g} rad/(N m) is not physical (a joint twists with its load: 0 < k <= "
        f"{MAX_COMPLIANCE:g} rad/(N m)); the fit is confounded with another effect"
    )


#: the lever arm [m] at which a joint-angle error is held to ``max_joint_error`` itself, and the most the bound is
#: widened for a joint with a shorter lever (:func:`joint_bound_scale`)
BOUND_LEVER = 1.0
MAX_BOUND_SCALE = 10.0


def joint_bound_scale(robot, q: Tensor, joint: int) -> float:
    """How much wider than ``max_joint_error`` a joint's error may be: ``BOUND_LEVER / L`` with ``L`` the joint's
    largest lever arm to the probe on the poses ``q`` (``|dp/dq_j|``), between 1 and ``MAX_BOUND_SCALE``.

    A wrist joint close to the probe moves it by millimetres per radian: the error that shows there as a few tens
    of micrometres is several mrad of angle, and only the lever makes it so. The bound is then the same
    displacement at the probe as ``max_joint_error`` at a 1 m lever, up to ten times the angle. A prismatic joint's
    lever is 1 (m per m): its bound is ``max_joint_error`` [m] itself.
    """
    j = joint - 1
    with torch.no_grad():
        h = 1e-6
        dq = torch.zeros_like(q)
        dq[:, j] = h
        lever = float(((robot.probe_in_base(q + dq) - robot.probe_in_base(q - dq)).norm(dim=-1) / (2 * h)).max())
    return min(max(BOUND_LEVER / max(lever, 1e-12), 1.0), MAX_BOUND_SCALE)
