"""The differentiable robot model: geometry, instrument pose and lever arm as ``nn.Parameter``s.

Every serial arm, whether described by a DH table or a URDF, is reduced to one form::

    T_base_flange(q) = O_1 R_1(q_1) O_2 R_2(q_2) ... O_n R_n(q_n) O_tip

where ``O_i`` is the constant transform in front of joint ``i`` (it depends on the
calibration parameters) and ``R_i`` the joint's motion along its unit axis: a rotation by ``q_i`` [rad]
for a revolute joint, a translation by ``q_i`` [m] for a prismatic one (``prismatic``, a boolean per
joint on the geometry). The parameterisation of the ``O_i`` is what differs:

* :class:`DHGeometry`: per joint ``[a, alpha, d, theta, beta]`` (Hayati's ``beta``, a
  rotation about y, for nearly parallel consecutive axes, which DH cannot represent);
* :class:`URDFGeometry`: a small 6-DoF error ``[tx, ty, tz, rx, ry, rz]`` on each joint origin.

pytorch-kinematics bakes its offsets and cuts their gradients, so torchcal computes
FK itself in float64 and keeps a pytorch-kinematics chain built from the same
float64 matrices for structure, limits, Jacobians and IK (:attr:`RobotModel.chain`).

Measured quantity: the probe position in the tracker frame,
``p_tracker = T_tracker_base @ T_base_flange(q) @ t_flange_probe``.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from torchcal import _dual
from torchcal._torch import plain, same_version, version_key
from torchcal.errors import ShapeError
from torchcal.robot import transforms as tf
from torchcal.robot.readings import Readings

Tensor = torch.Tensor
GRAVITY = 9.80665  # m/s^2, standard gravity, along -z of the robot base frame
_TORQUE_CACHE = 8  # static torques a robot keeps: a fit's damping ladder tries five geometries before its next
# Jacobian (one by one where its residuals cannot be batched; a batched call's torques are not kept)


class DHConvention(enum.Enum):
    """Denavit-Hartenberg conventions.

    STANDARD: link i = Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) [Ry(beta_i)]
    MODIFIED (Craig): link i = Rx(alpha_{i-1}) [Ry(beta_{i-1})] Tx(a_{i-1}) Rz(q_i + theta_i) Tz(d_i),
    where the table row i holds alpha_{i-1}, a_{i-1}, theta_i, d_i.
    """

    STANDARD = "standard"
    MODIFIED = "modified"


def _check_dtype(name: str, t: Tensor, ref: Tensor) -> None:
    if t.dtype != ref.dtype or t.device != ref.device:
        raise ShapeError(
            f"{name} has dtype {t.dtype} on {t.device}, but the model is {ref.dtype} on {ref.device}; "
            "torchcal computes in float64 and never converts silently"
        )


class _Group(nn.Module):
    """A parameter group: zero-initialised corrections ``delta`` and a boolean ``mask`` of free elements.

    Fixed elements keep their current value (zero unless set): ``mask`` tells the
    estimators what they may vary, it does not zero anything in the forward pass.
    """

    names: list[str]

    def _init_group(self, shape: Sequence[int], names: list[str], mask: Tensor, dtype, device) -> None:
        self.delta = nn.Parameter(torch.zeros(*shape, dtype=dtype, device=device))
        self.register_buffer("mask", mask.to(device=device, dtype=torch.bool).reshape(*shape).clone())
        self.names = names

    def reset(self) -> None:
        with torch.no_grad():
            self.delta.zero_()

    def _init_joint_types(self, prismatic, dof: int, device) -> None:
        """The per-joint boolean ``prismatic`` (default all revolute): a buffer for tensor code, left out of the
        state dict (the robot description says it, and runs written before prismatic joints load unchanged), and
        the same flags as a tuple for the chain's Python-level branches."""
        flags = [False] * dof if prismatic is None else [bool(f) for f in prismatic]
        if len(flags) != dof:
            raise ShapeError(f"prismatic must have {dof} flags, got {len(flags)}")
        self.register_buffer("prismatic", torch.tensor(flags, dtype=torch.bool, device=device), persistent=False)
        self.joint_types = tuple("prismatic" if f else "revolute" for f in flags)


class DHGeometry(_Group):
    """Per-joint DH errors ``[a, alpha, d, theta, beta]`` on nominal buffers.

    Args:
        a, alpha, d, theta: nominal values, shape (dof,), metres and radians.
        beta: nominal tilt about y between nearly parallel axes (dof,) [rad], default zero (a calibrated table
            written back, :func:`torchcal.robot.export_formats.dh_yaml`).
        convention: :class:`DHConvention`.
        prismatic: per joint, whether it is prismatic (its reading [m] adds to ``d``, ``theta`` is fixed);
            default all revolute (the reading adds to ``theta``).
    """

    COLUMNS = ("a", "alpha", "d", "theta", "beta")

    def __init__(
        self,
        *,
        a,
        alpha,
        d,
        theta,
        convention: DHConvention,
        prismatic=None,
        beta=None,
        dtype=torch.float64,
        device="cpu",
    ):
        super().__init__()
        if dtype != torch.float64:
            raise ShapeError(f"the calibration path is float64, got dtype {dtype}")
        nominal = torch.stack([torch.as_tensor(v, dtype=dtype) for v in (a, alpha, d, theta)], dim=-1)
        dof = nominal.shape[0]
        b = torch.zeros(dof, dtype=dtype) if beta is None else torch.as_tensor(beta, dtype=dtype).reshape(dof)
        nominal = torch.cat([nominal, b.unsqueeze(-1)], dim=-1)
        self.register_buffer("nominal", nominal.to(device))
        self.convention = DHConvention(convention)
        # beta only where consecutive axes are (nearly) parallel: there DH's d is ill-defined
        # and the tilt about y is not representable by alpha; elsewhere beta is redundant.
        parallel = torch.sin(nominal[:, 1]).abs() < 0.1
        mask = torch.ones(dof, 5, dtype=torch.bool)
        mask[:, 4] = parallel
        if self.convention is DHConvention.MODIFIED:
            mask[0, 4] = False  # alpha_0 relates the base frame, not two joint axes
        else:
            mask[-1, 4] = False  # the flange frame has no next joint axis to be parallel to
        names = [f"{c}{i + 1}" for i in range(dof) for c in self.COLUMNS]
        self._init_group((dof, 5), names, mask, dtype, device)
        # the joint moves along (prismatic) or about (revolute) z of the frame in front of it: Tz(q) commutes with
        # Rz(theta) Tz(d), so the chain's form O_i R_i(q_i) holds for both
        self.register_buffer("axes", torch.tensor([[0.0, 0.0, 1.0]] * dof, dtype=dtype, device=device))
        self._init_joint_types(prismatic, dof, device)

    @property
    def dof(self) -> int:
        return self.nominal.shape[0]

    @property
    def values(self) -> Tensor:
        """Current DH table ``(dof, 5)``: nominal + correction."""
        return _dual.add(self.nominal, self.delta)  # not +: under jacfwd that imports torch._dynamo

    def origins(self, delta: Tensor | None = None) -> Tensor:
        """Constant transforms ``(dof + 1, 4, 4)``: ``O_1 .. O_n`` then ``O_tip``.

        Args:
            delta: corrections ``(..., dof, 5)`` to use instead of the module's own (batched for derivatives);
                the result is then ``(..., dof + 1, 4, 4)``.
        """
        v = self.values if delta is None else self.nominal + delta
        a, alpha, d, theta, beta = v.unbind(-1)
        zero = torch.zeros_like(a)
        Tz_d = tf.translation(torch.stack([zero, zero, d], -1))
        Tx_a = tf.translation(torch.stack([a, zero, zero], -1))
        Rz_th = tf.homogeneous(tf.rot_z(theta), torch.zeros_like(v[..., :3]))
        Rx_al = tf.homogeneous(tf.rot_x(alpha), torch.zeros_like(v[..., :3]))
        Ry_be = tf.homogeneous(tf.rot_y(beta), torch.zeros_like(v[..., :3]))
        eye = torch.eye(4, dtype=v.dtype, device=v.device).expand(*v.shape[:-2], 1, 4, 4)
        if self.convention is DHConvention.STANDARD:
            M = Rz_th @ Tz_d @ Tx_a @ Rx_al @ Ry_be  # link i after its joint rotation
            return torch.cat([eye, M], dim=-3)
        M = Rx_al @ Ry_be @ Tx_a @ Rz_th @ Tz_d  # link i before its joint rotation
        return torch.cat([M, eye], dim=-3)

    def set_values(self, table: Tensor) -> None:
        """Set the corrections so that :attr:`values` equals ``table (dof, 5)``."""
        with torch.no_grad():
            self.delta.copy_(table - self.nominal)


class URDFGeometry(_Group):
    """Small 6-DoF errors ``[tx, ty, tz, rx, ry, rz]`` on each joint origin: ``O_i = O_i,nom @ [exp(r) | t]``.

    Args:
        origins: nominal ``(dof + 1, 4, 4)`` (fixed joints folded in), the last one ``O_tip``.
        axes: unit joint axes ``(dof, 3)`` in the joint frames.
        joint_names: the URDF joint names, used to name the parameters.
        prismatic: per joint, whether it is prismatic; default all revolute.
    """

    COLUMNS = ("tx", "ty", "tz", "rx", "ry", "rz")

    def __init__(
        self,
        *,
        origins: Tensor,
        axes: Tensor,
        joint_names: Sequence[str],
        prismatic=None,
        dtype=torch.float64,
        device="cpu",
    ):
        super().__init__()
        if dtype != torch.float64:
            raise ShapeError(f"the calibration path is float64, got dtype {dtype}")
        dof = axes.shape[0]
        self.register_buffer("nominal", origins.to(dtype=dtype, device=device).clone())
        self.register_buffer("axes", axes.to(dtype=dtype, device=device).clone())
        names = [f"{j}.{c}" for j in joint_names for c in self.COLUMNS]
        self._init_group((dof, 6), names, torch.ones(dof, 6, dtype=torch.bool), dtype, device)
        self._init_joint_types(prismatic, dof, device)

    @property
    def dof(self) -> int:
        return self.axes.shape[0]

    def origins(self, delta: Tensor | None = None) -> Tensor:
        """Constant transforms ``(dof + 1, 4, 4)``; ``delta (..., dof, 6)`` replaces the module's corrections
        (batched for derivatives: the result is then ``(..., dof + 1, 4, 4)``)."""
        err = tf.se3_from_vector(self.delta if delta is None else delta)
        M = self.nominal[:-1] @ err
        return torch.cat([M, self.nominal[-1:].expand(*M.shape[:-3], 1, 4, 4)], dim=-3)


class Instrument(_Group):
    """The instrument pose ``T_tracker_base = T_nominal @ [exp(r) | t]``, correction ``[tx, ty, tz, rx, ry, rz]``.

    The correction acts in robot-base coordinates, so that its components line up with the
    robot's own parameters (``tz`` with ``d1``, ``rz`` with ``theta1``) whatever the tracker's
    orientation.

    With ``stations`` (two or more names: the placements of the instrument, one pose each) the group holds one pose
    per station: ``nominal (S, 4, 4)``, ``delta (S, 6)``, element names ``instrument[NAME].tx``; without them it is the
    one pose of a single placement, ``(4, 4)`` and ``(6,)`` as ever.
    """

    COLUMNS = ("tx", "ty", "tz", "rx", "ry", "rz")

    def __init__(
        self, T_nominal: Tensor | None = None, dtype=torch.float64, device="cpu", stations: Sequence[str] | None = None
    ):
        super().__init__()
        self.stations = tuple(str(s) for s in stations) if stations is not None and len(stations) > 1 else ()
        T = torch.eye(4, dtype=dtype) if T_nominal is None else torch.as_tensor(T_nominal, dtype=dtype)
        if self.stations:
            T = T.expand(len(self.stations), 4, 4) if T.dim() == 2 else T
            if tuple(T.shape) != (len(self.stations), 4, 4):
                raise ShapeError(f"T_nominal must be (4, 4) or ({len(self.stations)}, 4, 4), got {tuple(T.shape)}")
        self.register_buffer("nominal", T.to(device).clone())
        if self.stations:
            names = [f"instrument[{s}].{c}" for s in self.stations for c in self.COLUMNS]
            shape = (len(self.stations), 6)
        else:
            names, shape = [f"instrument.{c}" for c in self.COLUMNS], (6,)
        self._init_group(shape, names, torch.ones(shape, dtype=torch.bool), dtype, device)

    def matrix(self, delta: Tensor | None = None) -> Tensor:
        """``T_tracker_base (4, 4)`` (``(S, 4, 4)`` with stations); ``delta (..., 6)`` (``(..., S, 6)``) replaces the
        module's correction (then ``(..., [S,] 4, 4)``)."""
        return self.nominal @ tf.se3_from_vector(self.delta if delta is None else delta)

    def rows(self, station: Tensor | None, delta: Tensor | None = None) -> Tensor:
        """The pose that measured each row: ``(4, 4)`` for a single station (every row), else ``(N, 4, 4)`` picked by
        ``station (N,)`` int64 (None: the first station's ``(4, 4)``)."""
        M = self.matrix(delta)
        if not self.stations:
            return M
        return M[..., 0, :, :] if station is None else M[..., station, :, :]

    def point_jacobian(self, points: Tensor, columns: Sequence[int], delta: Tensor | None = None) -> Tensor:
        """``d (T p) / d delta`` of base-frame points ``p (N, 3)`` [m] for the flat ``columns`` of the correction:
        ``(N, 3, len(columns))`` [m per m or rad], at ``delta`` (default the module's own).

        ``T p`` is linear in ``T``, so this is ``dT/d delta`` (a ``3 x 4`` per column, no pose in it) applied to
        each point: a product per pose instead of the transform differentiated pose by pose.
        """
        d = (self.delta if delta is None else delta).detach()
        B = _small_jacobian(lambda x: self.matrix(x)[..., :3, :], d, columns).reshape(3, 4, -1)
        return torch.einsum("abk,nb->nak", B[:, :3], points) + B[:, 3]

    def rotation_turns(self, columns: Sequence[int], delta: Tensor | None = None) -> Tensor:
        """``N_k = dR/dd_k R^T`` of the pose's rotation ``R`` for the flat ``columns`` of the correction ``(k, 3,
        3)``, or ``(S, k, 3, 3)`` per station (zero for another station's columns), at ``delta``: each turns what
        the pose maps, ``d(R M)/dd_k = N_k R M`` (skew-symmetric: R stays a rotation; no pose in it)."""
        d = (self.delta if delta is None else delta).detach()
        R = self.matrix(d)[..., :3, :3].detach()
        B = _small_jacobian(lambda x: self.matrix(x)[..., :3, :3], d, columns)
        B = B.reshape(*R.shape[:-2], 3, 3, len(columns))
        return torch.einsum("...abk,...cb->...kac", B, R)

    def rows_point_jacobian(
        self, points: Tensor, station: Tensor | None, columns: Sequence[int], delta: Tensor | None = None
    ) -> Tensor:
        """:meth:`point_jacobian` for rows measured from several stations: ``(N, 3, len(columns))``, zero where a
        column belongs to another station than the row's (``station (N,)``; a single station: the plain one)."""
        if not self.stations:
            return self.point_jacobian(points, columns, delta)
        d = (self.delta if delta is None else delta).detach()
        S = len(self.stations)
        B = _small_jacobian(lambda x: self.matrix(x)[..., :3, :], d, columns).reshape(S, 3, 4, -1)
        owner = torch.tensor([c // 6 for c in columns], dtype=torch.long, device=points.device)
        Br = B[station]  # (N, 3, 4, k): the row's own station's derivative, zero for the other stations' columns
        J = torch.einsum("nabk,nb->nak", Br[:, :, :3], points) + Br[:, :, 3]
        return J * (station[:, None] == owner[None, :]).to(J.dtype)[:, None, :]

    def set_matrix(self, T: Tensor, station: int | None = None) -> None:
        """Make ``T`` the new nominal and zero the correction (used after a closed-form initial fit); with stations,
        of ``station`` (None: every station)."""
        with torch.no_grad():
            if self.stations and station is not None:
                self.nominal[station].copy_(T)
                self.delta[station].zero_()
            else:
                self.nominal.copy_(T)
                self.delta.zero_()


class Tool(_Group):
    """The lever arm ``t_flange_probe = nominal + delta`` (probe position in the flange frame, m).

    With ``probes`` (two or more names: reflectors on one tool) one lever arm per probe, ``nominal, delta (P, 3)``,
    element names ``tool[NAME].x``.
    """

    COLUMNS = ("x", "y", "z")

    def __init__(
        self, t_nominal: Tensor | None = None, dtype=torch.float64, device="cpu", probes: Sequence[str] | None = None
    ):
        super().__init__()
        self.probes = tuple(str(p) for p in probes) if probes is not None and len(probes) > 1 else ()
        t = torch.zeros(3, dtype=dtype) if t_nominal is None else torch.as_tensor(t_nominal, dtype=dtype)
        if self.probes:
            t = t.expand(len(self.probes), 3) if t.dim() == 1 else t
            if tuple(t.shape) != (len(self.probes), 3):
                raise ShapeError(f"t_nominal must be (3,) or ({len(self.probes)}, 3), got {tuple(t.shape)}")
            names = [f"tool[{p}].{c}" for p in self.probes for c in self.COLUMNS]
            shape = (len(self.probes), 3)
        else:
            names, shape = [f"tool.{c}" for c in self.COLUMNS], (3,)
        self.register_buffer("nominal", t.to(device).clone())
        self._init_group(shape, names, torch.ones(shape, dtype=torch.bool), dtype, device)

    def vector(self, delta: Tensor | None = None) -> Tensor:
        """``t_flange_probe (3,)`` [m] (``(P, 3)`` with probes); ``delta (..., 3)`` replaces the module's correction
        (then ``(..., 3)``)."""
        return self.nominal + (self.delta if delta is None else delta)

    def rows(self, probe: Tensor | None, delta: Tensor | None = None) -> Tensor:
        """The lever arm of each row: ``(3,)`` for a single probe, else ``(N, 3)`` picked by ``probe (N,)`` (None: the
        first probe's)."""
        t = self.vector(delta)
        if not self.probes:
            return t
        return t[..., 0, :] if probe is None else t[..., probe, :]


class ToolRotation(_Group):
    """The probe frame's orientation in the flange frame ``R_flange_probe = R_nominal @ exp(delta)``, correction
    ``[rx, ry, rz]`` [rad] (part of the tool: element names ``tool.rx``, ``tool.ry``, ``tool.rz``).

    Only a robot measured with a 6-D probe (a T-Mac: position and orientation) has it
    (:meth:`RobotModel.enable_orientation`): a reflector has no orientation to fit.
    """

    COLUMNS = ("rx", "ry", "rz")

    def __init__(self, R_nominal: Tensor | None = None, dtype=torch.float64, device="cpu"):
        super().__init__()
        R = torch.eye(3, dtype=dtype) if R_nominal is None else torch.as_tensor(R_nominal, dtype=dtype)
        self.register_buffer("nominal", R.to(device).clone())
        self._init_group((3,), [f"tool.{c}" for c in self.COLUMNS], torch.ones(3, dtype=torch.bool), dtype, device)

    def matrix(self, delta: Tensor | None = None) -> Tensor:
        """``R_flange_probe (3, 3)``; ``delta (..., 3)`` replaces the module's correction (then ``(..., 3, 3)``)."""
        return self.nominal @ tf.so3_exp(self.delta if delta is None else delta)

    def set_matrix(self, R: Tensor) -> None:
        """Make ``R`` the new nominal and zero the correction (after the closed-form start)."""
        with torch.no_grad():
            self.nominal.copy_(R)
            self.delta.zero_()


@dataclass(frozen=True)
class ParameterInfo:
    """One element of a calibration parameter group, for reports and estimators."""

    group: str  # "geometry" | "instrument" | "tool" | "tool_rotation" | "readings"
    name: str  # e.g. "d1", "shoulder_pan_joint.tz", "instrument.rz", "instrument[B].rz", "tool.x", "tool[2].x"
    index: tuple[int, ...]  # index into the group's delta tensor
    unit: str  # "m", "rad" or "1" (a ratio of the readings map)


class RobotModel(nn.Module):
    """A serial robot arm with calibration parameters, float64, batched over poses.

    Calling the module gives ``T_base_flange (..., 4, 4)`` for joints ``q (..., dof)``.

    ``q`` are always the controller's readings (``dof`` of them, what files, effects and ``compensate`` see); the
    chain turns by ``n_joints`` model joints ``A q + b`` (:class:`~torchcal.robot.readings.Readings`: a
    parallelogram, reversed directions, URDF mimic joints). Without a readings map the two are the same and every
    entry point skips the map. ``limits`` are per reading, ``joint_limits`` per model joint.
    """

    def __init__(
        self,
        *,
        name: str,
        geometry: DHGeometry | URDFGeometry,
        limits: Tensor,
        joint_names: Sequence[str],
        link_names: Sequence[str],
        masses: Tensor | None = None,
        coms: Tensor | None = None,
        source: str | None = None,
        kind: str = "dh",
        base_link: str = "base",
        tip_link: str = "flange",
        readings: Readings | None = None,
        reading_limits: Tensor | None = None,
        reading_names: Sequence[str] | None = None,
        dtype=torch.float64,
        device="cpu",
    ):
        super().__init__()
        if dtype != torch.float64:
            raise ShapeError(f"the calibration path is float64, got dtype {dtype}")
        self.name = name
        self.kind = kind
        self.source = source
        self.geometry = geometry
        self.instrument = Instrument(dtype=dtype, device=device)
        self.tool = Tool(dtype=dtype, device=device)
        self.tool_rotation: ToolRotation | None = None  # enable_orientation: a 6-D probe's frame in the flange's
        dof = geometry.dof
        self.readings = Readings.identity(dof, dtype=dtype, device=device) if readings is None else readings
        if self.readings.n_joints != dof:
            raise ShapeError(f"the readings map has {self.readings.n_joints} rows for a chain of {dof} joints")
        self.joint_names = list(joint_names)
        self.link_names = list(link_names)  # dof + 2: base, the link moved by each joint, tip
        self.base_link = base_link
        self.tip_link = tip_link
        joint_limits = torch.as_tensor(limits, dtype=dtype).reshape(dof, 2).to(device).clone()
        # from the description, which every reload reads again: not in the state (old run directories load as before)
        self.register_buffer("joint_limits", joint_limits, persistent=False)
        n_read = self.readings.n_readings
        if reading_limits is not None:
            lim = torch.as_tensor(reading_limits, dtype=dtype).reshape(n_read, 2).to(device).clone()
        else:
            lim = joint_limits.clone() if self.readings.is_identity else self.readings.reading_limits(joint_limits)
        self.register_buffer("limits", lim)
        if reading_names is not None:
            self.reading_names = list(reading_names)
        elif self.readings.is_identity:
            self.reading_names = list(self.joint_names)
        else:
            self.reading_names = [f"J{k + 1}" for k in range(n_read)]
        # link masses [kg] and centres of mass in each joint's child frame (the frame that
        # rotates with joint i, F_i below): what gravity-torque effects need
        m = torch.zeros(dof, dtype=dtype) if masses is None else torch.as_tensor(masses, dtype=dtype)
        c = torch.zeros(dof, 3, dtype=dtype) if coms is None else torch.as_tensor(coms, dtype=dtype)
        self.register_buffer("masses", m.to(device).clone())
        self.register_buffer("coms", c.to(device).clone())
        self.has_masses = masses is not None
        self._chain_cache: tuple[bytes, object] | None = None

    # ----------------------------------------------------------------- basics
    @property
    def dof(self) -> int:
        """The number of joint readings (the controller's joints; the model's chain has :attr:`n_joints`)."""
        return self.readings.n_readings

    @property
    def n_joints(self) -> int:
        """The number of the chain's model joints (mimic joints included)."""
        return self.geometry.dof

    @property
    def joint_types(self) -> tuple[str, ...]:
        """``"revolute"`` or ``"prismatic"`` per reading: the unit of its column (rad or m), that of the model joints
        it drives (``geometry.joint_types`` are the chain's)."""
        types = self.geometry.joint_types
        if self.readings.is_identity:
            return types
        A = self.readings.nominal
        return tuple(
            "prismatic" if any(t == "prismatic" and float(A[i, k]) != 0.0 for i, t in enumerate(types)) else "revolute"
            for k in range(A.shape[1])
        )

    @property
    def prismatic(self) -> Tensor:
        """Boolean ``(dof,)``: which readings drive prismatic joints (reading in m)."""
        return torch.tensor([k == "prismatic" for k in self.joint_types], dtype=torch.bool, device=self.device)

    @property
    def has_readings_map(self) -> bool:
        """True when the readings are not the model joints themselves (a ``readings:`` block, mimic joints)."""
        return not self.readings.is_identity

    def model_joints(self, q: Tensor, delta: Tensor | None = None) -> Tensor:
        """The chain's joint angles ``(..., n_joints)`` [rad] of readings ``q (..., dof)``: ``q`` itself without a
        readings map. ``delta`` replaces the readings map's correction."""
        if self.readings.is_identity and delta is None:
            return q
        return self.readings.joints(q, delta)

    @property
    def dtype(self) -> torch.dtype:
        return self.limits.dtype

    @property
    def device(self) -> torch.device:
        return self.limits.device

    def _check_q(self, q: Tensor) -> Tensor:
        if not isinstance(q, Tensor):
            raise ShapeError(f"q must be a torch.Tensor of shape (N, {self.dof}), got {type(q).__name__}")
        _check_dtype("q", q, self.limits)
        if q.ndim < 1 or q.shape[-1] != self.dof:
            raise ShapeError(f"q must have shape (N, {self.dof}) for robot '{self.name}', got {tuple(q.shape)}")
        return q

    # --------------------------------------------------------------------- FK
    def joint_frames(self, q: Tensor, origins: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Frames of every joint's child link and the flange.

        Args:
            q: joint readings ``(..., dof)`` [rad].
            origins: ``(n_joints + 1, 4, 4)`` to use instead of the geometry's current ones.

        Returns:
            ``F (..., n_joints, 4, 4)`` (one per model joint) with ``F_i = T_base_(link moved by joint i)`` (the joint
            rotation included; its origin lies on joint i's axis), and ``T_base_flange (..., 4, 4)``.
        """
        q = self.model_joints(self._check_q(q))
        Rs, ts, R, t = self._chain(q, self.geometry.origins() if origins is None else origins, frames=True)
        return tf.homogeneous(torch.stack(Rs, dim=-3), torch.stack(ts, dim=-2)), tf.homogeneous(R, t)

    def _chain(self, q: Tensor, O: Tensor, frames: bool) -> tuple[list[Tensor], list[Tensor], Tensor, Tensor]:
        """The product of the chain as rotations and translations: the joint frames' ``R (..., 3, 3)`` and
        ``t (..., 3)`` (when ``frames``) and the flange's.

        Joint i turns the frame in front of it by ``O_i (I + sin(q_i) K + (1 - cos(q_i)) K^2)`` (Rodrigues, ``K`` the
        axis' cross-product matrix) and moves it by ``O_i``'s translation ``o_i``. With ``C_i = [O_i, O_i K,
        O_i K^2, o_i]`` (``3 x 10``, no pose in it) each joint is one product ``R C_i`` and elementwise terms
        (``R O_i + s R O_i K + (1 - c) R O_i K^2`` and ``t + R o_i``). The poses sit in the last dimension and each
        ``R`` is held transposed, ``Rt[k, a, pose] = R[a, k]``: then ``C_i^T Rt`` is one plain matrix product
        ``(10, 3) x (3, 3 poses)`` (the same computation with and without autograd) whose blocks are the next
        ``Rt``'s terms, and every elementwise term runs along contiguous poses. The residuals of every
        least-squares iteration pass through here; at a few thousand poses the cost is the number of torch
        operations and how well each vectorises, half of that of a product per factor with the poses first.
        """
        Rts, ts, Rt_end, t_end = self._chain_t(q, O, frames)
        batch = q.shape[:-1]
        Rs = [_poses_first(R, batch) for R in Rts]
        return Rs, [_poses_first(t, batch) for t in ts], _poses_first(Rt_end, batch), _poses_first(t_end, batch)

    def _chain_t(self, q: Tensor, O: Tensor, frames: bool) -> tuple[list[Tensor], list[Tensor], Tensor, Tensor]:
        """:meth:`_chain` with the poses in the last dimension: ``Rt (3, 3, M)`` with ``Rt[k, a, pose] = R[a, k]``
        and ``t (3, M)``, the ``M`` poses of ``q`` flattened (:func:`_rotate` applies such an ``R`` to a vector)."""
        dof = self.n_joints
        qt = q.reshape(-1, dof).T  # (dof, M)
        m = qt.shape[1]
        rot, off = O[:, :3, :3], O[:, :3, 3]
        K = tf.skew(self.geometry.axes)  # (dof, 3, 3)
        OK = rot[:dof] @ K
        Ct = torch.cat([rot[:dof], OK, OK @ K, off[:dof].unsqueeze(-1)], dim=-1).transpose(-1, -2)  # (dof, 10, 3)
        s, c = torch.sin(qt), 1.0 - torch.cos(qt)  # (dof, M)
        prismatic = self.geometry.joint_types
        Rt, t = None, off[0].unsqueeze(-1).expand(3, m)  # Rt[k, a, pose] = R[a, k]; t[a, pose]
        Rts, ts = [], []
        for i in range(dof):
            if Rt is None:  # joint 0: the base's origin, the same for every pose
                X = Ct[i].unsqueeze(-1)  # (10, 3, 1)
            else:
                X = (Ct[i] @ Rt.reshape(3, 3 * m)).reshape(10, 3, m)
                t = t + X[9]
            if prismatic[i] == "prismatic":  # no turn; a move by q_i [m] along the axis, R O_i a_i
                Rt = X[0:3].expand(3, 3, m)
                t = t + _dual.mul(_rotate(Rt, self.geometry.axes[i]), qt[i])
            else:  # _dual: the readings carry no tangent where jacfwd differentiates by the geometry (a 6-D probe)
                Rt = X[0:3] + _dual.mul(s[i], X[3:6]) + _dual.mul(c[i], X[6:9])
            if frames:
                Rts.append(Rt)
                ts.append(t)
        end = (O[-1, :3, :].T @ Rt.reshape(3, 3 * m)).reshape(4, 3, m)
        return Rts, ts, end[0:3], t + end[3]

    def forward(self, q: Tensor) -> Tensor:
        """``T_base_flange (..., 4, 4)`` for joint readings ``q (..., dof)`` [rad, m for a prismatic joint], current
        geometry."""
        _, _, R, t = self._chain(self.model_joints(self._check_q(q)), self.geometry.origins(), frames=False)
        return tf.homogeneous(R, t)

    def T_tracker_base(self, station: int | None = None) -> Tensor:
        """``T_tracker_base (4, 4)``: of ``station`` (index, default 0) when the instrument has several."""
        M = self.instrument.matrix()
        return M if M.dim() == 2 else M[station or 0]

    def t_flange_probe(self, probe: int | None = None) -> Tensor:
        """``t_flange_probe (3,)`` [m]: of ``probe`` (index, default 0) when the tool has several."""
        t = self.tool.vector()
        return t if t.dim() == 1 else t[probe or 0]

    @property
    def has_orientation(self) -> bool:
        """Whether the model carries the probe frame's orientation (:meth:`enable_orientation`)."""
        return self.tool_rotation is not None

    def enable_orientation(self, R_flange_probe: Tensor | None = None) -> None:
        """Give the model the probe frame's orientation in the flange frame (a 6-D probe such as a T-Mac): the
        group ``tool_rotation`` (``tool.rx, tool.ry, tool.rz``), nominal ``R_flange_probe (3, 3)`` (default the
        identity, or the present one where it is enabled already)."""
        if self.tool_rotation is None:
            self.tool_rotation = ToolRotation(dtype=self.dtype, device=self.device)
        if R_flange_probe is not None:
            self.tool_rotation.set_matrix(R_flange_probe.to(self.dtype).to(self.device))

    def probe_rotation(self, q: Tensor) -> Tensor:
        """Orientation of the probe frame in the robot base frame ``R_base_flange(q) R_flange_probe (..., 3, 3)``.

        Raises:
            OptionError: the model has no probe orientation (:meth:`enable_orientation`).
        """
        if self.tool_rotation is None:
            from torchcal.errors import OptionError

            raise OptionError(f"robot '{self.name}' carries no probe orientation (enable_orientation)")
        return self(q)[..., :3, :3] @ self.tool_rotation.matrix()

    def flange_rotation_axes(self, q: Tensor, columns: Sequence[int]) -> tuple[Tensor, Tensor, Tensor]:
        """``R_base_flange (N, 3, 3)`` at joints ``q (N, dof)`` and the axes about which its exact derivatives turn
        it, in the base frame: by each joint ``z (N, dof, 3)``, ``dR/dq_j = [z_j]x R``, and by the geometry elements
        ``columns`` (flat indices into the geometry's delta) ``w (N, len(columns), 3)``, ``dR/dd_k = [w_k]x R``; a
        robot without a readings map (its readings are its joints).

        With ``F_j`` the frame of joint j (its rotation included) and ``a_j`` its axis, ``z_j = F_j a_j`` (zero for a
        prismatic joint). The chain ``R = P_i O_i S_i`` is linear in each origin's rotation ``O_i``, ``P_i = F_(i-1)``
        the frame in front of it (the identity for the first), so ``dR/dd = P_i (dO_i/dd) O_i^T P_i^T R``, and
        ``(dO_i/dd) O_i^T = [s]x`` (``O_i`` stays a rotation) with ``s`` from the small ``dO_i/dd`` (no pose in it, by
        reverse mode on :meth:`~torchcal.robot.geometry.Geometry.origins`, as :meth:`tracker_jacobian` takes them):
        ``w = P_i s``.
        """
        if not self.readings.is_identity:
            raise ShapeError(f"robot '{self.name}' maps its readings to its joints: no rotation Jacobian by readings")
        q = self._check_q(q)
        with torch.no_grad():
            O = self.geometry.origins()
            Rts, _, Rt_end, _ = self._chain_t(q, O, frames=True)
            n = q.shape[0]
            R = Rt_end.expand(3, 3, n).permute(2, 1, 0)  # Rt[k, a, pose] = R[a, k]
            frames = [Rt.expand(3, 3, n).permute(2, 1, 0) for Rt in Rts]  # (N, 3, 3) each
            z = torch.stack([F @ a for F, a in zip(frames, self.geometry.axes)], dim=1)  # (N, dof, 3)
            z = torch.where(self.geometry.prismatic[:, None], torch.zeros_like(z), z)
            k = len(columns)
            A = _small_jacobian(lambda x: self.geometry.origins(x)[..., :3, :3], self.geometry.delta, columns)
            A = A.reshape(self.n_joints + 1, 3, 3, k)
            w = R.new_zeros(n, k, 3)
            for i in range(self.n_joints + 1):
                nz = torch.nonzero(A[i].reshape(9, k).abs().amax(0)).flatten()
                if len(nz) == 0:
                    continue
                M = A[i][..., nz].permute(2, 0, 1) @ O[i, :3, :3].T  # (k_i, 3, 3): dO_i/dd O_i^T, skew
                s = torch.stack([M[:, 2, 1], M[:, 0, 2], M[:, 1, 0]], -1)  # (k_i, 3)
                w[:, nz] += s if i == 0 else (frames[i - 1] @ s.T).transpose(1, 2)
        return R, z, w

    @property
    def stations(self) -> tuple[str, ...]:
        """The instrument's station names (empty for a single placement)."""
        return self.instrument.stations

    @property
    def probes(self) -> tuple[str, ...]:
        """The tool's probe names (empty for a single probe)."""
        return self.tool.probes

    def set_stations(self, names: Sequence[str] | None) -> None:
        """One instrument pose per station ``names`` (two or more; fewer: a single pose), each starting from the
        current (first) pose; the corrections restart at zero."""
        T = self.T_tracker_base().detach()
        self.instrument = Instrument(T, dtype=self.dtype, device=self.device, stations=names)

    def set_probes(self, names: Sequence[str] | None) -> None:
        """One lever arm per probe ``names`` (two or more; fewer: a single lever arm), each starting from the current
        (first) one."""
        t = self.t_flange_probe().detach()
        self.tool = Tool(t, dtype=self.dtype, device=self.device, probes=names)

    def _lever(self, t: Tensor, probe: Tensor | None) -> Tensor:
        """``t (3,)`` or ``(P, 3)`` -> ``(3,)`` or the rows' ``(N, 3)``."""
        if t.dim() == 1:
            return t
        # no index: the first probe (what works in one frame, e.g. a diagnostic plot of the probe's path)
        return t[0] if probe is None else t[probe]

    def probe_in_base(self, q: Tensor, probe: Tensor | None = None) -> Tensor:
        """Probe position in the robot base frame ``(..., 3)`` [m]; with several probes ``probe (N,)`` picks each
        row's lever arm."""
        q = self._check_q(q)
        _, _, Rt, t = self._chain_t(self.model_joints(q), self.geometry.origins(), frames=False)
        lever = self._lever(self.tool.vector(), probe)
        if lever.dim() == 1:
            return _poses_first(_rotate(Rt, lever) + t, q.shape[:-1])
        return _poses_first(_rotate_rows(Rt, lever) + t, q.shape[:-1])

    def probe_pose(self, q: Tensor, probe: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`probe_in_base` ``(..., 3)`` [m] and :meth:`probe_rotation` ``(..., 3, 3)`` (the same values) from one
        pass along the chain.

        Raises:
            OptionError: the model has no probe orientation (:meth:`enable_orientation`).
        """
        if self.tool_rotation is None:
            self.probe_rotation(q)  # raises
        q = self._check_q(q)
        _, _, Rt, t = self._chain_t(self.model_joints(q), self.geometry.origins(), frames=False)
        lever = self._lever(self.tool.vector(), probe)
        p = _rotate(Rt, lever) if lever.dim() == 1 else _rotate_rows(Rt, lever)
        batch = q.shape[:-1]
        return _poses_first(p + t, batch), _poses_first(Rt, batch) @ self.tool_rotation.matrix()

    def probe_jacobian(self, q: Tensor, probe: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Probe position in the base frame ``(..., 3)`` and its joint Jacobian ``(..., 3, dof)``.

        The geometric Jacobian, ``dp/dq_j = z_j x (p - o_j)`` for a revolute joint with ``z_j`` the axis and
        ``o_j`` a point of joint j, ``z_j`` itself for a prismatic one [m/m]: exact, and far cheaper than
        differentiating the FK per pose. With a readings map the derivative is by the readings:
        ``J_readings = J_joints A``.
        """
        q = self._check_q(q)
        Rts, ts, Rt, t = self._chain_t(self.model_joints(q), self.geometry.origins(), frames=True)
        lever = self._lever(self.tool.vector(), probe)
        p = (_rotate(Rt, lever) if lever.dim() == 1 else _rotate_rows(Rt, lever)) + t  # (3, M)
        z = torch.stack([_rotate(R, a) for R, a in zip(Rts, self.geometry.axes)])  # (dof, 3, M)
        J = torch.linalg.cross(z, p - torch.stack(ts), dim=1)  # (dof, 3, M)
        if "prismatic" in self.geometry.joint_types:
            J = torch.where(self.geometry.prismatic[:, None, None], z, J)
        batch = q.shape[:-1]
        J = J.permute(2, 1, 0).reshape(*batch, 3, self.n_joints)
        return _poses_first(p, batch), J if self.readings.is_identity else J @ self.readings.matrix()

    def probe_position(self, q: Tensor, station: Tensor | None = None, probe: Tensor | None = None) -> Tensor:
        """Probe position in the tracker frame ``(..., 3)`` [m]: what a laser tracker measures (with several stations
        or probes, ``station``/``probe (N,)`` pick each row's)."""
        if not self.stations and not self.probes:
            return tf.transform_points(self.T_tracker_base(), self.probe_in_base(q))
        return tf.transform_points(self.instrument.rows(station), self.probe_in_base(q, probe))

    # ------------------------------------------------------ parameter Jacobian
    def tracker_jacobian(
        self,
        q: Tensor,
        columns: Sequence[tuple[str, int]],
        deltas: dict[str, Tensor] | None = None,
        station: Tensor | None = None,
        probe: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Probe position in the tracker frame and its exact derivative by calibration parameters.

        The chain ``p = T_tb(d_inst) O_0(d_geo) R_0(q_0) O_1 R_1(q_1) ... O_n t(d_tool)`` is linear in each
        constant factor, so ``dp/dd = sum_i R(P_i) dO_i/dd s_i`` with ``P_i`` the frames in front of ``O_i``
        and ``s_i`` the probe behind it (homogeneous). The small ``dO_i/dd`` (no pose in it) come from
        reverse-mode autograd on :meth:`origins`; the pose-dependent part is a few batched products. Far
        cheaper in time and memory than ``torch.func.jacfwd`` of the whole forward pass, which holds one
        copy of every intermediate per parameter and imports ``torch._dynamo`` at its first use.

        Args:
            q: joint readings ``(N, dof)`` [rad].
            columns: the parameters, as ``(group, flat index into the group's delta)`` with group one of
                ``"geometry"``, ``"instrument"``, ``"tool"`` and, where the robot calibrates its readings map,
                ``"readings"`` (``dp/dA_ik = dp/dq_i r_k``).
            deltas: group -> corrections to use instead of the module's own (the deltas' shapes).
            station, probe: ``(N,)`` int64, each row's station and probe where the instrument has several stations or
                the tool several probes (a column of one station's pose or one probe's lever arm is zero in the other
                rows).

        Returns:
            ``p (N, 3)`` [m] and ``J (N, 3, len(columns))`` [m per m or rad].
        """
        q = self._check_q(q)
        deltas = deltas or {}
        d = {g: (deltas[g] if g in deltas else grp.delta).detach() for g, grp in self.groups().items()}
        cols = {g: [(k, i) for k, (gg, i) in enumerate(columns) if gg == g] for g in d}
        if sum(len(c) for c in cols.values()) != len(columns):
            bad = sorted({g for g, _ in columns} - set(d))
            raise ShapeError(f"unknown parameter groups {bad}; groups: {', '.join(d)}")
        if self.stations or self.probes:
            return self._tracker_jacobian_rows(q, columns, d, cols, station, probe)
        r = q
        with torch.no_grad():
            q = self.model_joints(r, d.get("readings"))
            O = self.geometry.origins(d["geometry"])
            T = self.instrument.matrix(d["instrument"])
            t = self.tool.vector(d["tool"])
            # the poses in the last dimension, as the chain computes them (every product below runs along them)
            Rts, ts, Rt_flange, t_flange = self._chain_t(q, O, frames=True)
            p_base = _rotate(Rt_flange, t) + t_flange  # (3, N)
            p = (T[:3, :3] @ p_base + T[:3, 3:]).T
        n = q.shape[0]
        Jt = torch.zeros(3, len(columns), n, dtype=q.dtype, device=q.device)  # J[pose, a, k] = Jt[a, k, pose]
        if cols["geometry"]:
            idx = [i for _, i in cols["geometry"]]
            Jb = self._geometry_derivative(q, O, t.unsqueeze(-1).expand(3, n), Rts, d["geometry"], idx)
            Jt[:, [k for k, _ in cols["geometry"]]] = (T[:3, :3] @ Jb.reshape(3, -1)).reshape(3, len(idx), n)
        J = Jt.permute(2, 0, 1)
        if cols["instrument"]:
            idx = [i for _, i in cols["instrument"]]
            J[..., [k for k, _ in cols["instrument"]]] = self.instrument.point_jacobian(p_base.T, idx, d["instrument"])
        if cols["tool"]:
            idx = [i for _, i in cols["tool"]]
            C = _small_jacobian(self.tool.vector, d["tool"], idx)  # (3, k)
            k = len(idx)
            RC = (C.T @ Rt_flange.reshape(3, -1)).reshape(k, 3, n)  # RC[k, c, pose] = (R_flange C)[c, k]
            TRC = (T[:3, :3] @ RC.transpose(0, 1).reshape(3, -1)).reshape(3, k, n)
            J[..., [kk for kk, _ in cols["tool"]]] = TRC.permute(2, 0, 1)
        if cols.get("readings"):
            # q = A r + b: dp/dA_ik = dp/dq_i r_k, with dp/dq_i = z_i x (p - o_i) as in probe_jacobian
            n_read = self.dof
            for kk, flat in cols["readings"]:
                i, k = divmod(flat, n_read)
                z = _rotate(Rts[i], self.geometry.axes[i])
                if self.geometry.joint_types[i] == "prismatic":  # moved along its axis by q_i
                    Ji = T[:3, :3] @ z.expand_as(p_base)
                else:
                    Ji = T[:3, :3] @ torch.linalg.cross(z, p_base - ts[i], dim=0)  # (3, N)
                J[..., kk] = (Ji * r[:, k]).T
        return p, J.contiguous()

    def _geometry_derivative(
        self, q: Tensor, O: Tensor, lever: Tensor, Rts: list[Tensor], delta: Tensor, idx: list[int]
    ) -> Tensor:
        """The probe's derivative by the geometry elements ``idx`` in the base frame ``(3, len(idx), N)``: joints
        ``q (N, n_joints)``, origins ``O``, the lever arm ``lever (3, N)`` and the chain's frames ``Rts``
        (:meth:`_chain_t`). The chain is linear in each origin, so each column is the small ``dO_i/dd`` (no pose in
        it, by reverse mode on :meth:`origins`) applied to the probe right behind ``O_i`` and turned by the frame
        in front of it."""
        n, dof = q.shape[0], self.n_joints
        A = _small_jacobian(lambda x: self.geometry.origins(x)[..., :3, :], delta, idx)
        A = A.reshape(dof + 1, 3, 4, len(idx))
        # the probe right behind each origin: s_n = t, s_i = R_i(q_i) O_{i+1} s_{i+1}
        s = lever
        behind = [s]
        sin, one_cos = torch.sin(q.T), 1.0 - torch.cos(q.T)  # (dof, N)
        for i in range(dof - 1, -1, -1):
            s = O[i + 1, :3, :3] @ s + O[i + 1, :3, 3:]
            if self.geometry.joint_types[i] == "prismatic":  # moved along the axis by q_i
                s = s + self.geometry.axes[i].unsqueeze(-1) * q.T[i]
            else:
                K = tf.skew(self.geometry.axes[i])
                Ks = K @ s
                s = s + sin[i] * Ks + one_cos[i] * (K @ Ks)
            behind.append(s)
        behind.reverse()
        Jb = torch.zeros(3, len(idx), n, dtype=q.dtype, device=q.device)
        for i in range(dof + 1):
            nz = torch.nonzero(A[i].reshape(12, -1).abs().amax(0)).flatten()
            if len(nz) == 0:
                continue
            Ai = A[i][..., nz]  # (3, 4, k)
            k = len(nz)
            # V[a, k, pose] = sum_d Ai[a, d, k] s_i[d] + Ai[a, 3, k]: the derivative in the frame in front of O_i
            V = Ai[:, :3].transpose(1, 2).reshape(3 * k, 3) @ behind[i] + Ai[:, 3].reshape(3 * k, 1)
            V = V.reshape(3, k, n)
            if i > 0:  # rotated by the frame in front: sum_b R[a, b] V[b] with R[a, b] = Rt[b, a]
                V = (Rts[i - 1].unsqueeze(2) * V.unsqueeze(1)).sum(0)
            Jb[:, nz] += V
        return Jb

    def _tracker_jacobian_rows(self, r, columns, d, cols, station, probe) -> tuple[Tensor, Tensor]:
        """:meth:`tracker_jacobian` with several stations or probes: the same products with each row's instrument
        pose and lever arm (a separate path, so that a single station and probe compute exactly as before). Rows that
        name no station or probe (a caller in one frame: a candidate's geometric span) take the first."""
        first = torch.zeros(r.shape[0], dtype=torch.long, device=r.device)
        station = first if self.stations and station is None else station
        probe = first if self.probes and probe is None else probe
        with torch.no_grad():
            q = self.model_joints(r, d.get("readings"))
            O = self.geometry.origins(d["geometry"])
            T = self.instrument.rows(station, d["instrument"])
            T = T.expand(len(q), 4, 4) if T.dim() == 2 else T  # (N, 4, 4)
            t = self._lever(self.tool.vector(d["tool"]), probe)
            t = t.expand(len(q), 3) if t.dim() == 1 else t  # (N, 3)
            Rts, ts, Rt_flange, t_flange = self._chain_t(q, O, frames=True)
            p_base = _rotate_rows(Rt_flange, t) + t_flange  # (3, N)
            R = T[:, :3, :3]  # (N, 3, 3)
            p = (R @ p_base.T.unsqueeze(-1)).squeeze(-1) + T[:, :3, 3]
        n = q.shape[0]
        J = torch.zeros(n, 3, len(columns), dtype=q.dtype, device=q.device)
        if cols["geometry"]:
            idx = [i for _, i in cols["geometry"]]
            Jb = self._geometry_derivative(q, O, t.T, Rts, d["geometry"], idx)  # each row's lever arm
            J[..., [k for k, _ in cols["geometry"]]] = torch.einsum("nab,bkn->nak", R, Jb)
        if cols["instrument"]:
            idx = [i for _, i in cols["instrument"]]
            J[..., [k for k, _ in cols["instrument"]]] = self.instrument.rows_point_jacobian(
                p_base.T, station, idx, d["instrument"]
            )
        if cols["tool"]:
            # d p / d t = R_tracker R_flange e_c, in the rows of the column's probe only
            RRf = torch.einsum("nab,cbn->nac", R, Rt_flange)  # (N, 3, 3): R Rf (Rt_flange[c, b] = Rf[b, c])
            for kk, flat in cols["tool"]:
                pi, c = divmod(flat, 3) if self.probes else (0, flat)
                col = RRf[:, :, c]
                if self.probes:
                    col = col * (probe == pi).to(col.dtype)[:, None]
                J[..., kk] = col
        if cols.get("readings"):
            n_read = self.dof
            for kk, flat in cols["readings"]:
                i, k = divmod(flat, n_read)
                z = _rotate(Rts[i], self.geometry.axes[i])
                if self.geometry.joint_types[i] == "prismatic":
                    Ji = z.expand_as(p_base)
                else:
                    Ji = torch.linalg.cross(z, p_base - ts[i], dim=0)
                J[..., kk] = (R @ Ji.T.unsqueeze(-1)).squeeze(-1) * r[:, k : k + 1]
        return p, J.contiguous()

    # ---------------------------------------------------------------- gravity
    def gravity_torques(self, q: Tensor, payload: float | Tensor = 0.0, payload_com: Tensor | None = None) -> Tensor:
        """Static gravity torque at each joint reading ``(..., dof)`` [N m], robot base z pointing up.

        ``tau_j = z_j . sum_{k >= j} (c_k - o_j) x (m_k g)`` with ``z_j, o_j`` the axis and a point
        of joint j and ``c_k`` the centre of mass of link k; ``payload`` [kg] (a number, or one per pose ``(...,)``)
        sits at the probe, or at ``payload_com`` ``(..., 3)`` [m, flange frame] (:meth:`payload_torques`). A
        prismatic joint's generalised force is ``z_j . sum_{k >= j} m_k g`` [N]. With a readings map the torques are
        the generalised forces of the readings, ``A^T tau`` (virtual work: what the drive of each reading holds).
        """
        r = self._check_q(q)
        q = self.model_joints(r)
        Rts, ts, Rt_flange, t_flange = self._chain_t(q, self.geometry.origins(), frames=True)
        # the poses in the last dimension (as the chain computes them): every product below runs along them
        origins_w = torch.stack(ts)  # (dof, 3, M)
        com = torch.stack([_rotate(R, c) for R, c in zip(Rts, self.coms)]) + origins_w  # (dof, 3, M)
        axes_w = torch.stack([_rotate(R, a) for R, a in zip(Rts, self.geometry.axes)])  # (dof, 3, M)
        # sum_{k >= j} (c_k - o_j) x f_k = sum_{k >= j} c_k x f_k - o_j x sum_{k >= j} f_k with f_k = m_k g:
        # suffix sums over the links, linear in the joints instead of a (dof x dof) table per pose
        w = -GRAVITY * self.masses  # (dof,) z-components of the link weights
        # c x (0, 0, w) = w (c_y, -c_x, 0)
        m_xy = torch.stack([com[:, 1], -com[:, 0]], dim=1) * w[:, None, None]  # (links, 2, M)
        suffix = m_xy.flip(0).cumsum(0).flip(0)[: self.n_joints]  # (dof, 2, M)
        W = w.flip(0).cumsum(0).flip(0)[: self.n_joints]  # (dof,)
        total_xy = suffix - torch.stack([origins_w[:, 1], -origins_w[:, 0]], dim=1) * W[:, None, None]
        tau = (total_xy * axes_w[:, :2]).sum(1)  # (dof, M)
        if "prismatic" in self.geometry.joint_types:  # the weights beyond the joint along its axis (z-component)
            tau = torch.where(self.geometry.prismatic[:, None], axes_w[:, 2] * W[:, None], tau)
        if isinstance(payload, Tensor) or payload:
            tau = tau + self._payload_tau(origins_w, axes_w, Rt_flange, t_flange, payload, payload_com)
        if not self.readings.is_identity:
            tau = self.readings.matrix().T @ tau  # (readings, M)
        return tau.T.reshape(*r.shape[:-1], self.dof)

    def payload_torques(self, q: Tensor, payload: float | Tensor = 1.0, payload_com: Tensor | None = None) -> Tensor:
        """The static torque ``(..., dof)`` [N m, N] of the payload alone: ``payload`` [kg] (a number or one per pose
        ``(...,)``) at ``payload_com`` ``(..., 3)`` [m, flange frame], or at the probe where it is None. It needs no
        link masses: a robot description without them (a DH table) still knows the payload's lever at each joint."""
        r = self._check_q(q)
        Rts, ts, Rt_flange, t_flange = self._chain_t(self.model_joints(r), self.geometry.origins(), frames=True)
        axes_w = torch.stack([_rotate(R, a) for R, a in zip(Rts, self.geometry.axes)])
        tau = self._payload_tau(torch.stack(ts), axes_w, Rt_flange, t_flange, payload, payload_com)
        if not self.readings.is_identity:
            tau = self.readings.matrix().T @ tau
        return tau.T.reshape(*r.shape[:-1], self.dof)

    def _payload_tau(self, origins_w, axes_w, Rt_flange, t_flange, payload, payload_com) -> Tensor:
        """The payload's torque per joint ``(dof, M)`` in the chain's pose-last frames."""
        m = t_flange.shape[-1]
        mass = torch.as_tensor(payload, dtype=t_flange.dtype, device=t_flange.device).reshape(-1).expand(m)
        if payload_com is None:
            point = _rotate(Rt_flange, self.t_flange_probe()) + t_flange  # (3, M)
        else:
            point = _rotate_rows(Rt_flange, payload_com.reshape(m, 3).to(t_flange.dtype)) + t_flange
        w = -GRAVITY * mass  # (M,)
        # (c - o_j) x (0, 0, w) = w ((c - o_j)_y, -(c - o_j)_x, 0)
        lever = point[None] - origins_w  # (dof, 3, M)
        tau = (torch.stack([lever[:, 1], -lever[:, 0]], dim=1) * w * axes_w[:, :2]).sum(1)  # (dof, M)
        if "prismatic" in self.geometry.joint_types:
            tau = torch.where(self.geometry.prismatic[:, None], axes_w[:, 2] * w, tau)
        return tau

    def static_torques(self, q: Tensor, payload: float | Tensor = 0.0, payload_com: Tensor | None = None) -> Tensor:
        """:meth:`gravity_torques` without gradient, as the joint effects take them for their regressor, the last
        results reused ``(..., dof)`` [N m].

        A least-squares fit evaluates its effects at the same joint angles dozens of times, and its Jacobian twice
        at the same parameter values; the torque (a pass over the chain of every pose) is then computed once for
        each joint-angle tensor (the same object, unchanged in place; with a payload per pose, the same payload
        tensors too) and each geometry (and lever arm, with a payload) by value, so the results are those of
        computing it every time.
        """
        geo = self.geometry.delta
        if not self.readings.is_identity:  # the map moves the torques too: one key for both
            geo = torch.cat([geo.reshape(-1), self.readings.delta.reshape(-1)])
        rows = isinstance(payload, Tensor)
        tool = self.tool.delta if rows or payload else None
        kq = None if q.is_meta or q.requires_grad else version_key(q, *((payload, payload_com) if rows else ()))
        kp = "rows" if rows else float(payload)  # a payload per row is keyed by its tensors' versions (in kq)
        if kq is None or not plain(geo) or (tool is not None and not plain(tool)):
            with torch.no_grad():
                return self.gravity_torques(q, payload, payload_com)
        cache = self.__dict__.setdefault("_torque_cache", [])
        for (k, kp0, kg, kt), tau in cache:
            if same_version(k, kq) and kp0 == kp and torch.equal(kg, geo) and (kt is None or torch.equal(kt, tool)):
                return tau
        with torch.no_grad():
            tau = self.gravity_torques(q, payload, payload_com)
        if not plain(tau):  # a transform's tensor reached it through the robot's other values: not a plain result
            return tau
        key = (kq, kp, geo.detach().clone(), None if tool is None else tool.detach().clone())
        cache.insert(0, (key, tau))
        del cache[_TORQUE_CACHE:]
        return tau

    def gravity_regressor(self, q: Tensor) -> Tensor:
        """The gravity torques' regressor ``Y (..., dof, 4 n_joints)`` [N m per kg, N per kg]: ``tau = Y @ pi``.

        The static gravity torque is linear in the links' mass moments ``pi_k = (m_k, m_k c_k)`` (``c_k`` the centre
        of mass in joint k's child frame, as :attr:`coms`), ``pi = (pi_1, ..., pi_n)``; column block ``k`` of row
        ``j`` is zero for ``k < j`` and else ``[z_j . ((o_k - o_j) x g), z_j . ((R_k e_x) x g), z_j . ((R_k e_y) x g),
        z_j . ((R_k e_z) x g)]`` with ``z_j, o_j`` joint j's axis and a point on it, ``o_k, R_k`` link k's frame and
        ``g = (0, 0, -GRAVITY)``; for a prismatic joint ``[z_j . g, 0, 0, 0]`` (the weight along its axis). With a
        readings map the rows are the readings' generalised forces, ``A^T Y``. For a robot with masses, ``Y @ pi``
        equals :meth:`gravity_torques` (no payload). Without masses it is what a lumped compliance estimates through
        (:class:`~torchcal.effects.LumpedCompliance`).
        """
        r = self._check_q(q)
        Rts, ts, _, _ = self._chain_t(self.model_joints(r), self.geometry.origins(), frames=True)
        n, m = self.n_joints, ts[0].shape[-1]
        o = torch.stack(ts)  # (n, 3, M)
        z = torch.stack([_rotate(R, a) for R, a in zip(Rts, self.geometry.axes)])  # (n, 3, M)
        # vectors whose torque the links' moments weigh: o_k (times m_k) and the link axes R_k e_a (times m_k c_k,a)
        axes = torch.stack(Rts)  # (n, 3 [a], 3 [xyz], M): R_k e_a, column a of R_k, is row a of the held Rt
        # v x g with g = (0, 0, -G): (-G v_y, G v_x, 0); z_j . (v x g) = G (z_j,y v_x - z_j,x v_y)
        zx, zy = z[:, 0], z[:, 1]  # (n [j], M)

        def lever(vx: Tensor, vy: Tensor) -> Tensor:  # (n [k], M) -> (n [j], n [k], M)
            return GRAVITY * (zy[:, None] * vx[None] - zx[:, None] * vy[None])

        mass = lever(o[:, 0], o[:, 1]) - GRAVITY * (zy * o[:, 0] - zx * o[:, 1])[:, None]  # (o_k - o_j) x g
        moment = torch.stack([lever(axes[:, a, 0], axes[:, a, 1]) for a in range(3)], dim=2)  # (j, k, 3, M)
        if "prismatic" in self.geometry.joint_types:  # a prismatic joint holds the weight along its axis: z_j . g
            slide = self.geometry.prismatic[:, None, None]
            mass = torch.where(slide, (-GRAVITY * z[:, 2])[:, None].expand_as(mass), mass)
            moment = torch.where(slide[..., None], torch.zeros_like(moment), moment)
        Y = torch.cat([mass.unsqueeze(2), moment], dim=2)  # (j, k, 4, M)
        below = torch.ones(n, n, dtype=torch.bool, device=r.device).tril(-1)  # k < j: link k is behind joint j
        Y = Y.masked_fill(below[:, :, None, None], 0.0).reshape(n, 4 * n, m)
        if not self.readings.is_identity:
            Y = torch.einsum("jr,jcm->rcm", self.readings.matrix(), Y)  # the readings' generalised forces
        return Y.permute(2, 0, 1).reshape(*r.shape[:-1], self.dof, 4 * n)

    def static_gravity_regressor(self, q: Tensor) -> Tensor:
        """:meth:`gravity_regressor` without gradient, the last results reused as :meth:`static_torques` reuses its
        own ``(..., dof, 4 dof)``."""
        geo, ratios = self.geometry.delta, self.readings.delta
        kq = None if q.is_meta or q.requires_grad else version_key(q)
        if kq is None or not plain(geo) or not plain(ratios):
            with torch.no_grad():
                return self.gravity_regressor(q)
        cache = self.__dict__.setdefault("_regressor_cache", [])
        for (k, kg, kr), Y in cache:
            if same_version(k, kq) and torch.equal(kg, geo) and torch.equal(kr, ratios):
                return Y
        with torch.no_grad():
            Y = self.gravity_regressor(q)
        if not plain(Y):
            return Y
        cache.insert(0, ((kq, geo.detach().clone(), ratios.detach().clone()), Y))
        del cache[_TORQUE_CACHE:]
        return Y

    def __getstate__(self):
        # a copy (deepcopy, pickle) leaves the torque cache behind: its keys are the original's joint tensors, which
        # the copy never sees again, and it holds a few tensors of the size of the data
        state = super().__getstate__()
        state.pop("_torque_cache", None)
        state.pop("_regressor_cache", None)
        return state

    # ------------------------------------------------------------- parameters
    def groups(self) -> dict[str, _Group]:
        """The parameter groups: geometry, instrument, tool, and ``readings`` where the description declares ratios
        of its readings map that may be calibrated."""
        out = {"geometry": self.geometry, "instrument": self.instrument, "tool": self.tool}
        if self.tool_rotation is not None:
            out["tool_rotation"] = self.tool_rotation
        if self.readings.has_free:
            out["readings"] = self.readings
        return out

    def parameter_info(self) -> list[ParameterInfo]:
        """Every calibration parameter element, in a fixed order (geometry, instrument, tool, then the readings map's
        free ratios, unit 1)."""
        out = []
        for gname, g in self.groups().items():
            shape = g.delta.shape
            for flat, name in enumerate(g.names):
                idx = _unravel(flat, tuple(shape))  # torch.unravel_index imports sympy (0.3 s, 40 MB)
                if gname == "readings":
                    if bool(g.mask[idx]):  # the map's fixed entries (zeros, mimic rows) are no parameters
                        out.append(ParameterInfo(gname, name, idx, "1"))
                    continue
                col = name.rsplit(".", 1)[-1] if "." in name else name.rstrip("0123456789")
                unit = "rad" if col in ("alpha", "theta", "beta", "rx", "ry", "rz") else "m"
                out.append(ParameterInfo(gname, name, idx, unit))
        return out

    def reset_parameters(self) -> None:
        for g in self.groups().values():
            g.reset()

    # ------------------------------------------------------- pytorch-kinematics
    @property
    def chain(self):
        """The pytorch-kinematics ``SerialChain`` of this robot with its current geometry.

        Built from the float64 origin matrices (not through pk's URDF parser, which goes
        through float32), rebuilt when the parameters change.
        """
        with torch.no_grad():
            O = self.geometry.origins().detach()
        key = O.cpu().numpy().tobytes()
        if self._chain_cache is None or self._chain_cache[0] != key:
            self._chain_cache = (key, build_pk_chain(self, O))
        return self._chain_cache[1]


def _unravel(flat: int, shape: tuple[int, ...]) -> tuple[int, ...]:
    """Row-major multi-index of the flat index ``flat`` in ``shape``."""
    out = []
    for n in reversed(shape):
        flat, r = divmod(flat, n)
        out.append(r)
    return tuple(reversed(out))


def _poses_first(x: Tensor, batch: tuple[int, ...]) -> Tensor:
    """A pose-last rotation ``Rt (3, 3, M)`` (held transposed) or vector ``(3, M)`` of :meth:`RobotModel._chain_t`
    as ``(*batch, 3, 3)`` or ``(*batch, 3)``."""
    if x.ndim == 3:
        return x.permute(2, 1, 0).reshape(*batch, 3, 3)
    return x.T.reshape(*batch, 3)


def _rotate(Rt: Tensor, v: Tensor) -> Tensor:
    """``R v`` per pose ``(3, M)`` for a pose-last rotation ``Rt (3, 3, M)`` (``Rt[k, a] = R[a, k]``) and ``v (3,)``:
    one product ``v^T (3, 3 M)``."""
    m = Rt.shape[-1]
    return (v @ Rt.reshape(3, 3 * m)).reshape(3, m)


def _rotate_rows(Rt: Tensor, v: Tensor) -> Tensor:
    """``R_m v_m`` per pose ``(3, M)``: a pose-last rotation ``Rt (3, 3, M)``, one vector per pose ``v (M, 3)``."""
    return torch.einsum("kam,mk->am", Rt, v)


def _small_jacobian(f, d0: Tensor, columns: Sequence[int]) -> Tensor:
    """``d f(d) / d d`` at ``d0`` for the flat ``columns`` of ``d``: ``(f(d0).numel(), len(columns))``.

    ``f`` must accept a leading batch dimension. It is evaluated once on ``M`` copies of ``d0``, one per
    output element, and one reverse pass of the sum of each copy's own element gives every row at once.
    ``torch.func``'s forward mode would do the same, but it imports ``torch._dynamo`` (seconds, tens of
    MB) at its first use.
    """
    cols = torch.as_tensor(list(columns), dtype=torch.long, device=d0.device)
    m = f(d0.detach()).numel()
    d = d0.detach().expand(m, *d0.shape).clone().requires_grad_(True)
    with torch.enable_grad():
        y = f(d).reshape(m, m)
        if not y.requires_grad:
            return torch.zeros(m, len(cols), dtype=d0.dtype, device=d0.device)
        (g,) = torch.autograd.grad(y.diagonal().sum(), d, allow_unused=True)
    if g is None:
        return torch.zeros(m, len(cols), dtype=d0.dtype, device=d0.device)
    return g.reshape(m, -1)[:, cols]


def build_pk_chain(robot: RobotModel, origins: Tensor):
    """A pytorch-kinematics SerialChain from float64 origin matrices ``(dof + 1, 4, 4)``."""
    import pytorch_kinematics as pk

    dtype, device = origins.dtype, origins.device
    root = pk.Frame(
        name=robot.link_names[0],
        link=pk.Link(name=robot.link_names[0]),
        joint=pk.Joint(name="root", dtype=dtype, device=device),
    )
    parent = root
    for i in range(robot.n_joints):
        joint = pk.Joint(
            name=robot.joint_names[i],
            offset=pk.Transform3d(matrix=origins[i].clone(), dtype=dtype, device=device),
            joint_type=robot.geometry.joint_types[i],
            axis=robot.geometry.axes[i].clone(),
            dtype=dtype,
            device=device,
            limits=(float(robot.joint_limits[i, 0]), float(robot.joint_limits[i, 1])),
        )
        frame = pk.Frame(name=robot.link_names[i + 1], link=pk.Link(name=robot.link_names[i + 1]), joint=joint)
        parent.add_child(frame)
        parent = frame
    tip = pk.Frame(
        name=robot.link_names[-1],
        link=pk.Link(name=robot.link_names[-1]),
        joint=pk.Joint(
            name=f"{robot.link_names[-1]}_fixed",
            offset=pk.Transform3d(matrix=origins[-1].clone(), dtype=dtype, device=device),
            joint_type="fixed",
            dtype=dtype,
            device=device,
        ),
    )
    parent.add_child(tip)
    chain = pk.Chain(root, dtype=dtype, device=device)
    return pk.SerialChain(chain, robot.link_names[-1], robot.link_names[0], dtype=dtype, device=device)
