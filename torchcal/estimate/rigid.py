"""Closed-form rigid fit between two point sets (Kabsch / Horn), float64."""

from __future__ import annotations

import torch

from torchcal.errors import EstimationError, ShapeError
from torchcal.robot import transforms as tf

Tensor = torch.Tensor


def rigid_fit(p_from: Tensor, p_to: Tensor, weights: Tensor | None = None) -> Tensor:
    """The rigid transform ``T_to_from (4, 4)`` minimising ``sum w |T p_from - p_to|^2``.

    Args:
        p_from, p_to: corresponding points ``(N, 3)``, N >= 3 and not collinear.
        weights: ``(N,)`` non-negative, default equal.

    Raises:
        EstimationError: when the points do not fix a rotation (fewer than 3, or collinear).
    """
    if p_from.shape != p_to.shape or p_from.ndim != 2 or p_from.shape[1] != 3:
        raise ShapeError(f"rigid_fit needs two (N, 3) point sets, got {tuple(p_from.shape)} and {tuple(p_to.shape)}")
    n = p_from.shape[0]
    w = torch.ones(n, dtype=p_from.dtype, device=p_from.device) if weights is None else weights
    w = w / w.sum()
    c_from = (w[:, None] * p_from).sum(0)
    c_to = (w[:, None] * p_to).sum(0)
    H = ((p_from - c_from) * w[:, None]).T @ (p_to - c_to)
    U, S, Vh = torch.linalg.svd(H)
    if n < 3 or S[1] <= 1e-12 * max(float(S[0]), 1e-300):
        raise EstimationError(f"rigid fit is undetermined: {n} points, singular values {S.tolist()} (collinear?)")
    d = torch.sign(torch.linalg.det(Vh.T @ U.T))
    D = torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d]))
    R = Vh.T @ D @ U.T
    t = c_to - R @ c_from
    return tf.homogeneous(R, t)


def fit_instrument_and_tool(T_base_flange: Tensor, p_tracker: Tensor, t_flange_probe: Tensor | None = None,
                            weights: Tensor | None = None, iterations: int = 50, tol: float = 1e-12
                            ) -> tuple[Tensor, Tensor, float]:
    """Tracker pose and lever arm for fixed geometry, by alternating closed-form steps.

    Model: ``p_tracker = R (R_f t + p_f) + t0`` with ``T_tracker_base = [R | t0]`` and lever arm ``t``.
    For fixed ``t`` the pose is a rigid fit; for a fixed pose ``t`` is linear least squares.
    Each step lowers the same cost, so the iteration converges; used as the initial
    value of the full estimation (and as the "nominal model" baseline).

    Args:
        T_base_flange: ``(N, 4, 4)`` flange poses of the model.
        p_tracker: ``(N, 3)`` measured probe positions.
        t_flange_probe: initial lever arm ``(3,)`` (default zero).

    Returns:
        ``T_tracker_base (4, 4)``, ``t_flange_probe (3,)`` and the final RMS residual [m].
    """
    Rf, pf = T_base_flange[:, :3, :3], T_base_flange[:, :3, 3]
    t = torch.zeros(3, dtype=pf.dtype) if t_flange_probe is None else t_flange_probe.clone()
    w = torch.ones(len(pf), dtype=pf.dtype) if weights is None else weights
    eye = torch.eye(3, dtype=pf.dtype)
    prev = None
    for _ in range(iterations):
        T = rigid_fit((Rf @ t) + pf, p_tracker, w)
        R = T[:3, :3]
        # for fixed R, translation t0 and lever arm t are jointly linear: p - R pf = t0 + R Rf t
        A = torch.cat([eye.expand(len(pf), 3, 3), R @ Rf], dim=-1)  # (N, 3, 6)
        b = p_tracker - pf @ R.T
        AtA = (w[:, None, None] * A.transpose(1, 2) @ A).sum(0)
        Atb = (w[:, None, None] * A.transpose(1, 2) @ b.unsqueeze(-1)).sum(0)
        x = torch.linalg.solve(AtA, Atb).squeeze(-1)
        t = x[3:]
        r = (Rf @ t + pf) @ R.T + x[:3] - p_tracker
        cost = float((w * r.square().sum(-1)).sum() / w.sum())
        if prev is not None and prev - cost <= tol * prev:
            break
        prev = cost
    T = rigid_fit((Rf @ t) + pf, p_tracker, w)
    r = tf.transform_points(T, (Rf @ t) + pf) - p_tracker
    return T, t, float((w * r.square().sum(-1)).sum().div(w.sum()).sqrt())
