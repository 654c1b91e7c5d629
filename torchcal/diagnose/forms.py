"""What form does the effect at a localised variable take? Order selection by BIC.

At a variable found by :mod:`torchcal.diagnose.localise`, each form of a basis family is fitted by
linear least squares to the whitened residual, with the columns projected off the current model's
span (the same :class:`~torchcal.diagnose.localise.Workspace`), and scored by the Bayesian
information criterion ``BIC = n ln(RSS / n) + k ln n`` (``n = 3N`` observations, ``k`` parameters);
the form with the smallest BIC wins, ``none`` (no effect, ``k = 0``) included. The families:

* joint angle ``q_j`` (through the joint's Jacobian column): Fourier series, harmonics chosen by forward
  selection among orders ``1..10`` (each order adds a sine and a cosine), and the first-K series for
  comparison; polynomials ``q_j, q_j^2, .., q_j^D`` (degree 1 is a transmission-ratio error). A prismatic
  joint's reading [m] takes the polynomials alone (degree 1 is a scale error of its reading).
* gravity torque ``tau_j``: polynomials (degree 1 is compliance) and the sign step (backlash).
* flank ``flank_j``: the step (backlash).
* time ``t`` (additive translation in the tracker frame, one amplitude per axis): linear, polynomial, and
  the exponential warm-up ``A (1 - exp(-(t - t_0) / tau))``: ``tau`` by a one-dimensional profile
  (the amplitudes by linear least squares at each ``tau``, a log grid then golden-section refinement),
  its standard deviation from the curvature of the profile ``chi^2(tau) = RSS(tau) / s^2``,
  ``sigma_tau = sqrt(2 / chi^2''(tau))``.
* ``temperature`` and the probe position: polynomials.
* a joint angle times time (``q<j>_t``, the joint error changes over the campaign): the joint offset
  drifting linearly (``offset_drift``), harmonics of ``q_j`` whose size changes linearly in time (Fourier,
  forward selection) and polynomials of ``q_j`` times time. No effect class carries these yet: the loop
  reports them in ``unexplained`` with both variables.

Physical names (:data:`PHYSICAL`): Fourier in ``q_j`` -> ``cyclic`` (``params`` carry the harmonic
orders), polynomial in ``q_j`` -> ``transmission`` (:class:`~torchcal.effects.Transmission`), linear
in the gravity torque -> ``compliance``, a step -> ``backlash``, linear or exponential in ``t`` and
linear in ``temperature`` -> ``drift``. Any other form keeps ``kind = None``: structure with a form but
no effect class to carry it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal._threads import torch_threads
from torchcal.diagnose.localise import MAX_HARMONIC, Variable, Workspace
from torchcal.effects import Backlash, Compliance, Cyclic, Drift, MeasurementModel, Transmission
from torchcal.effects.base import Effect

Tensor = torch.Tensor
F64 = torch.float64

#: highest polynomial degree tried
MAX_DEGREE = 3

#: (variable basis, form) -> physical kind; forms not listed have no effect class
PHYSICAL = {
    ("fourier", "fourier"): "cyclic",
    ("fourier", "polynomial"): "transmission",
    ("slide", "polynomial"): "transmission",
    ("tau", "linear"): "compliance",
    ("tau", "step"): "backlash",
    ("flank", "step"): "backlash",
    ("t", "linear"): "drift",
    ("t", "exponential"): "drift",
    ("temperature", "linear"): "drift",
}


@dataclass
class FormFit:
    """One form fitted at the variable.

    Attributes:
        form: ``none``, ``fourier``, ``fourier_first``, ``polynomial``, ``linear``, ``exponential`` or ``step``.
        order: harmonic orders (Fourier), degree (polynomial), or None.
        k: parameters counted by the BIC (the time constant included).
        rss: weighted residual sum of squares after the fit; bic: the criterion.
        beta: coefficients ``(m,)``: [rad] per basis term for joint variables, [m] per axis for Cartesian ones.
        cov: their covariance ``(m, m)``, ``s^2 (X^T X)^-1`` with ``s^2 = RSS / (n - u - k)``.
        names: a name per coefficient.
        tau, tau_sigma: exponential form: time constant and its standard deviation (unit of the variable).
    """

    form: str
    order: list[int] | int | None
    k: int
    rss: float
    bic: float
    beta: Tensor = field(repr=False)
    cov: Tensor = field(repr=False)
    names: list[str] = field(default_factory=list)
    tau: float | None = None
    tau_sigma: float | None = None

    def row(self) -> dict:
        out = {"form": self.form, "order": self.order, "k": self.k, "rss": self.rss, "bic": self.bic}
        if self.tau is not None:
            out.update(tau=self.tau, tau_sigma=self.tau_sigma)
        return out


@dataclass
class FormChoice:
    """The form chosen at one variable, its BIC table and the physical kind it maps to."""

    variable: Variable
    best: FormFit
    table: list[FormFit]
    kind: str | None
    reference: float = 0.0  # t / temperature: the variable's value where the drift is zero
    scale: float = 1.0  # Cartesian polynomial forms: coefficients are per ((v - reference) / scale)^d

    @property
    def form(self) -> str:
        return self.best.form

    @property
    def order(self):
        return self.best.order

    def params(self) -> dict:
        """Coefficients with standard deviations, ``{name: {"value", "sigma"}}`` (plus ``tau``)."""
        b, sd = self.best.beta, self.best.cov.diagonal().clamp(min=0).sqrt()
        out = {n: {"value": float(b[i]), "sigma": float(sd[i])} for i, n in enumerate(self.best.names)}
        if self.best.tau is not None:
            out["tau"] = {"value": self.best.tau, "sigma": self.best.tau_sigma}
        return out

    def to_dict(self) -> dict:
        v = self.variable
        return {
            "variable": v.name,
            "joint": v.joint,
            "kind": self.kind,
            "form": self.form,
            "order": self.order,
            "params": self.params(),
            "reference": self.reference,
            "scale": self.scale,
            "criterion": "BIC = n ln(RSS/n) + k ln n",
            "bic_table": [f.row() for f in sorted(self.table, key=lambda f: f.bic)],
        }

    def effect(self, model: MeasurementModel) -> Effect | None:
        """An effect module carrying the chosen form, initialised at the estimate (None: no class fits)."""
        v, b = self.variable, self.best.beta.detach().clone()
        if self.kind == "cyclic":
            n = len(self.order)
            return Cyclic(v.joint, harmonics=list(self.order), a=b[:n], b=b[n:])
        if self.kind == "transmission":
            return Transmission(v.joint, degree=int(self.order), c=b)
        if self.kind == "compliance":
            return Compliance(v.joint, k=float(b[0]))
        if self.kind == "backlash":
            return Backlash(v.joint, b=2.0 * float(b[0]), source="auto")
        if self.kind == "drift":
            # tracker-frame translation -> the instrument drift's base-frame translation rates
            R = model.robot.T_tracker_base().detach()[:3, :3]
            a = R.T @ b[:3]
            if self.form == "exponential":
                rates = torch.cat([a / self.best.tau, torch.zeros(3, dtype=F64, device=a.device)])
                return Drift(
                    v.name, "instrument", rates=rates, reference=self.reference, form="exponential", tau=self.best.tau
                )
            return Drift(
                v.name,
                "instrument",
                rates=torch.cat([a / self.scale, torch.zeros(3, dtype=F64, device=a.device)]),
                reference=self.reference,
            )
        return None


def _family(var: Variable) -> str:
    if var.weight is not None:
        return "product"
    if var.basis == "fourier":
        return "fourier"
    if var.kind == "joint" and var.name.startswith("q"):  # a prismatic joint's reading (not periodic)
        return "slide"
    if var.name.startswith("tau"):
        return "tau"
    if var.name.startswith("flank"):
        return "flank"
    if var.name in ("t", "temperature"):
        return var.name
    return "position"


class _Fitter:
    def __init__(self, ws: Workspace, var: Variable):
        self.ws, self.var = ws, var
        self.n, self.ln_n = ws.n, math.log(ws.n)

    def cols(self, B: Tensor) -> Tensor:
        return self.ws.columns(self.var, B)

    def lsq(self, X: Tensor) -> tuple[Tensor, Tensor, float]:
        """Coefficients, unscaled covariance ``(X^T X)^-1`` and RSS of ``r ~ X``."""
        if X.shape[1] == 0:
            return X.new_zeros(0), X.new_zeros(0, 0), self.ws.rss0
        A = X.T @ X
        A = A + 1e-12 * A.diagonal().mean() * torch.eye(A.shape[0], dtype=F64, device=A.device)
        L = torch.linalg.cholesky(A)
        beta = torch.cholesky_solve((X.T @ self.ws.r)[:, None], L)[:, 0]
        rss = float((self.ws.r - X @ beta).square().sum())
        return beta, torch.cholesky_inverse(L), rss

    def bic(self, rss: float, k: int) -> float:
        return self.n * math.log(max(rss, 1e-300) / self.n) + k * self.ln_n

    def fit(self, form, order, X, names, extra_k: int = 0) -> FormFit:
        beta, covu, rss = self.lsq(X)
        k = X.shape[1] + extra_k
        s2 = rss / max(self.n - self.ws.u - k, 1)
        return FormFit(form, order, k, rss, self.bic(rss, k), beta, s2 * covu, names)


def _poly_basis(x: Tensor, degree: int) -> Tensor:
    return x[:, None] ** torch.arange(1, degree + 1, dtype=F64, device=x.device)


def _axes_names(prefix: str, orders) -> list[str]:
    """Names of Cartesian coefficients, axis-major as :meth:`Workspace.columns` lays them out."""
    return [f"{prefix}{o}_{c}" for c in "xyz" for o in orders]


def _fourier_forms(f: _Fitter, q: Tensor, max_harmonic: int) -> list[FormFit]:
    ks = list(range(1, max_harmonic + 1))
    cols = {k: f.cols(torch.stack([torch.sin(k * q), torch.cos(k * q)], dim=1)) for k in ks}

    def fit_set(sel: list[int], form: str) -> FormFit:
        sel = sorted(sel)
        X = torch.cat([cols[k][:, :1] for k in sel] + [cols[k][:, 1:] for k in sel], dim=1)
        names = [f"a{k}" for k in sel] + [f"b{k}" for k in sel]
        return f.fit(form, sel, X, names)

    out = [fit_set(list(range(1, K + 1)), "fourier_first") for K in ks]
    chosen: list[int] = []
    best_bic = f.bic(f.ws.rss0, 0)
    while len(chosen) < len(ks):
        trials = [fit_set(chosen + [k], "fourier") for k in ks if k not in chosen]
        step = min(trials, key=lambda t: t.rss)
        out.append(step)
        chosen = list(step.order)
        if step.bic > best_bic and len(chosen) >= 3:
            break  # two more orders past the BIC minimum cannot come back below it in practice
        best_bic = min(best_bic, step.bic)
    return out


def _exponential(f: _Fitter, t: Tensor, t0: float, n_grid: int = 48) -> FormFit:
    span = max(float(t.max() - t0), 1e-9)

    def rss_at(tau: float) -> float:
        e = -torch.expm1(-(t - t0) / tau)
        return f.lsq(f.cols(e[:, None]))[2]

    taus = torch.logspace(math.log10(span / 200), math.log10(span * 30), n_grid, dtype=F64).tolist()
    prof = [rss_at(tau) for tau in taus]
    i = min(range(n_grid), key=prof.__getitem__)
    lo, hi = math.log(taus[max(i - 1, 0)]), math.log(taus[min(i + 1, n_grid - 1)])
    g = (math.sqrt(5) - 1) / 2
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = rss_at(math.exp(c)), rss_at(math.exp(d))
    for _ in range(40):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = rss_at(math.exp(c))
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = rss_at(math.exp(d))
    tau = math.exp(0.5 * (a + b))
    e = -torch.expm1(-(t - t0) / tau)
    fit = f.fit("exponential", None, f.cols(e[:, None]), ["A_x", "A_y", "A_z"], extra_k=1)
    s2 = fit.rss / max(f.n - f.ws.u - fit.k, 1)
    h = 0.02 * tau
    curv = (rss_at(tau + h) - 2 * fit.rss + rss_at(tau - h)) / (h * h) / s2
    fit.tau = tau
    fit.tau_sigma = math.sqrt(2.0 / curv) if curv > 0 else float("inf")
    return fit


def identify_form(
    ws: Workspace, var: Variable, *, max_harmonic: int = MAX_HARMONIC, max_degree: int = MAX_DEGREE
) -> FormChoice:
    """Fit the forms of ``var``'s family (module docstring) and choose one by BIC.

    Args:
        ws: the residual workspace of the current fit (:func:`torchcal.diagnose.localise.workspace`).
        var: the localised variable.
    """
    with torch_threads(1):
        return _identify(ws, var, max_harmonic, max_degree)


def _identify(ws: Workspace, var: Variable, max_harmonic: int, max_degree: int) -> FormChoice:
    f = _Fitter(ws, var)
    x = var.values
    fam = _family(var)
    table = [
        FormFit("none", None, 0, ws.rss0, f.bic(ws.rss0, 0), torch.zeros(0, dtype=F64), torch.zeros(0, 0, dtype=F64))
    ]
    reference, scale = 0.0, 1.0
    if fam == "fourier":
        table += _fourier_forms(f, x, max_harmonic)
        for d in range(1, max_degree + 1):
            table.append(f.fit("polynomial", d, f.cols(_poly_basis(x, d)), [f"c{i}" for i in range(1, d + 1)]))
    elif fam == "slide":
        for d in range(1, max_degree + 1):
            table.append(f.fit("polynomial", d, f.cols(_poly_basis(x, d)), [f"c{i}" for i in range(1, d + 1)]))
    elif fam == "tau":
        table.append(f.fit("linear", 1, f.cols(x[:, None]), ["k"]))
        for d in range(2, max_degree + 1):
            table.append(f.fit("polynomial", d, f.cols(_poly_basis(x, d)), [f"c{i}" for i in range(1, d + 1)]))
        s = torch.sign(x)
        s = torch.where(s == 0, torch.ones_like(s), s)
        table.append(f.fit("step", None, f.cols(s[:, None]), ["half_width"]))
    elif fam == "flank":
        table.append(f.fit("step", None, f.cols(x[:, None]), ["half_width"]))
    elif fam == "product":
        table.append(f.fit("offset_drift", None, f.cols(torch.ones_like(x)[:, None]), ["rate"]))
        table += _fourier_forms(f, x, max_harmonic)
        for d in range(1, max_degree + 1):
            table.append(f.fit("polynomial", d, f.cols(_poly_basis(x, d)), [f"c{i}" for i in range(1, d + 1)]))
    else:
        reference = float(x[0]) if fam in ("t", "temperature") else 0.0
        u = x - reference
        if fam == "position":  # centred: a constant translation is the instrument's
            u = x - x.mean()
        # scaled to [-1, 1] so that powers of seconds stay well conditioned; coefficients are per (u / scale)^d
        scale = max(float(u.abs().max()), 1e-300)
        u = u / scale
        table.append(f.fit("linear", 1, f.cols(u[:, None]), _axes_names("rate", [1])))
        for d in range(2, max_degree + 1):
            table.append(f.fit("polynomial", d, f.cols(_poly_basis(u, d)), _axes_names("c", range(1, d + 1))))
        if fam == "t":
            table.append(_exponential(f, x, reference))
    best = min(table, key=lambda r: r.bic)
    if best.form == "fourier_first":  # the same model as the selected set; report it as a Fourier form
        best = FormFit("fourier", best.order, best.k, best.rss, best.bic, best.beta, best.cov, best.names)
    kind = PHYSICAL.get((fam, best.form))
    if kind == "compliance" and best.order != 1:
        kind = None
    return FormChoice(var, best, table, kind, reference, scale)


__all__ = ["FormChoice", "FormFit", "MAX_DEGREE", "PHYSICAL", "identify_form"]
