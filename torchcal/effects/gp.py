"""A scalable Gaussian-process residual model with per-joint structure: the ``learned`` effect.

The correction in the robot base frame is the posterior mean of a Gaussian process over the
inputs ``x`` (the joint angles [rad], optionally ``t`` and ``temperature``, standardised) with the
kernel

    k(x, x') = sum_j s_j^2 k_j(x_j, x'_j)  +  s_0^2 exp(-1/2 sum_j ((x_j - x'_j) / L_j)^2),

an additive part (one 1-D kernel per variable, each with its own variance ``s_j^2`` and length
scale ``l_j``; squared-exponential, or periodic in the joint angle ``exp(-2 sin^2((q - q')/2) / l^2)``
whose period is one revolution, the period of a transmission harmonic) plus a full-joint
squared-exponential with one length scale per variable (automatic relevance determination).
A structure that lives on one joint (a harmonic on a wrist joint) gets a large variance on that
joint's 1-D component; a short-range structure over all joints is left to the ARD component.

The three Cartesian outputs are independent processes that share the kernel; each output is
standardised by its own RMS before the fit, so the predictive standard deviation is per output.
All hyperparameters (variances, length scales, the noise variance) are fitted by maximising the
evidence with L-BFGS (gradients through a Cholesky in float64), not chosen from a grid.

Scale: the sparse variational bound of Titsias (2009) with ``m`` inducing inputs ``Z`` (SGPR):

    log p(y) >= log N(y | 0, Q + sigma^2 I) - tr(K - Q) / (2 sigma^2),   Q = K_fu K_uu^-1 K_uf,

costs ``O(n m^2)`` time and ``O(m^2 + m b)`` memory when the ``n`` training rows are streamed in
blocks of ``b``. The hyperparameters are fitted on a seeded subset (at most ``max_fit`` rows with
``m_fit`` inducing inputs; by default the subset's exact marginal likelihood, with its gradient in
closed form): the evidence of real residuals has several local maxima, so a few seeded starting points
run a few iterations each on the subset's first ``coarse_rows`` rows, the best goes on, and a last
few iterations use the whole subset. A sparse bound with few inducing inputs would bias the fit
towards long length scales where the structure is short-range (as on the UR10), hence the exact
evidence on fewer rows. The posterior then uses every training row with ``max_inducing`` inducing
inputs placed by k-means in the metric of the fitted ARD length scales. With at least as
many inducing inputs as training rows the inducing inputs are the rows themselves and the bound
and the posterior are those of the exact (dense) Gaussian process. Up to ``max_exact`` rows the
posterior is the exact one, from a single Cholesky factor of ``K + sigma^2 I`` (``n^3 / 3``
operations, cheaper than the sparse posterior's ``2 n m^2`` up to about ``2.4 m`` rows).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import torch

from torchcal import _lbfgs
from torchcal._threads import torch_threads
from torchcal._torch import plain, same_version, version_key
from torchcal.effects.base import Context, Effect
from torchcal.errors import EstimationError, OptionError, ShapeError

Tensor = torch.Tensor
F64 = torch.float64

ADDITIVE_FORMS = ("rbf", "periodic")
EXTRA_INPUTS = ("t", "temperature")
_JITTER = 1e-8  # relative to the prior variance: keeps K_uu positive definite in float64
_BLOCK = 256  # rows per block when streaming K_uf (memory O(m * block * variables))
#: elements of the kernel's per-variable temporaries (:func:`_kernel` without gradient): 1 MB, cache-sized
_KERNEL_CHUNK = 131_072
#: the kernel's exponents are raised to this before ``exp``: torch's vectorised float64 ``exp`` leaves the arguments
#: whose result is subnormal or zero (below about -708.4) to a scalar path 10 to 60 times slower, and most pairs of
#: poses are that far apart under short length scales; ``exp(-708)`` = 3.3e-308 stands for them, a change of the
#: kernel by at most 3.3e-308 of its variance
_EXP_FLOOR = -708.0
#: Python threads that compute the posterior's row blocks side by side (kernel, triangular solve and products: large
#: torch ops on one torch thread each, which release the GIL); the blocks are summed in order, so the posterior is
#: the same for any number of them
BLOCK_WORKERS = 2
#: Python threads that run the evidence fit's random starts side by side (each one torch thread)
RESTART_WORKERS = 2


@dataclass
class GPSettings:
    """How :func:`fit_gp_correction` fits (defaults suit 100 to 50,000 training poses).

    Attributes:
        additive: form of the 1-D components on the joints, ``"rbf"`` or ``"periodic"`` (period 2 pi).
        extras: extra inputs read from the context, a subset of ``("t", "temperature")``.
        ard: include the full-joint ARD component.
        max_inducing: inducing inputs of the posterior; with ``n <= max_inducing`` the GP is exact.
        max_exact: with at most this many training rows the posterior is the exact GP from one dense Cholesky
            factor of ``K + sigma^2 I`` (``n^3 / 3`` operations against the sparse posterior's ``2 n m^2``: cheaper
            up to about ``2.4 m`` rows); 0: always the sparse posterior beyond ``max_inducing``.
        max_fit: training rows used to fit the hyperparameters (a seeded subset beyond that).
        m_fit: inducing inputs while fitting the hyperparameters (exact when ``max_fit <= m_fit``).
        iterations: L-BFGS iterations on the evidence.
        restarts: starting points of the evidence fit: the default one and ``restarts - 1`` seeded random ones;
            each runs ``restart_iterations`` L-BFGS iterations, and the best bound goes on for ``iterations``
            (the evidence has several local maxima on real residuals; one start lands in any of them).
        restart_iterations: L-BFGS iterations of each start before the best is chosen.
        coarse_rows: with more fitting rows than this, the restarts and ``iterations`` run on this many of them
            first, and ``refine_iterations`` on all of them follow.
        refine_iterations: L-BFGS iterations on all fitting rows after the coarse stage.
        warm_tolerance: a warm refit's L-BFGS stops at the first iteration that raises the log evidence of the
            fitting rows by less than this [nats] (its own resolution: hyperparameters whose evidence differs by a
            Bayes factor under ``e^0.5`` are equally supported); the fits from scratch run all their iterations.
            0, the default, runs every iteration: a warm refit's hyperparameters decide the pruning of named
            effects (a one-sided paired test at the validation level), and a refit stopped early moves close
            decisions there.
        kmeans_iterations: Lloyd iterations placing the inducing inputs.
        threads: torch threads while fitting (restored afterwards).
        seed: seeds the subsets and the k-means initialisation.
    """

    additive: str = "rbf"
    extras: tuple[str, ...] = ()
    ard: bool = True
    max_inducing: int = 1500
    max_exact: int = 3000
    max_fit: int = 800
    m_fit: int = 800
    iterations: int = 30
    restarts: int = 4
    restart_iterations: int = 15
    coarse_rows: int = 500
    refine_iterations: int = 15
    warm_tolerance: float = 0.0
    kmeans_iterations: int = 10
    threads: int = 1
    seed: int = 0

    def __post_init__(self):
        if self.additive not in ADDITIVE_FORMS:
            raise OptionError(f"additive form '{self.additive}' is not one of {', '.join(ADDITIVE_FORMS)}")
        bad = [e for e in self.extras if e not in EXTRA_INPUTS]
        if bad:
            raise OptionError(f"extra GP inputs {bad} are not among {', '.join(EXTRA_INPUTS)}")
        counts = (self.max_inducing, self.max_fit, self.m_fit, self.iterations, self.restarts, self.restart_iterations)
        if min(counts) < 1 or self.max_exact < 0:
            raise OptionError(
                "max_inducing, max_fit, m_fit, iterations, restarts and restart_iterations must be >= 1 and "
                f"max_exact >= 0, got {self.max_inducing}, {self.max_fit}, {self.m_fit}, {self.iterations}, "
                f"{self.restarts}, {self.restart_iterations}, {self.max_exact}"
            )


# ----------------------------------------------------------------------------- kernel


def _dist(x: Tensor, z: Tensor, periodic: Tensor) -> Tensor:
    """Per-variable squared distances ``(n, m, d)``: ``(x_j - z_j)^2``, or ``4 sin^2((x_j - z_j) / 2)`` where periodic.

    They do not depend on the hyperparameters, so the evidence fit computes them once.
    """
    return _squared(x.unsqueeze(1) - z.unsqueeze(0), periodic)


def _squared(diff: Tensor, periodic: Tensor) -> Tensor:
    """``diff^2``, or ``4 sin^2(diff / 2)`` in the periodic variables (the last dimension)."""
    if bool(periodic.any()):
        diff = torch.where(periodic, 2.0 * torch.sin(0.5 * diff), diff)
    return diff.square()


def _kern(D: Tensor, h: dict[str, Tensor], ard: bool) -> Tensor:
    """``k`` of the module docstring ``(n, m)`` from the distances of :func:`_dist`."""
    K = torch.exp(D * (-0.5 / h["add_len"].square())) @ h["add_var"]
    if ard:
        K = K + h["ard_var"] * torch.exp(-0.5 * (D @ (1.0 / h["ard_len"].square())))
    return K


def _kernel(x: Tensor, z: Tensor, h: dict[str, Tensor], periodic: Tensor, ard: bool) -> Tensor:
    """``k(x, z)`` ``(n, m)`` of the module docstring; ``h`` holds the positive hyperparameters.

    Where the additive form is periodic the ARD component uses the same periodic distance (a product of
    periodic kernels, positive definite as well).
    """
    if torch.is_grad_enabled() and any(t.requires_grad for t in (x, z, *h.values())):
        return _kern(_dist(x, z, periodic), h, ard)
    # no gradient (posterior, prediction): one variable at a time and in place, on chunks of rows whose
    # temporaries stay in the processor's cache (every variable makes five passes over them, which out of cache
    # wait on memory), so that streaming many blocks does not fragment the heap
    n, m = len(x), len(z)
    K = torch.zeros(n, m, dtype=x.dtype, device=x.device)
    add_c = [float(-0.5 / v.square()) for v in h["add_len"]]
    add_v = [float(v) for v in h["add_var"]]
    ard_c = [float(1.0 / v.square()) for v in h["ard_len"]] if ard else []
    per = [bool(v) for v in periodic]
    rows = max(1, _KERNEL_CHUNK // max(m, 1))
    d = torch.empty(min(rows, n), m, dtype=x.dtype, device=x.device)
    S = torch.empty_like(d) if ard else None
    for r in range(0, n, rows):
        Kr = K[r : r + rows]
        dr = d[: len(Kr)]
        if ard:
            Sr = S[: len(Kr)].zero_()
        for j in range(x.shape[1]):
            torch.sub(x[r : r + rows, j : j + 1], z[:, j].unsqueeze(0), out=dr)
            if per[j]:
                torch.sin(dr.mul_(0.5), out=dr).mul_(2.0)
            dr.square_()
            if ard:
                Sr.add_(dr, alpha=ard_c[j])
            Kr.add_(dr.mul_(add_c[j]).clamp_(min=_EXP_FLOOR).exp_(), alpha=add_v[j])
        if ard:
            Kr.add_(Sr.mul_(-0.5).clamp_(min=_EXP_FLOOR).exp_(), alpha=float(h["ard_var"]))
    return K


def _mean_and_input_jacobian(
    x: Tensor, z: Tensor, W: Tensor, h: dict[str, Tensor], periodic: Tensor, ard: bool
) -> tuple[Tensor, Tensor]:
    """``k(x, z) @ W`` ``(n, p)`` and its derivative by the inputs ``x (n, d)``, ``(n, p, d)``, in closed form.

    With ``s_j`` the squared distance of variable ``j`` (:func:`_squared`), ``E_j = exp(-s_j / (2 l_j^2))`` and
    ``A = exp(-sum_j s_j / (2 L_j^2))``: ``dk/dx_j = (-s_add_j^2 E_j / (2 l_j^2) - s_0^2 A / (2 L_j^2)) ds_j/dx_j``,
    ``ds_j/dx_j = 2 (x_j - z_j)``, or ``2 sin(x_j - z_j)`` where periodic. The kernel is summed as :func:`_kernel`
    sums it (the same values), from the same exponentials. Row blocks keep the temporaries ``O(block * m * d)``:
    reverse-mode autograd through :func:`_kern` instead holds ``(n, m, d)`` temporaries for every backward pass, and a
    solve that takes several passes over thousands of rows spends its time there.
    """
    n, m, d = len(x), len(z), x.shape[1]
    mean = torch.empty(n, W.shape[1], dtype=x.dtype, device=x.device)
    J = torch.empty(n, W.shape[1], d, dtype=x.dtype, device=x.device)
    rows = max(1, _KERNEL_CHUNK // 4 // max(m, 1))
    E, G = torch.empty(2, d, min(rows, n), m, dtype=x.dtype, device=x.device)  # per variable, (_exponentials)
    K, S = torch.empty(2, min(rows, n), m, dtype=x.dtype, device=x.device)
    coef = _jacobian_coefficients(h, periodic, ard)
    zT = z.T.contiguous()
    for r in range(0, n, rows):
        xr = x[r : r + rows]
        b = len(xr)
        Er, Gr, Kr, Sr = E[:, :b], G[:, :b], K[:b], S[:b]
        _exponentials(xr, zT, coef, Er, Gr, Kr.zero_(), Sr.zero_(), ard)
        mean[r : r + b] = Kr @ W
        J[r : r + b] = (Gr.reshape(d * b, m) @ W).reshape(d, b, -1).permute(1, 2, 0)
    return mean, J


def _jacobian_coefficients(h: dict[str, Tensor], periodic: Tensor, ard: bool) -> dict[str, list]:
    """The hyperparameters as Python numbers, per variable, for :func:`_exponentials`."""
    c = -0.5 / h["add_len"].square()
    e = 1.0 / h["ard_len"].square()
    b = float(h["ard_var"]) if ard else 0.0
    return {
        "c": [float(v) for v in c],
        "a": [float(v) for v in h["add_var"]],
        "ac": [float(v) for v in h["add_var"] * c],
        "e": [float(v) for v in e],
        "be": [0.5 * b * float(v) for v in e],
        "b": [b],
        "periodic": [bool(v) for v in periodic],
    }


def _exponentials(
    xr: Tensor, zT: Tensor, coef: dict[str, list], E: Tensor, G: Tensor, K: Tensor, S: Tensor, ard: bool
) -> None:
    """One row block of :func:`_mean_and_input_jacobian`, in place: the kernel ``K (b, m)`` and ``dk/dx_j`` in
    ``G (d, b, m)``; ``E (d, b, m)`` and ``S (b, m)`` are work space."""
    for j, per in enumerate(coef["periodic"]):
        Ej, Gj = E[j], G[j]
        torch.sub(xr[:, j : j + 1], zT[j].unsqueeze(0), out=Ej)
        if per:  # ds/dx = 2 sin(diff), s = (2 sin(diff / 2))^2
            torch.sin(Ej, out=Gj).mul_(2.0)
            torch.sin(Ej.mul_(0.5), out=Ej).mul_(2.0)
        else:
            torch.mul(Ej, 2.0, out=Gj)
        Ej.square_()
        if ard:
            S.add_(Ej, alpha=coef["e"][j])
        K.add_(Ej.mul_(coef["c"][j]).clamp_(min=_EXP_FLOOR).exp_(), alpha=coef["a"][j])
    if ard:
        K.add_(S.mul_(-0.5).clamp_(min=_EXP_FLOOR).exp_(), alpha=coef["b"][0])
    for j in range(len(coef["periodic"])):
        t = E[j].mul_(coef["ac"][j])
        if ard:
            t.sub_(S, alpha=coef["be"][j])
        G[j].mul_(t)


class _MeanByInputs(torch.autograd.Function):
    """The posterior mean ``(N, 3)`` [m] at standardised inputs ``x``, whose derivative by ``x`` is taken in closed
    form (:func:`_mean_and_input_jacobian`, computed with the mean) instead of by autograd through the kernel's
    temporaries; the value is the mean without gradient (:meth:`GPCorrection.predict`) to rounding. Once
    differentiable: no caller needs the second derivative."""

    @staticmethod
    def forward(ctx, x: Tensor, eff: GPCorrection) -> Tensor:
        with torch.no_grad():
            mean, J = _mean_and_input_jacobian(x, eff.inducing, eff.weights, eff.hyper(), eff.periodic, eff.ard)
        ctx.save_for_backward(J.mul_(eff.y_scale.unsqueeze(-1)))
        return mean * eff.y_scale + eff.y_mean

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        (J,) = ctx.saved_tensors
        return (grad.unsqueeze(-2) @ J).squeeze(-2), None


def _prior_var(h: dict[str, Tensor], ard: bool) -> Tensor:
    """``k(x, x)``, the same for every ``x`` (stationary components)."""
    return h["add_var"].sum() + (h["ard_var"] if ard else 0.0)


def _chol(K: Tensor, jitter: Tensor) -> Tensor:
    """Cholesky factor of ``K + jitter I``; where that fails (near-duplicate inducing inputs, or length scales so
    long that ``K`` is numerically singular) the jitter grows tenfold, up to 1e-4 of the prior variance."""
    eye = torch.eye(len(K), dtype=K.dtype, device=K.device)
    jitter = jitter.detach()  # a numerical guard, not a hyperparameter
    scale = float(jitter) if float(jitter) > 0 else 0.0
    for _ in range(5):
        L, info = torch.linalg.cholesky_ex(K + jitter * eye)
        if int(info) == 0:
            return L
        scale = max(scale * 10.0, 1e-10 * float(K.detach().diagonal().mean()))
        jitter = torch.tensor(scale, dtype=K.dtype, device=K.device)
    raise EstimationError(f"GP: covariance ({len(K)}x{len(K)}) is not positive definite with jitter {scale:.2g}")


def _chol_lower(K: Tensor, jitter: Tensor) -> Tensor:
    """:func:`_chol` of a ``K`` whose lower triangle alone is set, its jitter added on the diagonal in place (``K`` is
    work space): no ``n^2`` copies beside the factor."""
    diag = K.diagonal().clone()
    scale = float(jitter.detach()) if float(jitter) > 0 else 0.0
    for _ in range(5):
        K.diagonal().copy_(diag).add_(scale)
        L, info = torch.linalg.cholesky_ex(K)
        if int(info) == 0:
            return L
        scale = max(scale * 10.0, 1e-10 * float(diag.mean()))
    raise EstimationError(f"GP: covariance ({len(K)}x{len(K)}) is not positive definite with jitter {scale:.2g}")


def _latent_var(kxx: Tensor, Kxu: Tensor, chol_uu: Tensor, chol_b: Tensor | None) -> Tensor:
    """Posterior variance of the latent function ``(b,)`` (standardised) at rows whose kernel against the inducing
    inputs is ``Kxu (b, m)``: ``k(x, x) - |L_uu^-1 k|^2 + |L_B^-1 L_uu^-1 k|^2`` (sparse), or with ``chol_b`` None
    ``k(x, x) - |L^-1 k|^2``, ``L`` the factor of ``K + sigma^2 I`` (exact)."""
    a = torch.linalg.solve_triangular(chol_uu, Kxu.T, upper=False)
    var = kxx - a.square().sum(0)
    if chol_b is not None:
        var = var + torch.linalg.solve_triangular(chol_b, a, upper=False).square().sum(0)
    return var.clamp_min(0.0)


def _bound(
    x: Tensor,
    y: Tensor,
    z: Tensor,
    h: dict[str, Tensor],
    periodic: Tensor,
    ard: bool,
    exact: bool,
    dists: tuple[Tensor, Tensor] | None = None,
) -> Tensor:
    """Titsias's collapsed evidence bound (exact log marginal likelihood when ``exact``), summed over outputs.

    ``dists``: the distances ``(_dist(z, z), _dist(z, x))`` when precomputed.
    """
    n, p = y.shape
    s2 = h["noise"]
    kxx = _prior_var(h, ard)
    if exact:
        # the marginal likelihood itself from one Cholesky of K + s2 I: a quarter of the collapsed bound's work
        # with inducing inputs = rows, and the same value
        K = _kern(dists[0] if dists is not None else _dist(x, x, periodic), h, ard)
        L = _chol(K + s2 * torch.eye(n, dtype=K.dtype, device=K.device), _JITTER * kxx)
        a = torch.linalg.solve_triangular(L, y, upper=False)
        logdet = 2.0 * torch.log(L.diagonal()).sum()
        return -0.5 * (p * (logdet + n * math.log(2 * math.pi)) + a.square().sum())
    Duu, Duf = dists if dists is not None else (_dist(z, z, periodic), None if exact else _dist(z, x, periodic))
    Kuu = _kern(Duu, h, ard)
    Lu = _chol(Kuu, _JITTER * kxx)
    Kuf = Kuu if exact else _kern(Duf, h, ard)
    A = torch.linalg.solve_triangular(Lu, Kuf, upper=False) / s2.sqrt()  # (m, n)
    B = A @ A.T
    B.diagonal().add_(1.0)
    LB = _chol(B, torch.tensor(0.0, dtype=F64, device=B.device))
    c = torch.linalg.solve_triangular(LB, A @ y, upper=False) / s2.sqrt()  # (m, p)
    logdet = 2.0 * torch.log(LB.diagonal()).sum() + n * torch.log(s2)
    quad = y.square().sum() / s2 - c.square().sum()
    trace = 0.0 if exact else (n * kxx / s2 - A.square().sum())
    return -0.5 * (p * (logdet + n * math.log(2 * math.pi)) + quad + p * trace)


# ----------------------------------------------------------------------------- the effect


class GPCorrection(Effect):
    """The ``learned`` effect as an additive + ARD Gaussian process, exact or sparse (module docstring); base frame.

    Everything the prediction needs is a buffer, so ``state_dict`` and :meth:`config` rebuild it
    exactly (:func:`~torchcal.effects.effect_from_config`).

    Args:
        dof: joints.
        n_inducing: inducing inputs ``m``.
        extras: extra inputs after the joints, a subset of ``("t", "temperature")``.
        additive: form of the joints' 1-D components, ``"rbf"`` or ``"periodic"``.
        ard: whether the full-joint ARD component is present.
        exact: the exact GP: the inducing inputs are the training rows and ``chol_uu`` is the Cholesky factor of
            ``K + sigma^2 I`` (no ``chol_b``), else the sparse posterior's two factors.
    """

    kind = "learned"
    acts_on = "cartesian"
    fades_beyond_region = True

    def __init__(
        self,
        dof: int,
        n_inducing: int = 0,
        extras: tuple[str, ...] | list[str] = (),
        additive: str = "rbf",
        ard: bool = True,
        exact: bool = False,
    ):
        super().__init__(joint=None)
        if additive not in ADDITIVE_FORMS:
            raise OptionError(f"additive form '{additive}' is not one of {', '.join(ADDITIVE_FORMS)}")
        self.dof, self.extras, self.additive, self.ard = int(dof), tuple(extras), additive, bool(ard)
        self.exact = bool(exact)
        d, m = self.dof + len(self.extras), int(n_inducing)
        self.register_buffer("inducing", torch.zeros(m, d, dtype=F64))
        self.register_buffer("weights", torch.zeros(m, 3, dtype=F64))  # posterior mean = k(x, Z) @ weights [m]
        self.register_buffer("chol_uu", torch.eye(m, dtype=F64))  # chol(K_uu); exact: chol(K + s2 I)
        mb = 0 if self.exact else m  # chol(I + K_uu^-1/2 K_uf K_fu K_uu^-T/2 / s2); exact: none
        self.register_buffer("chol_b", torch.eye(mb, dtype=F64))
        self.register_buffer("y_mean", torch.zeros(3, dtype=F64))  # [m]
        self.register_buffer("y_scale", torch.ones(3, dtype=F64))  # [m] per output
        self.register_buffer("x_offset", torch.zeros(d, dtype=F64))  # joints: 0; extras: their mean
        self.register_buffer("x_scale", torch.ones(d, dtype=F64))  # joints: 1; extras: their std
        self.register_buffer("periodic", torch.tensor([additive == "periodic"] * self.dof + [False] * len(self.extras)))
        self.register_buffer("add_var", torch.zeros(d, dtype=F64))  # per-variable 1-D component variance
        self.register_buffer("add_len", torch.ones(d, dtype=F64))  # their length scales [rad / standard units]
        self.register_buffer("ard_var", torch.tensor(0.0, dtype=F64))
        self.register_buffer("ard_len", torch.ones(d, dtype=F64))
        self.register_buffer("noise", torch.tensor(1.0, dtype=F64))  # noise variance (standardised outputs)
        self._cache: tuple | None = None

    # -- inputs and hyperparameters

    def hyper(self) -> dict[str, Tensor]:
        return {
            "add_var": self.add_var,
            "add_len": self.add_len,
            "ard_var": self.ard_var,
            "ard_len": self.ard_len,
            "noise": self.noise,
        }

    def inputs(self, ctx: Context) -> Tensor:
        """The standardised GP inputs ``(N, dof + len(extras))`` of a context."""
        cols = [ctx.q]
        for name in self.extras:
            v = getattr(ctx, name)
            if v is None:
                raise ShapeError(f"the GP correction reads '{name}', and the data carry no '{name}' column")
            cols.append(v.reshape(-1, 1).to(ctx.q.dtype))
        return (torch.cat(cols, 1) - self.x_offset) / self.x_scale

    def _kxu(self, x: Tensor) -> Tensor:
        return _kernel(x, self.inducing, self.hyper(), self.periodic, self.ard)

    # -- prediction

    def predict(self, ctx: Context, *, std: bool = True, noise: bool = False) -> tuple[Tensor, Tensor | None]:
        """Posterior mean ``(N, 3)`` [m] and standard deviation ``(N, 3)`` [m] (of the function, or of a new
        observation with ``noise``), in row blocks so that memory stays ``O(block * m)``."""
        x = self.inputs(ctx)
        if not std:
            return self._mean(x), None
        means, stds = [], []
        kxx = _prior_var(self.hyper(), self.ard)
        for i in range(0, len(x), _BLOCK):
            Kxu = self._kxu(x[i : i + _BLOCK])
            means.append(Kxu @ self.weights * self.y_scale + self.y_mean)
            var = _latent_var(kxx, Kxu, self.chol_uu, None if self.exact else self.chol_b)
            if noise:
                var = var + self.noise
            stds.append(var.sqrt().unsqueeze(1) * self.y_scale)
        mean = torch.cat(means) if means else torch.zeros(0, 3, dtype=F64, device=x.device)
        # the mean is the one forward() computes: keep it for the model's evaluation at the same rows that follows
        # (the trust of a prediction takes both)
        self._keep(self._key(ctx), mean, x)
        return mean, (torch.cat(stds) if stds else torch.zeros_like(mean))

    def _mean(self, x: Tensor) -> Tensor:
        """Posterior mean ``(N, 3)`` [m] at the standardised inputs ``x``, in row blocks."""
        means = [
            self._kxu(x[i : i + _BLOCK]) @ self.weights * self.y_scale + self.y_mean for i in range(0, len(x), _BLOCK)
        ]
        return torch.cat(means) if means else torch.zeros(0, 3, dtype=F64, device=x.device)

    def _key(self, ctx: Context) -> tuple | None:
        """The key of the mean at ``ctx``: it depends on the context and the buffers only."""
        if ctx.q.requires_grad:
            return None
        return version_key(ctx.q, ctx.t, ctx.temperature, self.inducing, self.weights, self.y_scale)

    def _mean_inputs(self) -> list[Tensor]:
        """The buffers the posterior mean depends on (not the factors of its variance)."""
        return [self.inducing, self.weights, self.y_scale, self.y_mean, self.periodic, *self.hyper().values()]

    def _keep(self, key: tuple | None, mean: Tensor, x: Tensor) -> None:
        if key is not None and not mean.requires_grad:
            self._cache = (key, mean, x, [b.clone() for b in self._mean_inputs()])

    def _kept(self, key: tuple | None, x: Tensor) -> Tensor | None:
        """The kept mean where ``key`` names its context, or where the standardised inputs ``x`` and the buffers
        the mean depends on equal the kept ones (the same rows as another tensor: a stage that selects its training
        rows anew, a copy of the model): the mean a new computation would give, to the bit."""
        if key is None or self._cache is None:
            return None
        old_key, mean, old_x, buffers = self._cache
        if same_version(old_key, key):
            return mean
        if old_x.shape == x.shape and torch.equal(old_x, x):
            if all(torch.equal(a, b) for a, b in zip(buffers, self._mean_inputs())):
                self._cache = (key, mean, old_x, buffers)
                return mean
        return None

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
        q = ctx.q
        if len(self.inducing) == 0:
            return torch.zeros(q.shape[0], 3, dtype=q.dtype, device=q.device)
        x = self.inputs(ctx)
        if (
            torch.is_grad_enabled()
            and x.requires_grad
            and plain(x)
            and not any(b.requires_grad for b in self.buffers())
        ):
            # differentiated by the joints (compensation's Jacobian): the derivative in closed form
            return _MeanByInputs.apply(x, self)
        # as KernelCorrection: the output depends on the context and the buffers only, and a least-squares
        # fit evaluates it at the same q dozens of times, so the last plain result is reused
        key = self._key(ctx)
        kept = self._kept(key, x)
        if kept is not None:
            return kept
        out = self._mean(x)
        self._keep(key, out, x)
        return out

    def component_means(self, ctx: Context) -> Tensor:
        """Posterior mean of each additive component and of the ARD one ``(n_vars + 1, N, 3)`` [m].

        The components of a sum of kernels share the weights: component ``c``'s mean is ``k_c(x, Z) @ weights``.
        Each variable's distances are computed once for all components (as :func:`_kernel` computes them, the same
        values), in row blocks of :data:`_BLOCK`.
        """
        x = self.inputs(ctx)
        h = self.hyper()
        d, z = x.shape[1], self.inducing
        add_c = [float(-0.5 / v.square()) for v in h["add_len"]]
        add_v = [float(v) for v in h["add_var"]]
        ard_c = [float(1.0 / v.square()) for v in h["ard_len"]]
        out = torch.zeros(d + 1, len(x), 3, dtype=F64, device=x.device)
        for i in range(0, len(x), _BLOCK):
            xb = x[i : i + _BLOCK]
            S = torch.zeros(len(xb), len(z), dtype=F64, device=x.device) if self.ard else None
            for j in range(d):
                dj = _squared(xb[:, j : j + 1] - z[:, j].unsqueeze(0), self.periodic[j : j + 1])
                if self.ard:
                    S.add_(dj, alpha=ard_c[j])
                E = dj.mul_(add_c[j]).clamp_(min=_EXP_FLOOR).exp_()
                out[j, i : i + len(xb)] = torch.zeros_like(E).add_(E, alpha=add_v[j]) @ self.weights
            if self.ard:
                E = S.mul_(-0.5).clamp_(min=_EXP_FLOOR).exp_()
                out[d, i : i + len(xb)] = torch.zeros_like(E).add_(E, alpha=float(h["ard_var"])) @ self.weights
        return out * self.y_scale

    def moved_means(self, ctx: Context, moves: dict[int, list[Tensor]]) -> dict[int, list[Tensor]]:
        """The posterior mean ``(N, 3)`` [m] at ``ctx`` with joint ``j``'s column replaced by each of ``moves[j]``
        (``(N,)`` each), as :meth:`forward` gives it at those rows up to rounding.

        A move changes one variable's term of the additive sum and the ARD component by one factor, so each costs
        two exponentials per kernel entry where :meth:`forward` takes one per variable and the ARD's: the trust's
        variogram (:func:`torchcal.estimate.trust.correction_variogram`) moves every joint by seven lags.
        """
        x = self.inputs(ctx)
        out: dict[int, list[list[Tensor]]] = {j: [[] for _ in cols] for j, cols in moves.items()}
        for i in range(0, len(x), _BLOCK):
            for j, means in _moved_block(self, x[i : i + _BLOCK], i, moves).items():
                for acc, m in zip(out[j], means):
                    acc.append(m)
        empty = torch.zeros(0, 3, dtype=F64, device=x.device)
        return {j: [torch.cat(acc) if acc else empty for acc in accs] for j, accs in out.items()}

    def prime(self, ctx: Context, mean: Tensor) -> None:
        """Take ``mean`` (from :meth:`moved_means`) as the posterior mean at ``ctx`` for :meth:`forward` there."""
        self._keep(self._key(ctx), mean, self.inputs(ctx))

    def variable_names(self) -> list[str]:
        return [f"q{j + 1}" for j in range(self.dof)] + list(self.extras)

    def scale_(self, factor: float) -> None:
        with torch.no_grad():
            self.y_scale.mul_(factor)
            self.y_mean.mul_(factor)

    def config(self) -> dict:
        return {
            "dof": self.dof,
            "n_inducing": int(self.inducing.shape[0]),
            "extras": list(self.extras),
            "additive": self.additive,
            "ard": self.ard,
            "exact": self.exact,
        }

    def describe(self) -> dict:
        names = self.variable_names()
        return {
            "model": f"Gaussian process (additive + ARD, {'exact' if self.exact else 'sparse'})",
            "additive": self.additive,
            "n_inducing": int(self.inducing.shape[0]),
            "additive_std": dict(zip(names, (self.add_var.sqrt() * 1.0).tolist())),
            "additive_length_scale": dict(zip(names, self.add_len.tolist())),
            "ard_std": float(self.ard_var.sqrt()) if self.ard else 0.0,
            "ard_length_scale": dict(zip(names, self.ard_len.tolist())) if self.ard else {},
            "noise_std": float(self.noise.sqrt()),
            "output_scale_m": self.y_scale.tolist(),
            "units": "std relative to each output's RMS; length scales in rad (joints) or standard units",
        }


# ----------------------------------------------------------------------------- fitting


def kmeans(x: Tensor, m: int, generator: torch.Generator, iterations: int = 10) -> Tensor:
    """``m`` centres of ``x`` ``(n, d)`` by Lloyd's algorithm from a seeded random subset; ``x`` itself if ``n <= m``.

    An empty cluster keeps its previous centre. Memory ``O(block * m)``.
    """
    if len(x) <= m:
        return x.clone()
    c = x[torch.randperm(len(x), generator=generator)[:m]].clone()
    for _ in range(iterations):
        lab = torch.cat([torch.cdist(x[i : i + _BLOCK], c).argmin(1) for i in range(0, len(x), _BLOCK)])
        s = torch.zeros_like(c).index_add_(0, lab, x)
        k = torch.bincount(lab, minlength=m).to(x.dtype)
        c = torch.where(k.unsqueeze(1) > 0, s / k.clamp_min(1).unsqueeze(1), c)
    return c


def _bounds(d: int, device: torch.device | None = None) -> tuple[Tensor, Tensor]:
    """Box of the log hyperparameters (variances relative to the standardised outputs, length scales in rad or
    standard units): a line search that overshoots evaluates a finite kernel instead of exp(300)."""
    lo = [-14.0] * d + [-7.0] * d + [-14.0] + [-7.0] * d + [-14.0]
    hi = [5.0] * d + [7.0] * d + [5.0] + [7.0] * d + [3.0]
    return torch.tensor(lo, dtype=F64, device=device), torch.tensor(hi, dtype=F64, device=device)


def _unpack(theta: Tensor, d: int, ard: bool) -> dict[str, Tensor]:
    lo, hi = _bounds(d, theta.device)
    e = torch.maximum(torch.minimum(theta, hi), lo).exp()
    return {
        "add_var": e[:d],
        "add_len": e[d : 2 * d],
        "ard_var": e[2 * d] if ard else e[2 * d] * 0.0,
        "ard_len": e[2 * d + 1 : 3 * d + 1],
        "noise": e[3 * d + 1] + 1e-6,
    }


def _initial(d: int, n_joints: int, periodic: bool) -> Tensor:
    """Log hyperparameters to start from: the signal shared by the components, noise 10 % of the variance."""
    add_var = torch.full((d,), 0.4 / d, dtype=F64)
    add_len = torch.full((d,), 0.5 if periodic else 0.5, dtype=F64)
    add_len[n_joints:] = 1.0
    theta = torch.cat(
        [
            add_var.log(),
            add_len.log(),
            torch.tensor([math.log(0.5)], dtype=F64),
            torch.full((d,), math.log(1.0), dtype=F64),
            torch.tensor([math.log(0.1)], dtype=F64),
        ]
    )
    return theta


def _random_initial(d: int, n_joints: int, generator: torch.Generator) -> Tensor:
    """A seeded random start: length scales log-uniform (joints 0.05-2 rad, the others 0.3-3 standard units;
    ARD 0.1-3), 50-95 % of the variance as signal split at random between the components, the rest noise."""

    def logu(k, a, b):
        return math.log(a) + (math.log(b) - math.log(a)) * torch.rand(k, generator=generator, dtype=F64)

    add_len = logu(d, 0.3, 3.0)
    add_len[:n_joints] = logu(n_joints, 0.05, 2.0)
    signal = 0.5 + 0.45 * float(torch.rand(1, generator=generator, dtype=F64))
    w = -torch.log(torch.rand(d + 1, generator=generator, dtype=F64).clamp_min(1e-12))  # a flat Dirichlet
    w = signal * w / w.sum()
    return torch.cat(
        [
            w[:d].clamp_min(1e-6).log(),
            add_len,
            w[d:].clamp_min(1e-6).log(),
            logu(d, 0.1, 3.0),
            torch.tensor([math.log(1.0 - signal)], dtype=F64),
        ]
    )


class _Pairs(NamedTuple):
    """The pairs ``a <= b`` of a set of inputs for the exact evidence (:func:`pair_distances`): the kernel matrix is
    symmetric, so each evaluation's passes over the ``(n, n, d)`` distances run over half of them."""

    D: Tensor  # (P, d) per-variable squared distances of the pairs, P = n (n + 1) / 2
    rows: Tensor  # (P,) a
    cols: Tensor  # (P,) b
    weight: Tensor  # (P,) 1 on the diagonal, 2 off it: a pair's share of a sum over all (a, b)
    lower: Tensor  # (P,) the pair's element (b, a) of a row-major (n, n) matrix, in its lower triangle
    upper: Tensor  # (P,) the pair's element (a, b)


def pair_distances(x: Tensor, periodic: Tensor) -> _Pairs:
    """:func:`_dist` of ``x (n, d)`` against itself on the pairs ``a <= b`` alone (the upper triangle)."""
    n = len(x)
    rows, cols = torch.triu_indices(n, n, device=x.device)
    weight = torch.where(rows == cols, 1.0, 2.0).to(x.dtype)
    return _Pairs(_squared(x[rows] - x[cols], periodic), rows, cols, weight, cols * n + rows, rows * n + cols)


def _exact_loss_and_grad(
    theta: Tensor, pairs: _Pairs, y: Tensor, ard: bool, centre: Tensor, work: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """The exact evidence fit's loss (minus the log marginal likelihood per row, plus the weak prior of
    :func:`fit_hyperparameters`) and its gradient in ``theta``, in closed form.

    ``d log p / d theta = 1/2 tr((a a^T - p C^-1) dC/d theta)`` with ``a = C^-1 y``: one Cholesky, one inverse and
    a few weighted sums over the pairs' distances, less than half of what reverse-mode autograd through the
    Cholesky and the kernel's temporaries costs (this is the inner loop of every evidence fit). ``C`` and ``W =
    a a^T - p C^-1`` are symmetric, so the sums run over the pairs ``a <= b`` (off-diagonal ones twice).

    Args:
        theta: log hyperparameters ``(3 d + 2,)`` (:func:`_unpack`); pairs: :func:`pair_distances` of the inputs;
            y: standardised outputs ``(n, p)``; centre: the prior's centre (:func:`_initial`).
        work: a buffer shaped as ``pairs.D`` that the ``(P, d)`` temporary is written into (its content is then
            garbage). An evidence fit passes one for all its evaluations: a fresh temporary of this size is above
            the C allocator's mapping threshold, so each evaluation would map it anew and page-fault through it,
            which cost more than the exponential computed in it.
    """
    n, p = y.shape
    D = pairs.D
    d = D.shape[-1]
    lo, hi = _bounds(d, theta.device)
    inside = ((theta >= lo) & (theta <= hi)).to(theta.dtype)
    th = theta.detach()
    h = _unpack(th, d, ard)
    E = torch.mul(D, -0.5 / h["add_len"].square(), out=work).exp_()  # (P, d); in place: these passes are the cost
    k = E @ h["add_var"]
    if ard:
        G = torch.exp(-0.5 * (D @ (1.0 / h["ard_len"].square())))
        k = k + h["ard_var"] * G
    # the lower triangle alone: the Cholesky factorisation reads no other element
    K = torch.zeros(n, n, dtype=k.dtype, device=k.device)
    K.view(-1)[pairs.lower] = k
    K.diagonal().add_(h["noise"])
    L = _chol_lower(K, _JITTER * _prior_var(h, ard))
    a = torch.cholesky_solve(y, L)
    ll = -0.5 * (p * (2.0 * torch.log(L.diagonal()).sum() + n * math.log(2 * math.pi)) + (y * a).sum())
    W = (a @ a.T).sub_(torch.cholesky_inverse(L).mul_(p))  # (n, n) a a^T - p C^-1: d ll / d C = W / 2
    w = W.view(-1)[pairs.upper].mul_(pairs.weight)  # (P,): each pair's weight in the sums over all (a, b)
    g = torch.zeros_like(th)
    g[:d] = h["add_var"] * (w @ E)
    g[d : 2 * d] = h["add_var"] * (w @ E.mul_(D)) / h["add_len"].square()
    del E
    if ard:
        wG = w * G
        g[2 * d] = h["ard_var"] * wG.sum()
        g[2 * d + 1 : 3 * d + 1] = h["ard_var"] * (wG @ D) / h["ard_len"].square()
    g[3 * d + 1] = (h["noise"] - 1e-6) * W.diagonal().sum()
    g = 0.5 * g * inside
    prior = 0.5 * ((th[:-1] - centre[:-1]) / 3.0).square().sum()
    grad = -g / n
    grad[:-1] += (th[:-1] - centre[:-1]) / 9.0 / n
    return (-ll + prior) / n, grad


def fit_hyperparameters(
    x: Tensor,
    y: Tensor,
    z: Tensor,
    *,
    periodic: Tensor,
    ard: bool,
    iterations: int,
    n_joints: int,
    start: dict[str, Tensor] | None = None,
    restarts: int = 1,
    restart_iterations: int = 6,
    generator: torch.Generator | None = None,
    tolerance: float = 0.0,
) -> tuple[dict[str, Tensor], dict]:
    """Maximise the (collapsed) evidence over the log hyperparameters with L-BFGS, from several starts.

    Without ``start``, ``restarts`` starting points (the default :func:`_initial` and seeded random ones,
    :func:`_random_initial`) each run ``restart_iterations`` iterations; the one with the best bound goes on for
    ``iterations`` more. The best point any evaluation saw is returned (L-BFGS's line search may end elsewhere).

    Args:
        x: inputs ``(n, d)``, standardised; y: outputs ``(n, p)``, standardised; z: inducing inputs ``(m, d)``
            (``z is x`` gives the exact marginal likelihood).
        start: hyperparameters to start from (a previous fit's :meth:`GPCorrection.hyper`), else a default;
            with a start there are no restarts.
        generator: draws the random starts (a fixed seed when None).
        tolerance: stop at the first iteration that raises the log evidence by less than this [nats, all rows]
            (0: run every iteration).

    Returns:
        The hyperparameters and ``{"log_evidence_per_row", "evaluations", "restart_log_evidence_per_row"}``
        (the last: the bound per row that each start reached, the chosen one the best).
    """
    d = x.shape[1]
    evidence = _Evidence(x, y, z, periodic, ard, _initial(d, n_joints, False).to(x.device))
    if start is not None:
        theta0, tried = _theta_of(start), []
    else:
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        starts = [_initial(d, n_joints, bool(periodic[:n_joints].any()))]
        starts += [_random_initial(d, n_joints, g) for _ in range(restarts - 1)]
        tried = []
        if len(starts) > 1:
            # the starts are independent (their points drawn above): side by side in threads of one torch thread each
            # (an evaluation's Cholesky and products release the GIL), in order, so the choice is the same
            with ThreadPoolExecutor(RESTART_WORKERS, initializer=torch.set_num_threads, initargs=(1,)) as pool:
                tried = list(pool.map(lambda t0: evidence.run(t0, restart_iterations), starts))
        theta0 = min(tried, key=lambda r: r[0])[1] if tried else starts[0]
    loss, theta, evaluations = evidence.run(theta0, iterations, tolerance / len(x))
    evaluations += sum(r[2] for r in tried)
    if tried:
        loss, theta = min([(loss, theta)] + [r[:2] for r in tried], key=lambda r: r[0])
    if not math.isfinite(loss) or loss >= 1e10:
        raise EstimationError("GP: no evidence evaluation succeeded (the covariance was never positive definite)")
    with torch.no_grad():
        h = {k: v.detach().clone() for k, v in _unpack(theta, d, ard).items()}
    return h, {
        "log_evidence_per_row": -loss,
        "evaluations": evaluations,
        "restart_log_evidence_per_row": [-r[0] for r in tried],
    }


def _theta_of(start: dict[str, Tensor]) -> Tensor:
    """The log hyperparameters of a previous fit's :meth:`GPCorrection.hyper`."""
    noise = (start["noise"] - 1e-6).clamp_min(1e-6)
    return torch.cat(
        [
            start["add_var"].clamp_min(1e-12).log(),
            start["add_len"].log(),
            start["ard_var"].clamp_min(1e-12).log().reshape(1),
            start["ard_len"].log(),
            noise.log().reshape(1),
        ]
    ).to(F64)


#: the loss that sends L-BFGS's line search back from a trial point where the covariance is not positive definite
_WALL = 1e10


class _Evidence:
    """The negative log evidence per row of :func:`fit_hyperparameters`'s data over the log hyperparameters, with
    a weak log-normal prior about ``centre`` that keeps the length scales and variances off 0 and infinity where
    the data say little: exact (closed form, its gradient by hand) where ``z is x``, else the sparse bound
    (autograd)."""

    def __init__(self, x: Tensor, y: Tensor, z: Tensor, periodic: Tensor, ard: bool, centre: Tensor):
        self.x, self.y, self.z, self.periodic, self.ard, self.centre = x, y, z, periodic, ard, centre
        self.d = x.shape[1]
        self.exact = z is x
        # exact: the pairs' distances alone (the closed-form evidence); sparse: both blocks (autograd through it)
        self.pairs = pair_distances(x, periodic) if self.exact else None
        self.dists = None if self.exact else (_dist(z, z, periodic), _dist(z, x, periodic))

    def exact_loss(self, theta: Tensor, work: Tensor) -> Tensor:
        """The loss at ``theta``, its gradient set on ``theta.grad`` (the wall where it cannot be evaluated)."""
        try:
            loss, grad = _exact_loss_and_grad(theta, self.pairs, self.y, self.ard, self.centre, work)
        except EstimationError:  # not positive definite at this trial point: send the line search back
            loss, grad = torch.tensor(_WALL, dtype=F64, device=theta.device), torch.zeros_like(theta)
        if not bool(torch.isfinite(loss)) or not bool(torch.isfinite(grad).all()):
            loss, grad = torch.tensor(_WALL, dtype=F64, device=theta.device), torch.zeros_like(theta)
        theta.grad = grad
        return loss

    def sparse_loss(self, theta: Tensor) -> Tensor:
        """The loss at ``theta``, back-propagated into ``theta.grad`` (the wall where it cannot be evaluated)."""
        x, n = self.x, len(self.x)
        prior = 0.5 * ((theta[:-1] - self.centre[:-1]) / 3.0).square().sum()
        try:
            h = _unpack(theta, self.d, self.ard)
            loss = -_bound(x, self.y, self.z, h, self.periodic, self.ard, self.exact, self.dists) / n + prior / n
        except EstimationError:
            loss = (theta * 0.0).sum() + _WALL
        if not torch.isfinite(loss):
            loss = (theta * 0.0).sum() + _WALL
        loss.backward()
        return loss

    def run(self, theta0: Tensor, max_iter: int, tolerance: float = 0.0) -> tuple[float, Tensor, int]:
        """L-BFGS from ``theta0``: the best loss any evaluation saw, its point and the number of evaluations;
        ``tolerance``: the change of the loss (per row) below which it stops (0: L-BFGS's own 1e-9)."""
        theta = theta0.detach().to(self.x.device).clone().requires_grad_(True)
        best = [math.inf, theta0.detach().clone()]
        count = [0]  # per start: the starts run in threads
        work = torch.empty_like(self.pairs.D) if self.exact else None  # per start, as the starts run side by side

        def closure():
            theta.grad = None
            loss = self.exact_loss(theta, work) if self.exact else self.sparse_loss(theta)
            count[0] += 1
            value = float(loss.detach())
            if value < best[0]:
                best[0], best[1] = value, theta.detach().clone()
            return loss

        # torch.optim.LBFGS's method to the bit, without torch.optim (which imports torch._dynamo): torchcal._lbfgs
        tol = {"tolerance_grad": 1e-6, "tolerance_change": max(tolerance, 1e-9)}
        _lbfgs.minimize(closure, theta, max_iter=max_iter, history_size=20, **tol)
        return best[0], best[1], count[0]


def _in_order(fn: Callable, starts: Iterable[int]) -> Iterator:
    """``fn(i)`` for each block start, in order, computed by :data:`BLOCK_WORKERS` threads with at most one block
    waiting per thread (memory stays ``O(workers)`` blocks)."""
    if BLOCK_WORKERS <= 1:
        yield from map(fn, starts)
        return
    # each worker on one torch thread of its own: a new thread starts with the process's default (OpenMP's
    # per-thread setting), and a team of varying size sums in a varying order: the blocks' last bits would vary
    with ThreadPoolExecutor(BLOCK_WORKERS, initializer=torch.set_num_threads, initargs=(1,)) as pool:
        pending: deque = deque()
        for i in starts:
            pending.append(pool.submit(fn, i))
            if len(pending) > BLOCK_WORKERS:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def _square_kernel(eff: GPCorrection, x: Tensor) -> Tensor:
    """``k(x, x)`` ``(n, n)`` of ``eff``'s hyperparameters, in row blocks (three block-sized temporaries instead of
    three ``(n, n)`` ones). The matrix is symmetric: each block of rows is computed up to its last column of the
    diagonal and mirrored (the same values: ``x_a - x_b`` is exactly ``-(x_b - x_a)``), half of the work."""
    h = eff.hyper()
    n = len(x)
    K = torch.empty(n, n, dtype=x.dtype, device=x.device)
    for i in range(0, n, _BLOCK):
        j = min(n, i + _BLOCK)
        block = _kernel(x[i:j], x[:j], h, eff.periodic, eff.ard)
        K[i:j, :j] = block
        K[:i, i:j] = block[:, :i].T
    return K


def _exact_factor(eff: GPCorrection, x: Tensor) -> Tensor:
    """Cholesky factor of ``K(x, x) + sigma^2 I`` ``(n, n)``."""
    h = eff.hyper()
    C = _square_kernel(eff, x)
    C.diagonal().add_(h["noise"])
    return _chol(C, _JITTER * _prior_var(h, eff.ard))


def _posterior(eff: GPCorrection, x: Tensor, y: Tensor) -> None:
    """Weights and Cholesky factors of the posterior given all rows ``x, y`` (standardised), streamed in blocks
    (exact: the weights ``(K + sigma^2 I)^-1 y`` from one dense factor, the inducing inputs being ``x``)."""
    if eff.exact:
        L = _exact_factor(eff, x)
        eff.weights.copy_(torch.cholesky_solve(y, L))
        eff.chol_uu.copy_(L)
        return
    h, z = eff.hyper(), eff.inducing
    m = len(z)
    Lu = _chol(_square_kernel(eff, z), _JITTER * _prior_var(h, eff.ard))
    B = torch.eye(m, dtype=F64, device=z.device)
    Ay = torch.zeros(m, y.shape[1], dtype=F64, device=z.device)
    s = h["noise"].sqrt()

    def block(i: int) -> tuple[Tensor, Tensor]:
        A = torch.linalg.solve_triangular(Lu, _kernel(z, x[i : i + _BLOCK], h, eff.periodic, eff.ard), upper=False) / s
        return A @ A.T, A @ y[i : i + _BLOCK]

    for AA, Ay_i in _in_order(block, range(0, len(x), _BLOCK)):
        B += AA
        Ay += Ay_i
    LB = _chol(B, torch.tensor(0.0, dtype=F64, device=B.device))
    c = torch.cholesky_solve(Ay, LB) / s  # B^-1 A y / s
    w = torch.linalg.solve_triangular(Lu.T, c, upper=True)  # K_uu^-T/2 B^-1 A y / s
    eff.weights.copy_(w)
    eff.chol_uu.copy_(Lu)
    eff.chol_b.copy_(LB)


def fit_gp_correction(
    ctx: Context,
    y: Tensor,
    settings: GPSettings | None = None,
    *,
    ctx_val: Context | None = None,
    y_val: Tensor | None = None,
    warm: GPCorrection | None = None,
    warm_iterations: int = 10,
    summary: bool = True,
) -> tuple[GPCorrection, dict]:
    """Fit a :class:`GPCorrection` to corrections ``y`` at the poses of ``ctx``.

    Args:
        ctx: training context (joints ``q (N, dof)`` [rad]; ``t``, ``temperature`` when ``settings.extras`` name them).
        y: corrections ``(N, 3)`` [m, robot base frame] (what the model misses, as ``corrections`` computes).
        settings: :class:`GPSettings`.
        ctx_val, y_val: optional validation poses; only evaluated (the evidence chooses the hyperparameters),
            so that the caller can judge the model on poses it has not seen.
        warm: a previous fit of the same structure (an alternating refit): its hyperparameters are the start,
            and ``warm_iterations`` L-BFGS iterations replace ``settings.iterations``.
        summary: also each variable's share and the validation coverage (a kernel evaluation per component and
            the predictive variances: a sixth of a refit's time, and an alternating refit reads neither).

    Returns:
        The fitted effect and a dict: the hyperparameters (``describe()``), the evidence, the rows and inducing
        inputs used, each variable's share of the fitted correction's variance (``variable_share``), and with
        validation data the validation errors per pose ``val_errors (n_val,)`` [m], ``val_rmse_m`` and the
        fraction of validation coordinates within two predictive standard deviations ``val_coverage_2sigma``
        (without ``summary`` neither the shares nor the coverage).
    """
    s = settings or GPSettings()
    if y.ndim != 2 or y.shape[1] != 3 or len(y) != len(ctx.q):
        raise ShapeError(f"GP correction: expected y of shape ({len(ctx.q)}, 3), got {tuple(y.shape)}")
    with torch_threads(s.threads):
        return _fit(ctx, y.to(F64), s, ctx_val, y_val, warm, warm_iterations, summary)


def _fit(
    ctx: Context, y: Tensor, s: GPSettings, ctx_val, y_val, warm, warm_iterations, summary: bool = True
) -> tuple[GPCorrection, dict]:
    g = torch.Generator().manual_seed(int(s.seed))
    n, dof = ctx.q.shape
    exact = n <= s.max_exact
    eff = GPCorrection(dof, n if exact else min(n, s.max_inducing), s.extras, s.additive, s.ard, exact).to(ctx.q.device)
    x, ys = _standardise(eff, ctx, y, s)
    # 1. hyperparameters by the evidence on a seeded subset
    sub = torch.randperm(n, generator=g)[: s.max_fit] if n > s.max_fit else torch.arange(n)
    xf, yf = x[sub], ys[sub]
    zf = xf if len(xf) <= s.m_fit else kmeans(xf, s.m_fit, g, s.kmeans_iterations)
    if warm is not None and warm.config() != eff.config() | {"n_inducing": warm.config()["n_inducing"]}:
        raise OptionError(f"GP warm start: the previous model's structure {warm.config()} differs from {eff.config()}")
    h, info = _evidence_fit(eff, (xf, yf, zf), s, g, warm, warm_iterations)
    with torch.no_grad():
        for k, v in h.items():
            getattr(eff, k).copy_(v)
        # 2. inducing inputs for the posterior: every row when they fit, else k-means in the ARD metric
        if exact or n <= s.max_inducing:
            eff.inducing.copy_(x)
        else:
            metric = 1.0 / eff.ard_len if s.ard else 1.0 / eff.add_len
            eff.inducing.copy_(kmeans(x * metric, s.max_inducing, g, s.kmeans_iterations) / metric)
        # 3. posterior over all rows
        if _same_factor(warm, eff):  # a warm refit that kept the hyperparameters, on the same rows: the same factor
            eff.weights.copy_(torch.cholesky_solve(ys, warm.chol_uu))
            eff.chol_uu.copy_(warm.chol_uu)
        else:
            _posterior(eff, x, ys)
    out = {
        **eff.describe(),
        "log_evidence_per_row": info["log_evidence_per_row"],
        "evidence_evaluations": info["evaluations"],
        "restart_log_evidence_per_row": info["restart_log_evidence_per_row"],
        "rows": n,
        "rows_for_hyperparameters": len(xf),
        "inducing_for_hyperparameters": len(zf),
        "exact": exact or n <= s.max_inducing,
        **({"variable_share": _variable_share(eff, ctx.subset(sub), s)} if summary else {}),
        "rmse_unit": "m",
    }
    if ctx_val is not None and y_val is not None:
        out.update(_validation(eff, ctx_val, y_val, summary))
    return eff, out


def _same_factor(warm: GPCorrection | None, eff: GPCorrection) -> bool:
    """Whether ``eff`` (exact, its hyperparameters and inducing inputs set) has ``warm``'s factor of ``K + sigma^2
    I``: the same inputs and hyperparameters to the bit. A warm refit whose evidence fit stopped at its start (the
    evidence no longer moves, ``GPSettings.warm_tolerance``) on the rows of the fit it started from then needs only
    the solve with the new outputs, not the ``n^3 / 3`` factorisation and the ``n^2`` kernel."""
    if warm is None or not (warm.exact and eff.exact) or warm.inducing.shape != eff.inducing.shape:
        return False
    same = torch.equal(warm.inducing, eff.inducing) and torch.equal(warm.periodic, eff.periodic)
    return same and all(torch.equal(v, eff.hyper()[k]) for k, v in warm.hyper().items())


def _standardise(eff: GPCorrection, ctx: Context, y: Tensor, s: GPSettings) -> tuple[Tensor, Tensor]:
    """Set ``eff``'s input and output standardisation from the data; returns the inputs ``x`` and the
    standardised outputs."""
    dof = ctx.q.shape[1]
    with torch.no_grad():
        for k, name in enumerate(s.extras):
            v = getattr(ctx, name)
            if v is None:
                raise ShapeError(f"GP settings name the extra input '{name}', and the data carry none")
            eff.x_offset[dof + k] = v.mean()
            eff.x_scale[dof + k] = v.std().clamp_min(1e-12)
        x = eff.inputs(ctx)
        eff.y_mean.copy_(y.mean(0))
        eff.y_scale.copy_((y - eff.y_mean).square().mean(0).sqrt().clamp_min(1e-12))
        return x, (y - eff.y_mean) / eff.y_scale


def _evidence_fit(eff: GPCorrection, xyz: tuple[Tensor, Tensor, Tensor], s: GPSettings, g, warm, warm_iterations):
    """The hyperparameters by the evidence on the subset ``xyz`` (inputs, outputs, inducing inputs): from a warm
    start, or with the restarts and most iterations on its first rows (cheap: the exact evidence costs O(n^3))
    and a few iterations on all of it from the best point found there."""
    xf, yf, zf = xyz
    common = {"periodic": eff.periodic, "ard": s.ard, "n_joints": eff.dof}
    restarts = {"restarts": s.restarts, "restart_iterations": s.restart_iterations, "generator": g}
    start, coarse = None if warm is None else warm.hyper(), None
    if warm is None and s.coarse_rows < len(xf):
        xc, yc = xf[: s.coarse_rows], yf[: s.coarse_rows]
        zc = xc if len(xc) <= s.m_fit else kmeans(xc, s.m_fit, g, s.kmeans_iterations)
        start, coarse = fit_hyperparameters(xc, yc, zc, **common, iterations=s.iterations, **restarts)
    iterations = (s.refine_iterations if coarse is not None else s.iterations) if warm is None else warm_iterations
    tolerance = 0.0 if warm is None else s.warm_tolerance
    h, info = fit_hyperparameters(
        xf, yf, zf, **common, iterations=iterations, start=start, **restarts, tolerance=tolerance
    )
    if coarse is not None:
        info["evaluations"] += coarse["evaluations"]
        info["restart_log_evidence_per_row"] = coarse["restart_log_evidence_per_row"]
    return h, info


def _variable_share(eff: GPCorrection, ctx: Context, s: GPSettings) -> dict[str, float]:
    """Each variable's share of the correction's variance, a summary from the rows ``ctx`` of the evidence fit
    (memory and time stay bounded)."""
    with torch.no_grad():
        comp = eff.component_means(ctx)
        var = comp.square().sum(-1).mean(1)
        share = (var / var.sum().clamp_min(1e-30)).tolist()
    names = eff.variable_names() + (["ard"] if s.ard else [])
    return dict(zip(names, share[: len(names)]))


def _validation(eff: GPCorrection, ctx_val: Context, y_val: Tensor, summary: bool) -> dict:
    """The validation errors and RMSE, and (with ``summary``) the share of components within 2 sigma."""
    out = {}
    with torch.no_grad():
        mean, sd = eff.predict(ctx_val, std=summary, noise=True)
        e = (y_val - mean).norm(dim=-1)
        out["val_errors"] = e
        out["val_rmse_m"] = float(e.square().mean().sqrt())
        if summary:
            out["val_coverage_2sigma"] = float(((y_val - mean).abs() <= 2 * sd).double().mean())
    return out


def condition_gp(eff: GPCorrection, ctx: Context, y: Tensor, settings: GPSettings | None = None) -> GPCorrection:
    """A copy of ``eff`` with its hyperparameters and standardisation, conditioned on the poses ``ctx, y``.

    The learned stage judges a GP fitted on part of the training poses; the model it keeps should use all of
    them (a short-range correction gains most from more neighbours), and its hyperparameters need no refit.

    Args:
        eff: a fitted :class:`GPCorrection`.
        ctx: context of the poses (joints ``q (N, dof)`` [rad], and the extras ``eff`` reads).
        y: corrections ``(N, 3)`` [m, robot base frame].
        settings: inducing inputs (``max_inducing``), k-means iterations and seed; default :class:`GPSettings`.

    Returns:
        The conditioned effect (``eff`` is left unchanged).
    """
    s = settings or GPSettings()
    if y.ndim != 2 or y.shape[1] != 3 or len(y) != len(ctx.q):
        raise ShapeError(f"GP conditioning: expected y of shape ({len(ctx.q)}, 3), got {tuple(y.shape)}")
    n = len(y)
    exact = n <= s.max_exact
    new = GPCorrection(eff.dof, n if exact else min(n, s.max_inducing), eff.extras, eff.additive, eff.ard, exact)
    new = new.to(ctx.q.device)
    with torch_threads(s.threads), torch.no_grad():
        for name in ("y_mean", "y_scale", "x_offset", "x_scale", *eff.hyper()):
            getattr(new, name).copy_(getattr(eff, name))
        x = new.inputs(ctx)
        if exact or n <= s.max_inducing:
            new.inducing.copy_(x)
        else:
            g = torch.Generator().manual_seed(int(s.seed))
            metric = 1.0 / new.ard_len if new.ard else 1.0 / new.add_len
            new.inducing.copy_(kmeans(x * metric, s.max_inducing, g, s.kmeans_iterations) / metric)
        _posterior(new, x, (y.to(F64) - new.y_mean) / new.y_scale)
    new.train(eff.training)
    return new


#: largest ``m x n`` factor ``K_uu^-1/2 K_uf`` a :class:`GPConditioner` keeps in memory (elements, 8 bytes each);
#: beyond it the factor is recomputed in row blocks at each conditioning (no Cholesky, half the posterior's work)
_KEEP_FACTOR = 25_000_000


class GPConditioner:
    """A fitted GP re-conditioned on new outputs at the same inputs, its hyperparameters and inducing inputs held.

    An alternating refit of the learned stage moves the geometry a little, so the corrections change while the
    poses do not. With the hyperparameters held, everything of the posterior but the weights depends on the
    inputs alone: ``A = L_uu^-1 K_uf / sigma``, the Cholesky factor of ``B = I + A A^T`` and the kernel between the
    validation poses and the inducing inputs are computed once here, and each :meth:`condition` costs two
    triangular solves with three right-hand sides and a product with ``A`` instead of an evidence fit, a k-means
    and an ``O(n m^2)`` posterior. The new outputs are standardised by their own mean and RMS, as
    :func:`fit_gp_correction` does, so the hyperparameters (relative to the outputs' scale) keep their meaning.

    Args:
        eff: a fitted :class:`GPCorrection` (its inputs' standardisation, hyperparameters and inducing inputs
            are kept).
        ctx: the poses to condition on (joints ``q (n, dof)`` [rad], and the extras ``eff`` reads).
        ctx_val: optional validation poses, whose predictions :meth:`condition` judges.
        threads: torch threads while computing (restored afterwards).
    """

    def __init__(self, eff: GPCorrection, ctx: Context, ctx_val: Context | None = None, threads: int = 1):
        self.eff, self.threads = eff, int(threads)
        with torch_threads(self.threads), torch.no_grad():
            h, z = eff.hyper(), eff.inducing
            self.x = eff.inputs(ctx)
            m, n = len(z), len(self.x)
            self.s = h["noise"].sqrt()
            self.A = self.chol_b = None
            if eff.exact:  # the inducing inputs are the rows: one factor of K + sigma^2 I, as _posterior has it
                self.chol_uu = _exact_factor(eff, self.x)
            else:  # as _posterior, so that conditioning on the outputs the GP was fitted to gives its own weights
                self.chol_uu = _chol(_square_kernel(eff, z), _JITTER * _prior_var(h, eff.ard))
                B = torch.eye(m, dtype=F64, device=z.device)
                keep = m * n <= _KEEP_FACTOR
                blocks = []
                for A_i, AA in _in_order(self._block_and_square, range(0, n, _BLOCK)):
                    B += AA
                    if keep:
                        blocks.append(A_i)
                self.A = torch.cat(blocks, 1) if keep and blocks else None
                self.chol_b = _chol(B, torch.tensor(0.0, dtype=F64, device=B.device))
            self.Kvu = self.sd_val = None
            if ctx_val is not None:
                xv = eff.inputs(ctx_val)
                self.Kvu = torch.cat([eff._kxu(xv[i : i + _BLOCK]) for i in range(0, len(xv), _BLOCK)])
                # the predictive standard deviation of a new observation (standardised): it depends on the inputs only
                var = _latent_var(_prior_var(h, eff.ard), self.Kvu, self.chol_uu, self.chol_b) + h["noise"]
                self.sd_val = var.sqrt().unsqueeze(1)

    def _block(self, i: int) -> Tensor:
        """Rows ``i .. i + block`` of ``A = L_uu^-1 K_uf / sigma`` as an ``(m, block)`` matrix."""
        eff = self.eff
        Kuf = _kernel(eff.inducing, self.x[i : i + _BLOCK], eff.hyper(), eff.periodic, eff.ard)
        return torch.linalg.solve_triangular(self.chol_uu, Kuf, upper=False) / self.s

    def _block_and_square(self, i: int) -> tuple[Tensor, Tensor]:
        A = self._block(i)
        return A, A @ A.T

    def condition(self, y: Tensor, y_val: Tensor | None = None) -> tuple[GPCorrection, dict]:
        """The GP conditioned on corrections ``y (n, 3)`` [m, robot base frame] at the poses of ``ctx``.

        Returns:
            A new :class:`GPCorrection` (``eff`` is left unchanged) and, with ``y_val`` at the validation poses,
            ``{"val_errors" (n_val,) [m], "val_rmse_m", "val_coverage_2sigma"}`` as :func:`fit_gp_correction`.
        """
        if y.ndim != 2 or y.shape[1] != 3 or len(y) != len(self.x):
            raise ShapeError(f"GP conditioning: expected y of shape ({len(self.x)}, 3), got {tuple(y.shape)}")
        eff = self.eff
        new = GPCorrection(eff.dof, len(eff.inducing), eff.extras, eff.additive, eff.ard, eff.exact)
        new = new.to(eff.inducing.device)
        out: dict = {}
        with torch_threads(self.threads), torch.no_grad():
            y = y.to(F64)
            for name in ("x_offset", "x_scale", "inducing", *eff.hyper()):
                getattr(new, name).copy_(getattr(eff, name))
            new.y_mean.copy_(y.mean(0))
            new.y_scale.copy_((y - new.y_mean).square().mean(0).sqrt().clamp_min(1e-12))
            ys = (y - new.y_mean) / new.y_scale
            if eff.exact:
                new.weights.copy_(torch.cholesky_solve(ys, self.chol_uu))
            else:
                if self.A is not None:
                    Ay = self.A @ ys
                else:
                    Ay = torch.zeros(len(eff.inducing), 3, dtype=F64, device=ys.device)
                    for i in range(0, len(ys), _BLOCK):
                        Ay += self._block(i) @ ys[i : i + _BLOCK]
                c = torch.cholesky_solve(Ay, self.chol_b) / self.s
                new.weights.copy_(torch.linalg.solve_triangular(self.chol_uu.T, c, upper=True))
                new.chol_b.copy_(self.chol_b)
            new.chol_uu.copy_(self.chol_uu)
            if y_val is not None and self.Kvu is not None:
                mean = self.Kvu @ new.weights * new.y_scale + new.y_mean
                d = y_val.to(F64) - mean
                e = d.norm(dim=-1)
                out = {
                    "val_errors": e,
                    "val_rmse_m": float(e.square().mean().sqrt()),
                    "val_coverage_2sigma": float((d.abs() <= 2 * self.sd_val * new.y_scale).double().mean()),
                }
        new.train(eff.training)
        return new, out


def _moved_block(gp: GPCorrection, xb: Tensor, i: int, moves: dict[int, list[Tensor]]) -> dict[int, list[Tensor]]:
    """:meth:`GPCorrection.moved_means` on the rows ``i:i + len(xb)`` (standardised inputs ``xb``): the kernel's
    terms at the rows once, then per move the changed variable's term and the ARD factor anew."""
    h, z, per = gp.hyper(), gp.inducing, [bool(v) for v in gp.periodic]

    def sq(d: Tensor, j: int) -> Tensor:
        return torch.sin(d.mul_(0.5), out=d).mul_(2.0).square_() if per[j] else d.square_()

    add_c = [float(-0.5 / v.square()) for v in h["add_len"]]
    add_v = [float(v) for v in h["add_var"]]
    D = [sq(xb[:, j : j + 1] - z[:, j].unsqueeze(0), j) for j in range(xb.shape[1])]
    K = torch.zeros_like(D[0]) if D else torch.zeros(len(xb), len(z), dtype=F64, device=xb.device)
    for j, Dj in enumerate(D):
        K.add_((Dj * add_c[j]).clamp_(min=_EXP_FLOOR).exp_(), alpha=add_v[j])
    if gp.ard:
        ard_c = [float(1.0 / v.square()) for v in h["ard_len"]]
        S = torch.zeros_like(K)
        for j, Dj in enumerate(D):
            S.add_(Dj, alpha=ard_c[j])
        A = (S * -0.5).clamp_(min=_EXP_FLOOR).exp_()
        K.add_(A, alpha=float(h["ard_var"]))
    base = K @ gp.weights
    out = {}
    Dn, dK = torch.empty_like(K), torch.empty_like(K)  # reused: a fresh block per move is mapped and zeroed anew
    for j, cols in moves.items():
        Ej = (D[j] * add_c[j]).clamp_(min=_EXP_FLOOR).exp_()
        zj = z[:, j].unsqueeze(0)
        means = []
        for col in cols:
            xj = (col[i : i + len(xb)] - gp.x_offset[j]) / gp.x_scale[j]
            sq(torch.sub(xj.unsqueeze(1), zj, out=Dn), j)
            torch.mul(Dn, add_c[j], out=dK).clamp_(min=_EXP_FLOOR).exp_().sub_(Ej).mul_(add_v[j])
            if gp.ard:
                An = Dn.sub_(D[j]).mul_(ard_c[j]).add_(S).mul_(-0.5).clamp_(min=_EXP_FLOOR).exp_()
                dK.add_(An.sub_(A), alpha=float(h["ard_var"]))
            means.append((base + dK @ gp.weights) * gp.y_scale + gp.y_mean)
        out[j] = means
    return out
