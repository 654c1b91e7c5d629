"""The predictive standard deviation of a calibrated model: how far a new measurement at a pose may lie from the
prediction (CONTRACT §3, ``sx, sy, sz``).

The parameter covariance (:func:`~torchcal.estimate.covariance.prediction_std`) and a learned model's posterior
(:func:`~torchcal.estimate.covariance.learned_std`) say how far the *model* may be off through what it fitted; a
new measurement also carries the instrument's noise, and whatever the model leaves unexplained (effects it lacks,
the joints' reading noise). The run measures that on its held-out rows, which no fit saw. Per axis ``a``::

    sigma_a(q)^2 = k^2 (J C J^T + s_learned^2 + s_noise^2 + u_a^2 + rho(q) (f_a^2 - u_a^2))

``u_a^2`` is the held-out rows' mean squared residual less the other terms there (a moment estimate, never
negative); ``f_a^2`` the same of the model without its parts that fade beyond the calibrated region (the learned
corrections, the open joint-angle forms). ``rho(q)`` in 0..1 carries the level from the model's inside to its far
outside by how the model extrapolates: beyond the region the fading parts are held at their edge and fade, while
what they stood for goes on varying. Both are measured on the model itself: ``1 - w(q)``, the share faded
(``w = exp(-d^2 / (2 FADE_LENGTH^2))``, ``d`` the extrapolation), and the variogram of the fading parts' correction
``c(q)`` along each joint, ``gamma_j(h) / var(c)`` (how far ``c`` moves over a step ``h`` of joint ``j`` inside the
region, as a share of its whole spread), at each joint's distance beyond its range; ``rho`` is the largest.
``k >= 1`` then widens it until 99 % of the held-out rows have all three ``|error| / sigma <= 3`` (a Gaussian's
share): real residuals have heavier tails than their second moment says.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass

import torch

from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.covariance import ParameterCovariance, combined_std

Tensor = torch.Tensor

#: the fewest held-out rows a level is measured on; fewer: the level is not measured and the sigma says so
MIN_ROWS = 10
#: the share of held-out rows whose three |error| / sigma must all be <= 3 (a Gaussian's: 0.9973^3)
COVERED = 0.99
#: what the stored levels may hold (a crafted model.json is refused before use) [m]
MAX_LEVEL = 10.0
#: the variogram's lags, as shares of each joint's range in the region
LAGS = (0.0, 0.01, 0.025, 0.05, 0.1, 0.2, 0.4, 0.8)
#: the most moved rows the variogram evaluates the model at in one batch (its memory; Series C's 42 moves of 555
#: held-out rows are one batch)
BATCH_ROWS = 32_768


@dataclass(frozen=True)
class Trust:
    """A model's predictive standard deviation beyond its parameters (module docstring), measured on held-out rows.

    Attributes:
        noise: the instrument's standard deviation per axis ``(3,)`` [m].
        inside: what the model leaves unexplained inside the calibrated region, per axis ``(3,)`` [m].
        far: the same far beyond it, where the fading parts are gone ``(3,)`` [m].
        scale: the factor ``k`` (>= 1).
        n: the held-out rows it was measured on.
        coverage: the share of those rows with all three ``|error| / sigma <= 3``.
        median_ratio: the median ``|error| / sigma`` over their axes.
        lags: per joint, the variogram's lags ``(dof, L)`` [rad or m] (empty: none measured, rho is the fade alone).
        rho: per joint, the variogram over the correction's variance at those lags ``(dof, L)``, in 0..1.
    """

    noise: tuple[float, float, float]
    inside: tuple[float, float, float]
    far: tuple[float, float, float]
    scale: float
    n: int
    coverage: float
    median_ratio: float
    lags: tuple[tuple[float, ...], ...] = ()
    rho: tuple[tuple[float, ...], ...] = ()

    def to_dict(self) -> dict:
        """model.json's and report.json's ``trust`` entry (metres)."""
        return {
            "noise_m": list(self.noise),
            "unexplained_m": list(self.inside),
            "unexplained_far_m": list(self.far),
            "scale": self.scale,
            "n_holdout": self.n,
            "coverage_3sigma": self.coverage,
            "median_ratio": self.median_ratio,
            "variogram": {"lag": [list(x) for x in self.lags], "rho": [list(x) for x in self.rho]},
        }

    @classmethod
    def from_dict(cls, d) -> Trust:
        """Rebuild from :meth:`to_dict`.

        Raises:
            ValueError: a key is missing or a value is not a finite number in range.
        """
        if not isinstance(d, dict):
            raise ValueError("must be an object")

        def axes(key: str) -> tuple[float, float, float]:
            v = d.get(key)
            if not (isinstance(v, list) and len(v) == 3 and all(_number(x, 0.0, MAX_LEVEL) for x in v)):
                raise ValueError(f"{key} must be three numbers in 0..{MAX_LEVEL:g}")
            return float(v[0]), float(v[1]), float(v[2])

        scale, n = d.get("scale"), d.get("n_holdout")
        if not _number(scale, 1.0, 1e6):
            raise ValueError("scale must be a number >= 1")
        if not (isinstance(n, int) and not isinstance(n, bool) and n >= 0):
            raise ValueError("n_holdout must be a whole number")
        cov, med = d.get("coverage_3sigma"), d.get("median_ratio")
        lags, rho = _variogram(d.get("variogram"))
        return cls(
            axes("noise_m"),
            axes("unexplained_m"),
            axes("unexplained_far_m"),
            float(scale),
            n,
            float(cov) if _number(cov, 0.0, 1.0) else math.nan,
            float(med) if _number(med, 0.0, math.inf) else math.nan,
            lags,
            rho,
        )

    def std(self, model: MeasurementModel, ctx: Context, cov: ParameterCovariance | None) -> Tensor:
        """The predictive standard deviation ``(N, 3)`` [m] of ``model`` at ``ctx`` (module docstring)."""
        var = base_variance(model, ctx, cov, self.noise)
        inside = var.new_tensor(self.inside).square()
        far = var.new_tensor(self.far).square()
        lost = self.beyond(model, ctx.q)[:, None]
        return self.scale * (var + inside + lost * (far - inside).clamp(min=0)).sqrt()

    def beyond(self, model: MeasurementModel, q: Tensor) -> Tensor:
        """``rho`` ``(N,)`` (module docstring): 0 inside the region, towards 1 far beyond it."""
        rho = 1.0 - fade_weight(model, q)
        if model.region is None or not self.lags or len(self.lags) != q.shape[1]:
            return rho
        lo, hi = model.region[0].to(q), model.region[1].to(q)
        d = torch.maximum(lo - q, q - hi).clamp(min=0)  # (N, dof) each joint's distance beyond its range
        for j, (lag, r) in enumerate(zip(self.lags, self.rho)):
            rho = torch.maximum(rho, _interp(d[:, j], q.new_tensor(lag), q.new_tensor(r)))
        return rho.clamp(0.0, 1.0)


def _interp(x: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    """Piecewise-linear ``fp(xp)`` at ``x`` (``xp`` increasing), held at its ends."""
    if len(xp) == 1 or float(xp[-1]) <= 0:
        return fp[-1].expand_as(x)
    i = torch.searchsorted(xp, x.clamp(float(xp[0]), float(xp[-1]))).clamp(1, len(xp) - 1)
    x0, x1, f0, f1 = xp[i - 1], xp[i], fp[i - 1], fp[i]
    t = ((x - x0) / (x1 - x0).clamp(min=1e-300)).clamp(0.0, 1.0)
    return f0 + t * (f1 - f0)


def _variogram(v) -> tuple[tuple[tuple[float, ...], ...], tuple[tuple[float, ...], ...]]:
    """model.json's ``variogram`` (absent: none)."""
    if v is None:
        return (), ()
    lags, rho = (v.get("lag"), v.get("rho")) if isinstance(v, dict) else (None, None)
    ok = isinstance(lags, list) and isinstance(rho, list) and len(lags) == len(rho) <= 64
    ok = ok and all(isinstance(a, list) and isinstance(b, list) and len(a) == len(b) <= 64 for a, b in zip(lags, rho))
    ok = ok and all(_number(x, 0.0, 1e6) for a in lags for x in a) and all(_number(x, 0.0, 1.0) for b in rho for x in b)
    if not ok or any(list(a) != sorted(a) for a in lags):
        raise ValueError("variogram must hold lag and rho lists per joint (lags increasing, rho in 0..1)")
    return tuple(tuple(float(x) for x in a) for a in lags), tuple(tuple(float(x) for x in b) for b in rho)


def correction_variogram(model: MeasurementModel, ctx: Context) -> tuple[tuple, tuple]:
    """The variogram of the fading parts' correction ``c(q)`` (the model minus :func:`without_fading`) along each
    joint, over its variance (module docstring), from the poses ``ctx`` inside the region: each pose's joint ``j``
    moved by the lag, up or down, whichever stays in the region. Empty where the model has no fading part or no
    region."""
    far = without_fading(model)
    if model.region is None or len(far.effects) == len(model.effects):
        return (), ()
    lo, hi = model.region[0].to(ctx.q), model.region[1].to(ctx.q)

    def c(sub: Context) -> Tensor:
        return model(sub) - far(sub)

    with torch.no_grad():
        c0 = c(ctx)
        var = float((c0 - c0.mean(0)).square().sum(1).mean())
        if not var > 0:
            return (), ()
        lags = [[f * float(hi[j] - lo[j]) for f in LAGS] for j in range(ctx.q.shape[1])]
        moves = {j: [_moved(ctx.q[:, j], h, lo[j], hi[j]) for h in lag[1:]] for j, lag in enumerate(lags)}
        g = _moved_gammas(model, ctx, moves, c, c0)
        rhos = []
        for j, lag in enumerate(lags):
            rho = [0.0]
            for k in range(len(lag) - 1):
                rho.append(rho[-1] if g[j][k] is None else max(rho[-1], min(1.0, g[j][k] / var)))
            rhos.append(tuple(rho))
    return tuple(tuple(lag) for lag in lags), tuple(rhos)


def _moved_gammas(model: MeasurementModel, ctx: Context, moves: dict, c, c0: Tensor) -> dict[int, list]:
    """Half the mean squared change of ``c`` from ``c0`` (at ``ctx``) over each move's rows (``moves[j]``: per lag
    the moved readings of joint ``j`` and which stay in the region; None where none does): every move's rows in one
    evaluation of the model (each row's prediction is its own), a learned GP's mean there from its kernel at ctx."""
    gps = _gp_means(model, ctx, {j: [col for col, _ in m] for j, m in moves.items()})
    parts = []  # (j, k, rows, moved readings)
    for j, m in moves.items():
        for k, (col, ok) in enumerate(m):
            if bool(ok.any()):
                rows = torch.nonzero(ok).flatten()
                q = ctx.q[rows].clone()
                q[:, j] = col[rows]
                parts.append((j, k, rows, q))
    out: dict[int, list] = {j: [None] * len(m) for j, m in moves.items()}
    for batch in _batches(parts, BATCH_ROWS):
        rows = torch.cat([r for _, _, r, _ in batch])
        moved = dataclasses.replace(ctx.subset(rows), q=torch.cat([q for *_, q in batch]))
        for gp, means in gps:
            gp.prime(moved, torch.cat([means[j][k][r] for j, k, r, _ in batch]))
        d = (c(moved) - c0[rows]).square().sum(1)
        sizes = [len(r) for _, _, r, _ in batch]
        for (j, k, _, _), dk in zip(batch, torch.split(d, sizes)):
            out[j][k] = 0.5 * float(dk.mean())
    return out


def _batches(parts: list, rows: int) -> list[list]:
    """``parts`` (each with its rows third) in consecutive batches of about ``rows`` rows (at least one part each)."""
    out, n = [], rows
    for p in parts:
        if n + len(p[2]) > rows:
            out.append([])
            n = 0
        out[-1].append(p)
        n += len(p[2])
    return out


def _moved(q: Tensor, h: float, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """One joint's readings ``q`` ``(N,)`` moved by ``h``, up where that stays in ``lo..hi``, else down, and whether
    the moved reading is in the region."""
    up = q + h <= hi
    col = torch.where(up, q + h, q - h)
    return col, up | (col >= lo)


def _gp_means(model: MeasurementModel, ctx: Context, moves: dict) -> list:
    """Each learned GP of ``model`` with its means at the moved rows (:meth:`~torchcal.effects.gp.GPCorrection.
    moved_means`): a few exponentials per move where evaluating the GP anew takes one per variable."""
    from torchcal.effects.gp import GPCorrection

    return [(e, e.moved_means(ctx, moves)) for e in model.effects if isinstance(e, GPCorrection) and len(e.inducing)]


def _number(x, lo: float, hi: float) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and lo <= x <= hi


def fade_weight(model: MeasurementModel, q: Tensor) -> Tensor:
    """How much of the model's fading parts is left at ``q`` ``(N,)``: 1 inside the calibrated region, falling with
    the extrapolation as the parts themselves fall (:data:`~torchcal.effects.joint.FADE_LENGTH`)."""
    from torchcal.effects.joint import FADE_LENGTH

    d = model.extrapolation(q.detach())
    return torch.exp(-0.5 * (d / FADE_LENGTH) ** 2)


def without_fading(model: MeasurementModel) -> MeasurementModel:
    """A copy of ``model`` as it predicts far beyond its region: without its learned corrections and its open
    joint-angle forms (the parts that fade to the geometry there)."""
    from torchcal.effects.joint import RegionForm

    def fades(e) -> bool:
        return e.kind == "learned" or (isinstance(e, RegionForm) and e.region is not None and not e._unbounded())

    # the fading parts are not copied (a GP's posterior holds tens of megabytes): the copy's memo takes them as None
    gone = [e for e in model.effects if fades(e)]
    out = copy.deepcopy(model, {id(e): None for e in gone})
    out.effects = torch.nn.ModuleList([e for e in out.effects if e is not None])
    return out


def base_variance(
    model: MeasurementModel, ctx: Context, cov: ParameterCovariance | None, noise: tuple[float, float, float]
) -> Tensor:
    """The variance ``(N, 3)`` [m^2] the parameters, the learned posterior and the instrument's noise give."""
    s = combined_std(model, ctx, cov)
    n = ctx.q.new_tensor(noise).square().expand(len(ctx.q), 3)
    return n if s is None else n + s.square()


#: the level at which a few held-out rows bound the scale of the sigma (:class:`FewRows`): a scale outside the bounds
#: would have given errors this unlikely (each tail); what the words on stderr say (over- or understated)
FEW_ROWS_ALPHA = 0.005
#: the level of the scale the sigma uses (:attr:`FewRows.scale`): the largest the rows allow at this level, a one-sided
#: upper confidence bound (with no level measured, the parameters' sigma is a floor, not an estimate)
FEW_ROWS_COVER = 0.05


@dataclass(frozen=True)
class FewRows:
    """What fewer than :data:`MIN_ROWS` held-out rows can tell of the sigma the parameters, the learned posterior and
    the instrument's noise give (``sigma_0``): not a level, but bounds on its scale. With ``sigma = k sigma_0`` the
    rows' ``T = sum e^2 / sigma_0^2`` over their ``3n`` axes is ``k^2 chi2_3n``; a ``k`` above ``sqrt(T / chi2_3n(a))``
    (the lower ``a`` quantile, :data:`FEW_ROWS_ALPHA`) would have given errors that small with probability below
    ``a``, one below ``sqrt(T / chi2_3n(1 - a))`` errors that large: these bounds say which way ``sigma_0`` is off.
    The sigma uses ``k = sqrt(T / chi2_3n(c))`` (:data:`FEW_ROWS_COVER`), the largest scale the rows allow at ``c``:
    ``sigma_0`` holds no level for what the model leaves unexplained (too few rows to measure one), so it is a floor,
    and a few rows that happen to miss little must not make it one (``k >= 1`` unless the rows reject ``sigma_0`` as
    too large); a covariance 50 times the errors (poorly determined parameters, seven held-out rows) comes down to
    what the rows allow, one the errors exceed goes up.
    Where ``sigma_0`` is right the scale is about ``sqrt(3n / chi2_3n(c))`` (1.3 for 8 rows): the median
    ``|error| / sigma`` about 0.5.

    Attributes:
        noise: the instrument's standard deviation per axis ``(3,)`` [m].
        low, high: the bounds on ``k``.
        n: the held-out rows.
        median_ratio: the median ``|error| / sigma_0`` over their axes.
    """

    noise: tuple[float, float, float]
    low: float
    high: float
    n: int
    median_ratio: float

    @property
    def scale(self) -> float:
        """The ``k`` the sigma uses: ``sqrt(T / chi2_3n(c))`` (class docstring), from the bounds (``T = low^2
        chi2_3n(1 - a)``)."""
        from torchcal.stats import chi2_quantile

        k = 3 * self.n
        T = self.low**2 * chi2_quantile(1.0 - FEW_ROWS_ALPHA, k)
        upper = max(math.sqrt(T / chi2_quantile(FEW_ROWS_COVER, k)), 1e-12)
        return upper if self.high < 1.0 else max(upper, 1.0)  # below the floor only where the rows reject it

    @property
    def direction(self) -> str:
        """``"overstates"`` (``sigma_0`` above what the rows allow), ``"understates"`` or ``"consistent"``."""
        return "overstates" if self.high < 1.0 else "understates" if self.low > 1.0 else "consistent"

    def note(self) -> str:
        """What the sigma is and which way ``sigma_0`` is off, in words that agree with the rows."""
        head = (
            f"was measured on only {self.n} held-out rows (a level needs {MIN_ROWS}): the parameters' and the learned "
            f"model's uncertainty with the instrument's noise"
        )
        k = f"{self.scale:.3g}, the largest scale the rows allow at {FEW_ROWS_COVER:.0%} (no level measured)"
        if self.direction == "overstates":
            words = (
                f" overstate the error (the rows' errors are a median {self.median_ratio:.2g} of it); sx, sy, sz are "
                f"scaled down by {k}"
            )
        elif self.direction == "understates":
            words = (
                f" understate the error (the rows' errors are a median {self.median_ratio:.2g} of it); sx, sy, sz are "
                f"scaled up by {k}"
            )
        else:
            words = (
                f", which the rows' errors (a median {self.median_ratio:.2g} of it) neither bound above nor below "
                f"(scale {self.low:.3g} to {self.high:.3g}): sx, sy, sz are scaled by {k}"
            )
        return head + words + f"; hold out {MIN_ROWS} rows or more for a measured sigma"

    def std(self, model: MeasurementModel, ctx: Context, cov: ParameterCovariance | None) -> Tensor:
        """The predictive standard deviation ``(N, 3)`` [m]: ``k sigma_0``."""
        return self.scale * base_variance(model, ctx, cov, self.noise).sqrt()

    def to_dict(self) -> dict:
        return {
            "noise_m": list(self.noise),
            "scale": self.scale,
            "scale_bounds": [self.low, self.high],
            "direction": self.direction,
            "n_holdout": self.n,
            "median_ratio": self.median_ratio,
        }

    @classmethod
    def from_dict(cls, d) -> FewRows:
        """Rebuild from :meth:`to_dict`.

        Raises:
            ValueError: a key is missing or a value is not a finite number in range.
        """
        if not isinstance(d, dict):
            raise ValueError("must be an object")
        noise, bounds, n, med = d.get("noise_m"), d.get("scale_bounds"), d.get("n_holdout"), d.get("median_ratio")
        if not (isinstance(noise, list) and len(noise) == 3 and all(_number(x, 0.0, MAX_LEVEL) for x in noise)):
            raise ValueError(f"noise_m must be three numbers in 0..{MAX_LEVEL:g}")
        if not (isinstance(bounds, list) and len(bounds) == 2 and all(_number(x, 0.0, 1e6) for x in bounds)):
            raise ValueError("scale_bounds must be two numbers in 0..1e6")
        if not (bounds[0] <= bounds[1] and bounds[1] > 0):
            raise ValueError("scale_bounds must be [low, high] with 0 < high and low <= high")
        if not (isinstance(n, int) and not isinstance(n, bool) and 0 < n < MIN_ROWS):
            raise ValueError(f"n_holdout must be a whole number from 1 to {MIN_ROWS - 1}")
        return cls(
            (float(noise[0]), float(noise[1]), float(noise[2])),
            float(bounds[0]),
            float(bounds[1]),
            n,
            float(med) if _number(med, 0.0, math.inf) else math.nan,
        )


def few_rows(
    model: MeasurementModel,
    cov: ParameterCovariance | None,
    ctx: Context,
    p: Tensor,
    noise: tuple[float, float, float],
) -> FewRows | None:
    """:class:`FewRows` on ``1 <= n < MIN_ROWS`` held-out rows (poses ``ctx``, measured positions ``p`` ``(n, 3)``
    [m]); None for other counts (none to tell, or enough for :func:`fit_trust`)."""
    from torchcal.stats import chi2_quantile

    n = len(p)
    if not 0 < n < MIN_ROWS:
        return None
    with torch.no_grad():
        var = base_variance(model, ctx, cov, noise)
        e = model(ctx) - p
    z2 = e.square() / var.clamp(min=1e-300)
    T, k = float(z2.sum()), 3 * n
    low = math.sqrt(T / chi2_quantile(1.0 - FEW_ROWS_ALPHA, k))
    high = math.sqrt(T / chi2_quantile(FEW_ROWS_ALPHA, k))
    return FewRows(tuple(float(x) for x in noise), low, max(high, 1e-12), n, float(z2.sqrt().median()))


def fit_trust(
    model: MeasurementModel,
    cov: ParameterCovariance | None,
    ctx: Context,
    p: Tensor,
    noise: tuple[float, float, float],
    variogram: tuple[tuple, tuple] | None = None,
) -> Trust | None:
    """Measure :class:`Trust` on held-out rows: their poses ``ctx`` and measured positions ``p`` ``(N, 3)`` [m].

    ``variogram``: :func:`correction_variogram` of this model at ``ctx`` where the caller has it (it depends on the
    model and the poses only, not on ``cov``); computed here otherwise.

    Returns:
        None where fewer than :data:`MIN_ROWS` rows are given.
    """
    if len(p) < MIN_ROWS:
        return None
    lags, rho = correction_variogram(model, ctx) if variogram is None else variogram
    with torch.no_grad():
        var = base_variance(model, ctx, cov, noise)
        e = model(ctx) - p
        e_far = without_fading(model)(ctx) - p
    inside = (e.square() - var).mean(0).clamp(min=0)
    far = torch.maximum((e_far.square() - var).mean(0).clamp(min=0), inside)
    z = e.abs() / (var + inside).sqrt()
    worst = z.amax(dim=1)
    scale = max(1.0, float(torch.quantile(worst, COVERED)) / 3.0)
    return Trust(
        tuple(float(x) for x in noise),
        tuple(float(x) for x in inside.sqrt()),
        tuple(float(x) for x in far.sqrt()),
        scale,
        len(p),
        float((worst / scale <= 3.0).double().mean()),
        float((z / scale).median()),
        lags,
        rho,
    )
