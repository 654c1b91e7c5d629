"""Where does the residual structure live? One penalised smooth per candidate variable.

After a fit, the residuals ``r_i = p_i - f_i (N, 3)`` [m] (measured minus predicted, tracker frame) are
regressed, variable by variable, on a nonparametric one-dimensional model of each variable that can
carry an effect:

* ``q<j>``: joint j's angle. An error ``dq_j = g(q_j)`` of the joint reaches the probe through the
  joint's Jacobian column, ``r_i ~ J_j(q_i) g(q_ij)`` (a varying-coefficient model), so the basis is
  ``J_j(q_i) b_k(q_ij)`` with ``b_k`` the Fourier terms ``sin(k q), cos(k q)`` (k = 1..K) and the
  polynomial terms ``q, q^2`` (scale errors).
* ``tau<j>``: joint j's gravity torque [N m], same varying coefficient, cubic B-spline basis.
* ``flank<j>``: the gear flank joint j rests on (direction of motion along a trajectory, the sign of
  its gravity torque for static poses; none where that torque is of round-off size), same varying
  coefficient, one step column.
* ``t``, ``temperature``, ``x``, ``y``, ``z`` (probe position in the base frame): an additive Cartesian
  smooth ``r_i ~ g(v_i) in R^3``, cubic B-splines per coordinate.
* ``q<j>_t``: joint j's angle and time together, an error of the joint that changes over the campaign,
  ``dq_j = u(t) h(q_j)`` with ``u`` the time centred and scaled to ``[-1, 1]`` and ``h`` the constant (a
  joint offset drifting with time) plus the Fourier/polynomial terms of ``q<j>`` (a cyclic or scale error
  whose size changes); the plotted smooth is ``h``, the change of the joint error from the middle of the
  campaign to its end. Without it a product of a joint angle and time shows in neither one alone.

Each smooth is a ridge regression of the whitened residual on the whitened columns, with penalty
``lambda S`` (``S`` the identity for the Fourier/polynomial basis, second differences of the B-spline
coefficients for the splines) and ``lambda`` chosen by generalised cross-validation. Before it, the
columns are projected off what the current model already explains: the span of the fit's Jacobian
when given, else the instrument translation and every joint offset (what a geometric fit absorbs).

Test: with ``H`` the smoother's hat matrix (eigenvalues ``w``), the drop of the weighted sum of squares
``dSS = r^T (2H - H^2) r`` is, without the effect, ``sum_i v_i s^2 chi2_1`` with ``v = 2w - w^2``;
its upper tail is taken from the two-moment (Satterthwaite) approximation ``a chi2_b``,
``a = sum v^2 / sum v``, ``b = (sum v)^2 / sum v^2``, with ``s^2`` the residual variance of the smooth
fit. The effective degrees of freedom are ``trace H``. ``share`` is ``dSS`` over the residual's weighted
sum of squares. The ``K`` variables are tested at once: ``p_bonferroni = min(1, K p)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torchcal._threads import torch_threads
from torchcal.diagnose.score import chi2_sf_log10
from torchcal.effects import Context, MeasurementModel

Tensor = torch.Tensor
F64 = torch.float64

#: a joint that moves the probe by less than this (RMS over the poses, m/rad) cannot show an effect
MIN_LEVER = 1e-4
#: highest Fourier order of the joint-angle smooths
MAX_HARMONIC = 10
#: cubic B-spline basis size of the non-periodic smooths
N_SPLINE = 14
#: points of the plotted smooth
N_GRID = 200


@dataclass(frozen=True, eq=False)
class Variable:
    """One variable that can carry an effect.

    Attributes:
        name: short name: ``q3``, ``tau2``, ``flank2``, ``t``, ``temperature``, ``x``, ``y``, ``z``.
        label: axis label for plots, with the unit.
        kind: ``joint`` (acts through joint ``joint``'s Jacobian column) or ``cartesian`` (additive in
            the tracker frame).
        basis: ``fourier`` (angles), ``spline`` or ``step``.
        values: the variable at each pose ``(N,)``.
        joint: 1-based joint, or None for Cartesian variables.
        coef: joint variables: ``dp/dq_j`` in the tracker frame ``(N, 3)`` [m/rad]; else None.
        weight: product variables: the second factor at each pose ``(N,)`` (scaled time), multiplying
            every column; else None.
        parts: the variables a product is made of (``("q3", "t")``); empty for single variables.
    """

    name: str
    label: str
    kind: str
    basis: str
    values: Tensor
    joint: int | None = None
    coef: Tensor | None = None
    weight: Tensor | None = None
    parts: tuple[str, ...] = ()

    @property
    def variables(self) -> list[str]:
        """The variables the structure lives in: the parts of a product, else the name."""
        return list(self.parts) if self.parts else [self.name]


def _varies(x: Tensor, rel: float = 1e-9) -> bool:
    return bool(len(x) > 1) and float(x.std()) > rel * (1.0 + float(x.abs().max()))


def tracker_joint_jacobian(model: MeasurementModel, ctx: Context) -> Tensor:
    """``dp/dq`` of the probe in the tracker frame ``(N, 3, dof)`` [m/rad] at the model's joint angles."""
    with torch.no_grad():
        q = ctx.q + model.joint_offsets(ctx)
        _, J = model.robot.probe_jacobian(q)
        R = model.robot.T_tracker_base()[:3, :3]
        return R @ J


def candidate_variables(model: MeasurementModel, ctx: Context) -> list[Variable]:
    """The variables of the module docstring that vary over ``ctx``, for ``model``'s robot."""
    robot = model.robot
    Jt = tracker_joint_jacobian(model, ctx)
    lever = Jt.square().sum(1).mean(0).sqrt()
    with torch.no_grad():
        tau = robot.gravity_torques(ctx.q).detach() if robot.has_masses else None
        p_base = model.probe_in_base(ctx)
    out: list[Variable] = []
    u_t = None
    if ctx.t is not None and _varies(ctx.t):
        mid, half = 0.5 * float(ctx.t.max() + ctx.t.min()), 0.5 * float(ctx.t.max() - ctx.t.min())
        u_t = (ctx.t - mid) / half
        u_t = u_t - u_t.mean()  # centred: the product column is then (nearly) orthogonal to the joint's own
    products: list[Variable] = []
    for j in range(robot.dof):
        if float(lever[j]) < MIN_LEVER:
            continue
        G = Jt[:, :, j]
        q = ctx.q[:, j]
        if _varies(q) and robot.joint_types[j] == "prismatic":
            # a length [m]: no turn for harmonics to repeat over; a smooth of the reading (its forms: polynomials)
            out.append(Variable(f"q{j + 1}", f"q{j + 1} [m]", "joint", "spline", q, j + 1, G))
        elif _varies(q):
            out.append(Variable(f"q{j + 1}", f"q{j + 1} [rad]", "joint", "fourier", q, j + 1, G))
            if u_t is not None:
                products.append(
                    Variable(
                        f"q{j + 1}_t",
                        f"q{j + 1} [rad] (joint error change from mid-campaign to its end)",
                        "joint",
                        "fourier_const",
                        q,
                        j + 1,
                        G,
                        weight=u_t,
                        parts=(f"q{j + 1}", "t"),
                    )
                )
        if tau is not None and _varies(tau[:, j]):
            out.append(
                Variable(
                    f"tau{j + 1}", f"gravity torque at joint {j + 1} [N m]", "joint", "spline", tau[:, j], j + 1, G
                )
            )
        if ctx.direction is not None:
            s, what = ctx.direction[:, j], "motion direction"
        elif tau is not None and _varies(tau[:, j]):
            # a torque of round-off size (a wrist whose link masses sit on its axis) has a sign that is noise of
            # the arithmetic, and which poses it splits depends on the BLAS kernels; the candidates skip its
            # backlash for the same reason (:func:`torchcal.diagnose.candidates.candidates`)
            s, what = torch.sign(tau[:, j]), "sign of the gravity torque"
        else:
            s = None
        if s is not None:
            s = torch.where(s == 0, torch.ones_like(s), s)
            if not bool((s == s[0]).all()):
                out.append(
                    Variable(f"flank{j + 1}", f"loaded flank of joint {j + 1} ({what})", "joint", "step", s, j + 1, G)
                )
    for name, v, unit in (("t", ctx.t, "s"), ("temperature", ctx.temperature, "degC")):
        if v is not None and _varies(v):
            out.append(Variable(name, f"{name} [{unit}]", "cartesian", "spline", v))
    for c, name in enumerate("xyz"):
        if _varies(p_base[:, c]):
            out.append(Variable(name, f"probe {name} in the base frame [m]", "cartesian", "spline", p_base[:, c]))
    return out + products


# ------------------------------------------------------------------------------------------------ bases
def bspline_basis(x: Tensor, lo: float, hi: float, n: int = N_SPLINE) -> Tensor:
    """Cubic B-splines with equally spaced knots on ``[lo, hi]`` at ``x (M,)``: ``(M, n)``, rows sum to 1."""
    deg = 3
    inner = n - deg
    h = (hi - lo) / inner if hi > lo else 1.0
    knots = lo + h * torch.arange(-deg, inner + deg + 1, dtype=F64, device=x.device)
    xc = x.clamp(lo, hi)
    # Cox-de Boor on the full knot vector; the last interval is closed so x = hi gets its basis
    B = ((xc[:, None] >= knots[None, :-1]) & (xc[:, None] < knots[None, 1:])).to(F64)
    last = inner + deg - 1
    B[xc >= hi, :] = 0.0
    B[xc >= hi, last] = 1.0
    for d in range(1, deg + 1):
        left = (xc[:, None] - knots[None, : -(d + 1)]) / (knots[d:-1] - knots[: -(d + 1)])[None]
        right = (knots[None, d + 1 :] - xc[:, None]) / (knots[d + 1 :] - knots[1:-d])[None]
        B = left * B[:, :-1] + right * B[:, 1:]
    return B


def fourier_basis(q: Tensor, lo: float, hi: float, K: int = MAX_HARMONIC) -> Tensor:
    """``[u, u^2, sin(k q), cos(k q) for k = 1..K]`` with ``u`` the angle scaled to ``[-1, 1]``: ``(M, 2 + 2K)``."""
    mid, half = 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-12)
    u = (q - mid) / half
    k = torch.arange(1, K + 1, dtype=F64, device=q.device)
    arg = q[:, None] * k
    return torch.cat([u[:, None], u[:, None].square(), torch.sin(arg), torch.cos(arg)], dim=1)


def basis(var: Variable, x: Tensor) -> tuple[Tensor, Tensor]:
    """The variable's basis at ``x (M,)`` ``(M, p)`` and its penalty matrix ``(p, p)``."""
    lo, hi = float(var.values.min()), float(var.values.max())
    if var.basis in ("fourier", "fourier_const"):
        B = fourier_basis(x, lo, hi)
        if var.basis == "fourier_const":
            B = torch.cat([torch.ones_like(x)[:, None], B], dim=1)
        return B, torch.eye(B.shape[1], dtype=F64, device=B.device)
    if var.basis == "spline":
        B = bspline_basis(x, lo, hi)
        D = torch.diff(torch.eye(B.shape[1], dtype=F64, device=B.device), n=2, dim=0)
        return B, D.T @ D
    if var.basis == "step":
        return x[:, None].to(F64), torch.zeros(1, 1, dtype=F64, device=x.device)
    raise ValueError(f"unknown basis {var.basis!r}")


# ------------------------------------------------------------------------------------------- workspace
class Workspace:
    """Whitened residual and the projection off the current model's span, shared by all variables.

    Args:
        residuals: ``p_measured - p_predicted`` ``(N, 3)`` [m], tracker frame.
        W: per-pose whitening ``(N, 3, 3)`` (``L_i^-1``), or None with ``sigma``.
        sigma: per-axis standard deviations ``(N, 3)`` or a scalar [m] when ``W`` is None.
        jacobian: whitened Jacobian of the fit's residuals w.r.t. its free parameters ``(>= 3N, u)``; its
            first ``3N`` rows are used (prior pseudo-observations follow them). None: project off the
            instrument translation and the joint offsets of ``joint_coefs``.
        joint_coefs: ``dp/dq`` ``(N, 3, dof)`` for the default projection.
    """

    def __init__(
        self,
        residuals: Tensor,
        W: Tensor | None = None,
        sigma: Tensor | float | None = None,
        jacobian: Tensor | None = None,
        joint_coefs: Tensor | None = None,
    ):
        r = residuals.detach().to(F64)
        n = r.shape[0]
        if W is None:
            s = torch.as_tensor(1.0 if sigma is None else sigma, dtype=F64, device=r.device)
            s = s.expand(n, 3) if s.dim() < 2 else s
            W = torch.diag_embed(1.0 / s)
        self.W = W.detach().to(F64)
        self.N = n
        self.n = 3 * n
        self.r = (self.W @ r.unsqueeze(-1)).reshape(-1)
        if jacobian is not None:
            A = jacobian.detach()[: self.n]
        else:
            cols = [torch.eye(3, dtype=F64, device=self.W.device).expand(n, 3, 3)]
            if joint_coefs is not None:
                cols.append(joint_coefs.detach())
            A = (self.W @ torch.cat(cols, dim=2)).reshape(self.n, -1)
        A = A / A.norm(dim=0).clamp(min=1e-300)
        U, S, _ = torch.linalg.svd(A, full_matrices=False)
        self.Q = U[:, S > 1e-10 * S[0]]
        self.u = self.Q.shape[1]
        self.r = self.project(self.r[:, None])[:, 0]
        self.rss0 = float(self.r.square().sum())

    def project(self, X: Tensor) -> Tensor:
        """``X (3N, p)`` minus its part in the model's span (twice, for round-off)."""
        for _ in range(2):
            X = X - self.Q @ (self.Q.T @ X)
        return X

    def columns(self, var: Variable, B: Tensor) -> Tensor:
        """Whitened, projected design ``(3N, p)`` (joint) or ``(3N, 3p)`` (Cartesian) of basis ``B (N, p)``."""
        if var.kind == "joint":
            X = var.coef[:, :, None] * B[:, None, :]  # (N, 3, p)
            if var.weight is not None:
                X = X * var.weight[:, None, None]
        else:
            p = B.shape[1]
            X = torch.zeros(self.N, 3, 3 * p, dtype=F64, device=B.device)
            for c in range(3):
                X[:, c, c * p : (c + 1) * p] = B
        X = (self.W @ X).reshape(self.n, -1)
        return self.project(X)


# ------------------------------------------------------------------------------------------- the smooth
@dataclass
class Localisation:
    """The evidence that the residual depends on one variable (module docstring).

    Attributes:
        variable: the variable.
        edf: effective degrees of freedom of the smooth (trace of the hat matrix).
        statistic: ``dSS / s^2``.
        ref_scale, ref_dof: ``a`` and ``b`` of the reference ``a chi2_b``.
        p_value, log10_p, p_bonferroni: upper tail, its log10, Bonferroni over the ``n_variables``.
        share: fraction of the residual's weighted sum of squares the smooth explains.
        lam: the GCV penalty weight.
        grid: ``(G,)`` values of the variable to plot at.
        smooth: the fitted function on the grid: ``(G,)`` [rad] for joint variables, ``(G, 3)`` [m]
            (tracker frame) for Cartesian ones.
        smooth_se: its pointwise standard error, same shape.
        smooth_se_shape: the pointwise standard error of the smooth less its mean over the grid (its shape), same
            shape; None where not computed.
    """

    variable: Variable
    edf: float
    statistic: float
    ref_scale: float
    ref_dof: float
    p_value: float
    log10_p: float
    p_bonferroni: float
    share: float
    lam: float
    n_variables: int
    grid: Tensor = field(repr=False)
    smooth: Tensor = field(repr=False)
    smooth_se: Tensor = field(repr=False)
    smooth_se_shape: Tensor | None = field(default=None, repr=False)

    @property
    def name(self) -> str:
        return self.variable.name

    def significant(self, alpha: float) -> bool:
        return self.p_bonferroni < alpha

    def to_dict(self, with_smooth: bool = False) -> dict:
        v = self.variable
        out = {
            "variable": v.name,
            "variables": v.variables,
            "label": v.label,
            "kind": v.kind,
            "joint": v.joint,
            "basis": v.basis,
            "test": "penalised smooth (GCV), dSS against a scaled chi-square (Satterthwaite)",
            "edf": self.edf,
            "statistic": self.statistic,
            "ref_scale": self.ref_scale,
            "ref_dof": self.ref_dof,
            "p_value": self.p_value,
            "log10_p": self.log10_p,
            "p_bonferroni": self.p_bonferroni,
            "n_variables": self.n_variables,
            "share": self.share,
            "lambda": self.lam,
        }
        if with_smooth:
            out.update(grid=self.grid.tolist(), smooth=self.smooth.tolist(), smooth_se=self.smooth_se.tolist())
        return out


def fit_smooth(X: Tensor, r: Tensor, S: Tensor, n_eff: int, n_lambda: int = 41) -> dict:
    """Penalised least squares ``min |r - X b|^2 + lambda b^T S b`` with ``lambda`` by GCV.

    Args:
        X: design ``(n, p)``; r: response ``(n,)``; S: penalty ``(p, p)``.
        n_eff: residual degrees of freedom before the smooth (observations minus the model's parameters).

    Returns:
        ``beta``, ``lam``, ``edf``, ``rss``, ``v`` (eigenvalues of ``2H - H^2``), ``cov_unscaled``
        (``M^-1 A M^-1``, times ``s^2`` the covariance of ``beta``), ``s2``.
    """
    A = X.T @ X
    b = X.T @ r
    rr = float(r @ r)
    p = A.shape[0]
    eye = torch.eye(p, dtype=F64, device=A.device)
    trA = float(torch.trace(A))
    jitter = 1e-10 * (trA / p if trA > 0 else 1.0)
    if float(S.abs().max()) == 0.0:
        lams = torch.zeros(1, dtype=F64, device=A.device)
    else:
        scale = trA / max(float(torch.trace(S)), 1e-300)
        lams = scale * torch.logspace(-7, 3, n_lambda, dtype=F64, device=A.device)
    M = A[None] + lams[:, None, None] * S[None] + jitter * eye[None]
    L, info = torch.linalg.cholesky_ex(M)
    ok = info == 0
    beta = torch.cholesky_solve(b[None, :, None].expand(len(lams), p, 1), L)[..., 0]
    MinvA = torch.cholesky_solve(A[None].expand(len(lams), p, p), L)
    edf = MinvA.diagonal(dim1=-2, dim2=-1).sum(-1)
    rss = rr - 2 * beta @ b + ((beta @ A) * beta).sum(-1)
    rss = rss.clamp(min=1e-300)
    gcv = rss / (n_eff - edf).clamp(min=1.0).square()
    gcv = torch.where(ok, gcv, torch.full_like(gcv, float("inf")))
    i = int(torch.argmin(gcv))
    Li = L[i]
    # eigenvalues of H: those of L^-1 A L^-T (symmetric, similar to M^-1 A)
    Linv_A = torch.linalg.solve_triangular(Li, A, upper=False)
    w = torch.linalg.eigvalsh(torch.linalg.solve_triangular(Li, Linv_A.T, upper=False)).clamp(0.0, 1.0)
    Minv = torch.cholesky_inverse(Li)
    return {
        "beta": beta[i],
        "lam": float(lams[i]),
        "edf": float(edf[i]),
        "rss": float(rss[i]),
        "v": 2 * w - w.square(),
        "cov_unscaled": Minv @ A @ Minv,
        "s2": float(rss[i]) / max(n_eff - float(edf[i]), 1.0),
    }


def satterthwaite_tail(stat: float, v: Tensor) -> tuple[float, float, float, float]:
    """Upper tail of ``sum_i v_i chi2_1`` at ``stat`` by ``a chi2_b``: ``(p, log10 p, a, b)``."""
    s1, s2 = float(v.sum()), float(v.square().sum())
    if s1 <= 1e-12:
        return 1.0, 0.0, 0.0, 0.0
    a, b = s2 / s1, s1 * s1 / s2
    p, l10 = chi2_sf_log10(stat / a, b) if stat > 0 else (1.0, 0.0)
    return p, l10, a, b


def localise_variable(ws: Workspace, var: Variable, n_variables: int = 1) -> Localisation:
    """The smooth of the residual in ``var`` and its test (module docstring)."""
    B, S = basis(var, var.values)
    if var.kind == "cartesian":
        S = torch.block_diag(S, S, S)
    X = ws.columns(var, B)
    n_eff = ws.n - ws.u
    fit = fit_smooth(X, ws.r, S, n_eff)
    dss = max(ws.rss0 - fit["rss"], 0.0)
    stat = dss / fit["s2"] if fit["s2"] > 0 else float("inf")
    p, l10, a, b = satterthwaite_tail(stat, fit["v"])
    lo, hi = float(var.values.min()), float(var.values.max())
    grid = torch.linspace(lo, hi, N_GRID, dtype=F64) if var.basis != "step" else torch.tensor([-1.0, 1.0], dtype=F64)
    grid = grid.to(var.values.device)
    Bg, _ = basis(var, grid)
    cov = fit["s2"] * fit["cov_unscaled"]
    beta = fit["beta"]
    # the shape's standard error: that of the smooth less its mean over the grid, where a level the model's own span
    # carries (a joint offset) leaves the pointwise one wide everywhere and says nothing of the shape
    Bc = Bg - Bg.mean(0, keepdim=True)
    if var.kind == "cartesian":
        pb = Bg.shape[1]
        f = torch.stack([Bg @ beta[c * pb : (c + 1) * pb] for c in range(3)], dim=1)
        blocks = [cov[c * pb : (c + 1) * pb, c * pb : (c + 1) * pb] for c in range(3)]
        se = torch.stack([((Bg @ C) * Bg).sum(1).clamp(min=0).sqrt() for C in blocks], dim=1)
        se_shape = torch.stack([((Bc @ C) * Bc).sum(1).clamp(min=0).sqrt() for C in blocks], dim=1)
    else:
        f = Bg @ beta
        se = ((Bg @ cov) * Bg).sum(1).clamp(min=0).sqrt()
        se_shape = ((Bc @ cov) * Bc).sum(1).clamp(min=0).sqrt()
    return Localisation(
        var,
        fit["edf"],
        stat,
        a,
        b,
        p,
        l10,
        min(1.0, n_variables * p),
        dss / ws.rss0 if ws.rss0 > 0 else 0.0,
        fit["lam"],
        n_variables,
        grid,
        f,
        se,
        se_shape,
    )


def workspace(
    model: MeasurementModel,
    ctx: Context,
    residuals: Tensor,
    *,
    W: Tensor | None = None,
    sigma: Tensor | float | None = None,
    jacobian: Tensor | None = None,
) -> Workspace:
    """A :class:`Workspace` for ``model``'s residuals at ``ctx``: what :func:`localise` and the form selection test.

    Args:
        model: the fitted measurement model.
        ctx: the fitted samples.
        residuals: ``p_measured - p_predicted`` ``(N, 3)`` [m], tracker frame.
        W: whitening ``(N, 3, 3)`` of the fit (e.g. :attr:`Fit.whitening`), or ``sigma`` ``(N, 3)``/scalar [m].
        jacobian: the fit's whitened Jacobian ``(>= 3N, u)`` (:attr:`LMResult.jacobian`); recommended, since
            without it only the instrument translation and the joint offsets are projected off.
    """
    with torch_threads(1):  # small kernels (a 3N x u SVD): one thread, as the localisation after it
        coefs = None if jacobian is not None else tracker_joint_jacobian(model, ctx)
        return Workspace(residuals, W=W, sigma=sigma, jacobian=jacobian, joint_coefs=coefs)


def localise(
    model: MeasurementModel, ctx: Context, ws: Workspace, variables: list[Variable] | None = None
) -> list[Localisation]:
    """Test the residual in ``ws`` against every candidate variable (module docstring); strongest first.

    Args:
        model: the fitted measurement model (its Jacobians and gravity torques define the variables).
        ctx: the fitted samples.
        ws: the fit's :func:`workspace` (the form selection at the strongest variable reuses it).
        variables: defaults to :func:`candidate_variables`.
    """
    with torch_threads(1):
        variables = candidate_variables(model, ctx) if variables is None else variables
        out = [localise_variable(ws, v, len(variables)) for v in variables]
    out.sort(key=lambda loc: (loc.log10_p, -loc.share))
    return out


def unexplained(locs: list[Localisation], alpha: float = 0.01, with_smooth: bool = True) -> list[dict]:
    """The significant variables (Bonferroni level ``alpha``) as report entries, strongest first: where the
    residual still has structure, its share and the smooth to plot (for ``report.json``'s ``unexplained``)."""
    return [loc.to_dict(with_smooth=with_smooth) for loc in locs if loc.significant(alpha)]


def family_wise_p(locs: list[Localisation]) -> float:
    """The smallest Bonferroni-corrected p-value (1.0 for an empty list)."""
    return min((loc.p_bonferroni for loc in locs), default=1.0)


__all__ = [
    "Localisation",
    "Variable",
    "Workspace",
    "bspline_basis",
    "candidate_variables",
    "family_wise_p",
    "fit_smooth",
    "fourier_basis",
    "localise",
    "localise_variable",
    "satterthwaite_tail",
    "tracker_joint_jacobian",
    "unexplained",
    "workspace",
    "MAX_HARMONIC",
    "N_SPLINE",
]
