"""Rigid-body transforms in float64, batched over leading dimensions and differentiable.

Conventions: homogeneous matrices ``T_a_b`` map points of frame b into frame a,
``p_a = T_a_b @ p_b``. Rotation vectors are axis * angle (radians). URDF ``rpy`` is
extrinsic roll-pitch-yaw, ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import math

import torch

from torchcal import _dual

Tensor = torch.Tensor


def _cs(angle: Tensor) -> tuple[Tensor, Tensor]:
    return torch.cos(angle), torch.sin(angle)


def rot_x(angle: Tensor) -> Tensor:
    """Rotation about x. ``angle (...)`` -> ``(..., 3, 3)``."""
    c, s = _cs(angle)
    o, z = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack([o, z, z, z, c, -s, z, s, c], dim=-1).reshape(*c.shape, 3, 3)


def rot_y(angle: Tensor) -> Tensor:
    """Rotation about y. ``angle (...)`` -> ``(..., 3, 3)``."""
    c, s = _cs(angle)
    o, z = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack([c, z, s, z, o, z, -s, z, c], dim=-1).reshape(*c.shape, 3, 3)


def rot_z(angle: Tensor) -> Tensor:
    """Rotation about z. ``angle (...)`` -> ``(..., 3, 3)``."""
    c, s = _cs(angle)
    o, z = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack([c, -s, z, s, c, z, z, z, o], dim=-1).reshape(*c.shape, 3, 3)


def _broadcast(a: torch.Size, b: torch.Size) -> tuple[int, ...]:
    """NumPy broadcasting of two shapes, in plain Python: ``torch.broadcast_shapes`` imports sympy (0.3 s and
    40 MB at the first call)."""
    n = max(len(a), len(b))
    a, b = (1,) * (n - len(a)) + tuple(a), (1,) * (n - len(b)) + tuple(b)
    out = []
    for x, y in zip(a, b):
        if x != y and x != 1 and y != 1:
            raise ValueError(f"shapes {a} and {b} do not broadcast")
        out.append(y if x == 1 else x)
    return tuple(out)


def homogeneous(R: Tensor, t: Tensor) -> Tensor:
    """Stack ``R (..., 3, 3)`` and ``t (..., 3)`` into ``(..., 4, 4)``."""
    batch = _broadcast(R.shape[:-2], t.shape[:-1])
    R = R.expand(*batch, 3, 3)
    t = t.expand(*batch, 3)
    top = torch.cat([R, t.unsqueeze(-1)], dim=-1)
    bottom = torch.zeros(*batch, 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def translation(t: Tensor) -> Tensor:
    """Pure translation ``(..., 3)`` -> ``(..., 4, 4)``."""
    eye = torch.eye(3, dtype=t.dtype, device=t.device)
    return homogeneous(eye.expand(*t.shape[:-1], 3, 3), t)


def invert(T: Tensor) -> Tensor:
    """Inverse of a rigid transform ``(..., 4, 4)`` without a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = R.transpose(-1, -2)
    return homogeneous(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix ``[v]x`` of ``v (..., 3)`` -> ``(..., 3, 3)``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def so3_exp(rotvec: Tensor) -> Tensor:
    """Rodrigues' formula, ``(..., 3)`` -> ``(..., 3, 3)``.

    Differentiable everywhere including the origin: near zero the coefficients use
    their Taylor series, so the derivative at a zero correction is the exact
    generator (the calibration parameters start at zero).
    """
    # the constants meet the rotation vector through torchcal._dual: every Jacobian of a calibration with an
    # instrument differentiates this in forward mode, where ``theta2 / 6.0`` or ``eye + ...`` would take torch's
    # Python path (and import torch._dynamo); the values are those of the plain expressions
    theta2 = (rotvec * rotvec).sum(-1)
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    t4 = theta2 * theta2
    a_small = 1.0 - _dual.div_scalar(theta2, 6.0) + _dual.div_scalar(t4, 120.0)
    b_small = 0.5 - _dual.div_scalar(theta2, 24.0) + _dual.div_scalar(t4, 720.0)
    a = torch.where(small, a_small, torch.sin(theta) / theta)
    b = torch.where(small, b_small, (1.0 - torch.cos(theta)) / safe2)
    K = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    aK = a[..., None, None] * K
    return _dual.add(eye, aK) + b[..., None, None] * (K @ K)


def so3_log(R: Tensor) -> Tensor:
    """Rotation vector of ``R (..., 3, 3)``, valid for angles in [0, pi)."""
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = ((tr - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.arccos(cos)
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    small = theta < 1e-6
    factor = torch.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * torch.sin(torch.where(small, 1.0, theta))))
    return factor[..., None] * w


def axis_angle(axis: Tensor, angle: Tensor) -> Tensor:
    """Rotation about a unit ``axis (3,)`` by ``angle (...)`` -> ``(..., 3, 3)``."""
    K = skew(axis)
    eye = torch.eye(3, dtype=angle.dtype, device=angle.device)
    s = torch.sin(angle)[..., None, None]
    c = torch.cos(angle)[..., None, None]
    return eye + s * K + (1.0 - c) * (K @ K)


def se3_from_vector(xi: Tensor) -> Tensor:
    """Small-correction transform from ``[tx, ty, tz, rx, ry, rz] (..., 6)``: ``[exp(r) | t]``."""
    return homogeneous(so3_exp(xi[..., 3:]), xi[..., :3])


def rpy_to_matrix(rpy: Tensor) -> Tensor:
    """URDF roll-pitch-yaw ``(..., 3)`` -> ``(..., 3, 3)`` = Rz(yaw) Ry(pitch) Rx(roll)."""
    return rot_z(rpy[..., 2]) @ rot_y(rpy[..., 1]) @ rot_x(rpy[..., 0])


def matrix_to_rpy(R: Tensor) -> Tensor:
    """Inverse of :func:`rpy_to_matrix` ``(..., 3, 3)`` -> ``(..., 3)``.

    At pitch = +-pi/2 (gimbal lock) roll is set to zero and yaw takes the rest.
    """
    sp = (-R[..., 2, 0]).clamp(-1.0, 1.0)
    pitch = torch.asin(sp)
    cp = torch.sqrt(R[..., 2, 1] ** 2 + R[..., 2, 2] ** 2)
    lock = cp < 1e-12
    roll = torch.where(lock, torch.zeros_like(sp), torch.atan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = torch.where(lock, torch.atan2(-R[..., 0, 1], R[..., 1, 1]), torch.atan2(R[..., 1, 0], R[..., 0, 0]))
    # recover pitch accurately from both components (asin loses digits near +-pi/2)
    pitch = torch.atan2(sp, cp)
    return torch.stack([roll, pitch, yaw], dim=-1)


def transform_points(T: Tensor, p: Tensor) -> Tensor:
    """Apply ``T (..., 4, 4)`` to points ``p (..., 3)``."""
    # a constant transform of differentiated points (or the reverse) meets them through torchcal._dual
    return _dual.add((T[..., :3, :3] @ p.unsqueeze(-1)).squeeze(-1), T[..., :3, 3])


DEG = math.pi / 180.0
