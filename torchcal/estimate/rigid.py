"""Closed-form rigid fit between two point sets (Kabsch / Horn), float64, and its robust variant.

The robust variant (:func:`robust_instrument_and_tool`) survives gross errors in the measured points:
rows shifted by centimetres, or rows in millimetres among rows in metres (1000 times too far).
"""

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


def fit_instrument_and_tool(
    T_base_flange: Tensor,
    p_tracker: Tensor,
    t_flange_probe: Tensor | None = None,
    weights: Tensor | None = None,
    iterations: int = 50,
    tol: float = 1e-12,
    robust: bool = False,
    lever_prior: tuple[Tensor, float] | None = None,
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
        weights: ``(N,)`` non-negative row weights (default equal).
        robust: down-weight gross errors (:func:`robust_instrument_and_tool`); the RMS residual
            is then that of the rows kept with positive weight.
        lever_prior: ``(centre (3,) [m], ratio)``: the lever arm's prior, ``t ~ N(centre, sigma_prior^2)`` with
            ``ratio = sigma_noise^2 / sigma_prior^2`` (a unit row weight per ``sigma_noise``): the lever-arm step
            becomes a MAP (ridge) step, so a lever arm the poses do not fix (a tool axis that hardly turns) stays
            near its centre instead of wherever the round-off sends it. Not with ``robust``.

    Returns:
        ``T_tracker_base (4, 4)``, ``t_flange_probe (3,)`` and the final RMS residual [m].
    """
    if robust:
        T, t, rms, _ = robust_instrument_and_tool(T_base_flange, p_tracker, t_flange_probe, weights=weights)
        return T, t, rms
    Rf, pf = T_base_flange[:, :3, :3], T_base_flange[:, :3, 3]
    t = torch.zeros(3, dtype=pf.dtype, device=pf.device) if t_flange_probe is None else t_flange_probe.clone()
    w = torch.ones(len(pf), dtype=pf.dtype, device=pf.device) if weights is None else weights
    eye = torch.eye(3, dtype=pf.dtype, device=pf.device)
    prev = None
    for _ in range(iterations):
        T = rigid_fit((Rf @ t) + pf, p_tracker, w)
        R = T[:3, :3]
        # for fixed R, translation t0 and lever arm t are jointly linear: p - R pf = t0 + R Rf t
        A = torch.cat([eye.expand(len(pf), 3, 3), R @ Rf], dim=-1)  # (N, 3, 6)
        b = p_tracker - pf @ R.T
        AtA = (w[:, None, None] * A.transpose(1, 2) @ A).sum(0)
        Atb = (w[:, None, None] * A.transpose(1, 2) @ b.unsqueeze(-1)).sum(0)
        if lever_prior is not None:
            centre, ratio = lever_prior
            AtA[3:, 3:] += float(ratio) * eye
            Atb[3:, 0] += float(ratio) * centre.to(Atb)
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


#: median of the chi distribution with 3 degrees of freedom (the norm of a standard normal 3-vector)
_CHI3_MEDIAN = 1.5381722544
#: Tukey's cut-off on ``|r_i| / s``: the 0.9999 quantile of chi(3), so a row of a correct model is cut
#: with probability 1e-4, and every row past about 3 times the median residual gets weight zero
TUKEY_C = 4.7
#: the start's distance gate (step 1 of :func:`robust_instrument_and_tool`), in multiples of the median distance
#: of the measured points from their median point
GATE = 10.0
#: reweighting rounds at most (the weights settle in a few; rows come back when they fit again)
ROUNDS = 30


def robust_instrument_and_tool(
    T_base_flange: Tensor,
    p_tracker: Tensor,
    t_flange_probe: Tensor | None = None,
    weights: Tensor | None = None,
) -> tuple[Tensor, Tensor, float, Tensor]:
    """Tracker pose and lever arm that gross errors in ``p_tracker`` do not move.

    1. Gate: a row farther from the coordinate-wise median of the measured points than :data:`GATE`
       times the median such distance (a row in millimetres among rows in metres lies 1000 times
       too far) takes no part in the start; a robot's workspace is not that lopsided.
    2. Start: the least-squares fit (:func:`fit_instrument_and_tool`) on the gated rows.
    3. Iteratively reweighted least squares with Tukey's biweight on the residual norm
       ``u_i = |r_i| / s``: ``w_i = (1 - (u_i / c)^2)^2`` for ``u_i < c``, else 0, with the robust
       scale ``s = median |r_i| / median(chi_3)`` (a residual norm of a 3-vector of equal normal
       errors follows ``s * chi_3``) and ``c = TUKEY_C``; rows come back when they fit again.

    With the nominal geometry the residuals hold the geometric errors (systematic, not normal);
    the cut-off then lies at about three times the median residual, far below a gross error of
    centimetres and far above what a geometric error of a tenth of a millimetre leaves.

    Args:
        T_base_flange: ``(N, 4, 4)`` flange poses of the model.
        p_tracker: ``(N, 3)`` measured probe positions [m].
        t_flange_probe: initial lever arm ``(3,)`` [m] (default zero).
        weights: ``(N,)`` prior non-negative row weights (0 excludes a row), default equal.

    Returns:
        ``T_tracker_base (4, 4)``, ``t_flange_probe (3,)``, the RMS residual of the rows with positive
        weight [m] and the final robust weights ``(N,)`` in [0, 1] (0: a gross error).

    Raises:
        EstimationError: when fewer than 3 rows survive, or they do not fix a rotation.
    """
    T_base_flange, p_tracker = T_base_flange.detach(), p_tracker.detach()
    n = len(p_tracker)
    w0 = torch.ones(n, dtype=p_tracker.dtype, device=p_tracker.device) if weights is None else weights.to(p_tracker)
    centre = p_tracker.median(dim=0).values
    d = (p_tracker - centre).norm(dim=-1)
    scale_d = float(d[w0 > 0].median()) if bool((w0 > 0).any()) else 0.0
    w = w0 * (d <= GATE * max(scale_d, 1e-9)).to(w0.dtype)
    if int((w > 0).sum()) < 3:
        raise EstimationError(f"robust rigid fit: only {int((w > 0).sum())} of {n} rows are usable (3 needed)")
    T, t, _ = fit_instrument_and_tool(T_base_flange, p_tracker, t_flange_probe, weights=w)
    pf = T_base_flange[:, :3, 3] + T_base_flange[:, :3, :3] @ t
    for _ in range(ROUNDS):
        r = (tf.transform_points(T, pf) - p_tracker).norm(dim=-1)
        s = float(r[w0 > 0].median()) / _CHI3_MEDIAN
        u = r / max(s, 1e-15)
        w_new = w0 * torch.where(u < TUKEY_C, (1.0 - (u / TUKEY_C).square()).square(), torch.zeros_like(u))
        if int((w_new > 0).sum()) < 3:
            break
        change = float((w_new - w).abs().max())
        w = w_new
        T, t, _ = fit_instrument_and_tool(T_base_flange, p_tracker, t, weights=w)
        pf = T_base_flange[:, :3, 3] + T_base_flange[:, :3, :3] @ t
        if change < 1e-6:
            break
    r = tf.transform_points(T, pf) - p_tracker
    k = w > 0
    return T, t, float(r[k].square().sum(-1).mean().sqrt()), w
