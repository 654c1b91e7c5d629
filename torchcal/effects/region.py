"""A learned correction that knows where it has seen data.

A network or kernel fitted along a trajectory has seen a thin tube of joint space around that path. Where a later
path leaves the tube, its output is an extrapolation, and a tanh network extrapolates as confidently as it
interpolates. :class:`RegionGate` wraps such an effect and fades its correction towards zero, i.e. back to the
geometric model, with the distance from the training joints:

    ``dp_gated(q) = g(d(q)) * dp(q)``,  ``d(q) = min_i || (q - q_i) / s ||``,  ``g(d) = exp(-d^2 / (2 l^2))``

with ``q_i`` the training joints, the correction's calibrated region (thinned to at most ``max_points`` of them),
``s`` the joints' spread on the training data (so one length fits all joints) and ``l`` the gate's length, chosen
on validation data that continue the training path (:func:`choose_gate_length`). At a training sample ``d = 0`` and
the gate is 1, so wrapping an already fitted effect leaves the training fit unchanged; ``l = inf`` switches the
gate off. The gate is how the correction fades beyond its region, as an open joint form fades beyond its joint's
(:data:`torchcal.effects.joint.FADE_LENGTH`); runs written when the region was called ``support`` (the class
``SupportGate``, its config's ``n_support`` and its state's ``support``) load under the new names.

With a ``fallback`` robot (the kinematic calibration's geometry) the whole prediction fades to that geometry, not
only the learned correction: a filter that estimated its own geometry together with the network (the adaptive
engine) has a geometry that is only right together with its network, so away from the training joints

    ``y(q) = g * y_model(q) + (1 - g) * y_fallback(q)``

(tracker frame), which the gate writes as a position correction in the model's base frame. The model must then have
no other effects (the integrated method's models have none).

*Predictive standard deviation* (:meth:`RegionGate.set_predictive`, :func:`predictive_sigma`). Where the inner
effect is a network whose weights a filter estimated (covariance ``P_w`` of the weights in its state), the
gate predicts a standard deviation per sample and tracker axis ``a``. The gated prediction is ``g y_model +
(1 - g) y_fallback``, so its error is ``g e_model + (1 - g) e_fallback`` exactly; with the two errors independent

    ``var_a(q) = g^2 [k^2 (J_a(q) P_w J_a(q)^T + s_noise_a^2) + f_a^2 + (1 - h^2) s_far_a^2]
    + (1 - g)^2 s_fb_a^2 (1 + c d^2)``

with ``g`` the gate of the prediction (1 everywhere for an infinite gate), ``J = R dnet/dw`` the network's output
Jacobian rotated into the tracker frame, ``s_noise`` the measurement noise (tracker and joint noise at the probe)
and ``k`` and the floor ``f`` (per axis) fitted on validation samples by maximum likelihood
(:func:`fit_predictive_scale`): the filter treats the network's misfit as white noise, so ``P_w`` alone says
little about the error along a new stretch of path (its shape is mostly the prior's), and a model refitted on more
samples has a smaller ``P_w`` but not a smaller misfit: the floor carries the misfit the validation block showed.
Both are then widened (never narrowed) to a target coverage, over the validation residuals and, where given, the
refitted model's residuals on held-out samples (:func:`calibrate_factor`).
The model's own error grows away from its region towards its fallback's residual scale on samples after that fallback's
fitting samples ``s_far`` (the integrated method: geometry's on its validation block, or the kinematic calibration's on
the held-out samples), with ``h = exp(-d^2 / (2 l_s^2))`` of length ``sigma_length`` (the gate's own when it is finite):
a network extrapolates no better than geometry does. The fallback's error ``s_fb (1 + c d^2)^(1/2)`` grows with the
distance too: fitted on the geometric model's residuals on samples after the ones it was fitted on, at their distance
from those (:func:`fit_fallback_growth`), since geometry fitted along one stretch of path leaves less of the field there
than further away; where the fallback itself (geometry on all training samples) has residuals on samples it was not
fitted on, those size ``s_fb`` with the growth's shape kept (:func:`fit_fallback_scale`): it is better determined than
the refits the growth comes from. Without a fallback fit (``c = 0``, ``s_fb = s_far``), far from a finite gate's region
the variance is ``s_far^2``. :mod:`torchcal.effects.predictive` calibrates these parts on a model's residuals.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

from torchcal import _console, _lbfgs
from torchcal.effects.base import Context, Effect

Tensor = torch.Tensor

#: lengths tried by :func:`choose_gate_length`, in units of the joints' training spread (inf: no gate): a factor 2
#: apart from lengths where the gate barely acts (a path's continuation a few spreads away) down to one that keeps
#: the correction only on the training tube itself
GATE_LENGTHS = (math.inf, 8.0, 4.0, 2.0, 1.0, 0.5, 0.25, 0.12, 0.06)


class RegionGate(Effect):
    """Wrap a Cartesian correction ``inner`` so that it fades to zero away from the training joints.

    Args:
        inner: the fitted effect (``acts_on`` must be ``"cartesian"``: a position correction).
        region: the training joints, the region the correction was fitted on ``(M, dof)`` [rad]; thinned to
            ``max_points`` evenly spaced rows.
        length: gate length in units of the joints' spread (``inf`` or None: no gate).
        max_points: most region points kept (the distance costs ``N * M * dof``).
        fallback: the robot the prediction fades to (module docstring), or None (the correction fades to zero).
        fallback_in_base: the fallback's instrument pose is its placement relative to this model's base frame
            (:meth:`fallback_to_base`: a re-stationed run), not a tracker pose.
        predictive: ``config()["predictive"]`` of a saved gate with a predictive standard deviation: sizes its
            buffers for ``load_state_dict`` (:meth:`set_predictive` sets them on a new gate).
    """

    kind = "learned"
    acts_on = "cartesian"
    renamed = {"support": "region", "n_support": "n_region"}

    def __init__(
        self,
        inner: Effect,
        region: Tensor,
        length: float | None = math.inf,
        *,
        max_points: int = 3000,
        fallback=None,
        predictive: dict | None = None,
        fallback_in_base: bool = False,
    ):
        super().__init__(joint=None)
        if inner.acts_on != "cartesian":
            raise ValueError(f"RegionGate wraps a position correction; {type(inner).__name__} acts on {inner.acts_on}")
        if region.ndim != 2 or len(region) == 0:
            raise ValueError(f"region must have shape (M, dof) with M > 0, got {tuple(region.shape)}")
        self.inner = inner
        stride = max(1, math.ceil(len(region) / max_points))
        kept = region[::stride].detach().clone()
        self.register_buffer("region", kept)
        spread = kept.std(dim=0) if len(kept) > 1 else torch.ones(kept.shape[1], dtype=kept.dtype, device=kept.device)
        self.register_buffer("spread", spread.clamp(min=1e-3))
        self.length = math.inf if length is None else float(length)  # None: no gate (how config() writes inf)
        self.fallback = fallback
        self.fallback_in_base = bool(fallback_in_base) and fallback is not None
        if fallback is not None:
            for p in fallback.parameters():
                p.requires_grad_(False)
        # the predictive standard deviation (module docstring): its buffers exist only once set_predictive ran, or
        # sized from ``predictive`` (the config's entry) when a saved gate is rebuilt, so that load_state_dict fills
        # them; a gate without one keeps the state dict of earlier runs
        self.sigma_scale, self.sigma_length, self.sigma_floor = 1.0, math.inf, [0.0, 0.0, 0.0]
        self.sigma_fallback, self.fallback_growth = None, 0.0
        if predictive is not None:
            n_w, z = int(predictive["n_weights"]), torch.zeros(3, dtype=kept.dtype, device=kept.device)
            self.set_predictive(
                torch.zeros(n_w, n_w, dtype=kept.dtype, device=kept.device),
                torch.zeros(n_w, dtype=torch.long, device=kept.device),
                z,
                z,
                float(predictive["sigma_length"]),
                float(predictive["scale"]),
                predictive.get("floor"),
                predictive.get("fallback_sigma"),
                float(predictive.get("fallback_growth", 0.0)),
            )

    @property
    def has_predictive(self) -> bool:
        """Whether the gate has a predictive standard deviation (:meth:`set_predictive`)."""
        return "sigma_noise" in self._buffers

    def set_predictive(
        self,
        weight_cov: Tensor,
        weight_index: Tensor,
        sigma_noise: Tensor,
        sigma_far: Tensor,
        sigma_length: float,
        scale: float = 1.0,
        floor: Sequence[float] | None = None,
        fallback_sigma: Sequence[float] | None = None,
        fallback_growth: float = 0.0,
    ) -> None:
        """Give the gate a predictive standard deviation (module docstring).

        Args:
            weight_cov: covariance of the network's weights in the filter's state ``(k, k)`` [the net's units].
            weight_index: their indices in the network's flat weights ``(k,)``.
            sigma_noise: measurement noise per tracker axis ``(3,)`` [m].
            sigma_far: residual scale of the fallback (geometric) model per tracker axis ``(3,)`` [m].
            sigma_length: the gate length the standard deviation fades with (finite).
            scale: the calibration factor ``k`` of the network's and the noise's variance.
            floor: the misfit floor ``f`` per tracker axis ``(3,)`` [m] (default 0).
            fallback_sigma: the fallback's residual scale at the region ``s_fb`` per tracker axis ``(3,)`` [m]
                (default ``sigma_far``).
            fallback_growth: its growth ``c`` with the squared distance [1 / spread^2] (default 0: constant).
        """
        if not hasattr(self.inner, "net"):
            raise ValueError(f"a predictive standard deviation needs a network inside; got {type(self.inner).__name__}")
        k = len(weight_index)
        if weight_cov.shape != (k, k) or sigma_noise.shape != (3,) or sigma_far.shape != (3,):
            raise ValueError(
                f"weight_cov must be ({k}, {k}) and sigma_noise, sigma_far (3,); got {tuple(weight_cov.shape)}, "
                f"{tuple(sigma_noise.shape)}, {tuple(sigma_far.shape)}"
            )
        if not math.isfinite(sigma_length) or sigma_length <= 0:
            raise ValueError(f"sigma_length must be finite and positive, got {sigma_length}")
        self.register_buffer("weight_cov", weight_cov.detach().clone().to(self.region))
        self.register_buffer("weight_index", weight_index.detach().clone().long().to(self.region.device))
        self.register_buffer("sigma_noise", sigma_noise.detach().clone().to(self.region))
        self.register_buffer("sigma_far", sigma_far.detach().clone().to(self.region))
        self.sigma_length = float(sigma_length)
        self.sigma_scale = float(scale)
        self.sigma_floor = [0.0, 0.0, 0.0] if floor is None else [float(f) for f in floor]
        self.sigma_fallback = None if fallback_sigma is None else [float(x) for x in fallback_sigma]
        if fallback_growth < 0 or not math.isfinite(fallback_growth):
            raise ValueError(f"fallback_growth must be finite and non-negative, got {fallback_growth}")
        self.fallback_growth = float(fallback_growth)

    def variance_parts(self, robot, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The parts of the predictive variance (module docstring), each ``(N, 3)`` [m^2] (tracker axes):
        ``a = g^2 (J P_w J^T + s_noise^2)``, ``b = g^2 (1 - h^2) s_far^2 + (1 - g)^2 s_fb^2 (1 + c d^2)`` and the
        prediction's gate squared ``g^2`` (broadcast to the axes); ``var = k^2 a + g^2 f^2 + b``."""
        if not self.has_predictive:
            raise ValueError("this gate has no predictive standard deviation (set_predictive was not called)")
        net = self.inner.net
        R = robot.T_tracker_base()[:3, :3].detach()
        w = net.flat().detach()
        var_net = torch.empty(len(q), 3, dtype=q.dtype, device=q.device)
        for i in _console.progress(range(0, len(q), 1024), desc="predictive sigma"):  # (1024, 3, n_weights) rows
            J = net.jacobian_flat(w, q[i : i + 1024].detach())[1][..., self.weight_index]
            J = R @ J  # (n, 3, k) in the tracker frame
            var_net[i : i + 1024] = torch.einsum("nak,kl,nal->na", J, self.weight_cov, J)
        d = self.distance(q.detach())[:, None]
        h2 = torch.exp(-((d / self.sigma_length) ** 2))  # the model's error: from its floor towards s_far
        g = torch.ones_like(d) if math.isinf(self.length) else torch.exp(-0.5 * (d / self.length) ** 2)
        s_fb = (
            self.sigma_far
            if self.sigma_fallback is None
            else torch.tensor(self.sigma_fallback, dtype=d.dtype, device=d.device)
        )
        var_fb = s_fb**2 * (1.0 + self.fallback_growth * d**2)
        b = g**2 * (1.0 - h2) * self.sigma_far**2 + (1.0 - g) ** 2 * var_fb
        return g**2 * (var_net + self.sigma_noise**2), b, (g**2).expand(-1, 3)

    def predictive_std(self, robot, q: Tensor) -> Tensor:
        """Predicted standard deviation per sample and tracker axis ``(N, 3)`` [m]."""
        a, b, g2 = self.variance_parts(robot, q)
        floor = torch.tensor(self.sigma_floor, dtype=a.dtype, device=a.device)
        return (self.sigma_scale**2 * a + g2 * floor**2 + b).sqrt()

    @property
    def reads_instrument(self) -> bool:
        """A finite gate with a fallback maps the fallback's tracker-frame prediction into this robot's base frame
        (:meth:`forward`), through this robot's instrument pose."""
        return self.fallback is not None and not math.isinf(self.length) and not self.fallback_in_base

    def fallback_to_base(self, T_tracker_base: Tensor, station: int = 0) -> None:
        """Tie the fallback to this model's base frame: its instrument pose becomes ``T_tracker_base^-1 T_fb``
        ``(4, 4)`` (``T_tracker_base`` the model's pose at which the two were fitted), so that a new instrument
        placement (``torchcal station``) moves the fallback's prediction with the model's. Without it the fallback
        would stay at the old placement in tracker coordinates, and the faded prediction would mix two placements.
        A fallback of several stations keeps the pose of its ``station`` (index) relative to ``T_tracker_base``."""
        if self.fallback is None or self.fallback_in_base:
            return
        from torchcal.robot.model import Instrument

        fb = self.fallback
        rel = torch.linalg.solve(T_tracker_base.detach(), fb.T_tracker_base(station).detach())
        fb.instrument = Instrument(rel, dtype=fb.dtype, device=fb.device)
        for p in fb.instrument.parameters():
            p.requires_grad_(False)
        self.fallback_in_base = True

    def distance(self, q: Tensor) -> Tensor:
        """``d(q)``: distance to the nearest region point in units of the spread ``(N,)``."""
        s = self.region / self.spread
        x = q / self.spread
        out = torch.empty(len(q), dtype=q.dtype, device=q.device)
        for i in range(0, len(q), 2048):  # bounded memory: (2048, M) distances at a time
            out[i : i + 2048] = torch.cdist(x[i : i + 2048], s).min(dim=1).values
        return out

    def gate(self, q: Tensor) -> Tensor:
        """``g(d(q))`` in (0, 1] ``(N,)``."""
        if math.isinf(self.length):
            return torch.ones(len(q), dtype=q.dtype, device=q.device)
        d = self.distance(q.detach())
        return torch.exp(-0.5 * (d / self.length) ** 2)

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
        g = self.gate(ctx.q)[:, None]
        out = self.inner(robot, ctx, p_base=p_base) * g
        if self.fallback is None or math.isinf(self.length):
            return out
        p_own = robot.probe_in_base(ctx.q) if p_base is None else p_base
        y_fb = (
            self.fallback.T_tracker_base()
            @ torch.cat([self.fallback.probe_in_base(ctx.q), torch.ones_like(ctx.q[:, :1])], dim=-1).T
        )
        if self.fallback_in_base:  # y_fb is in this model's base frame already (fallback_to_base)
            return out + (1.0 - g) * (y_fb.T[:, :3] - p_own)
        T_inv = torch.linalg.inv(robot.T_tracker_base())
        p_fb = (T_inv @ y_fb).T[:, :3]  # the fallback's probe in this model's base frame
        return out + (1.0 - g) * (p_fb - p_own)

    def config(self) -> dict:
        return {
            "inner": {"class": type(self.inner).__name__, **self.inner.config()},
            "length": self.length if math.isfinite(self.length) else None,  # JSON has no inf
            "n_region": int(len(self.region)),
            "dof": int(self.region.shape[1]),
            "fallback": self.fallback is not None,
            **({"fallback_frame": "base"} if self.fallback_in_base else {}),  # absent: the tracker frame
            "predictive": {
                "n_weights": int(len(self.weight_index)),
                "scale": self.sigma_scale,
                "floor": self.sigma_floor,
                "sigma_length": self.sigma_length,
                "fallback_sigma": self.sigma_fallback,
                "fallback_growth": self.fallback_growth,
            }
            if self.has_predictive
            else None,
        }

    def describe(self) -> dict:
        return {
            "gate_length": self.length,
            "region_points": int(len(self.region)),
            "falls_back_to": "the kinematic calibration" if self.fallback is not None else "the model's geometry",
            "inner": self.inner.describe(),
        }

    def label(self) -> str:
        return self.inner.label()


def choose_gate_length(
    make_gate: Callable[[float], RegionGate],
    score: Callable[[RegionGate], float],
    lengths: Sequence[float] = GATE_LENGTHS,
) -> tuple[float, list[dict]]:
    """The gate length with the lowest validation score, and the table of all tried.

    Args:
        make_gate: builds the gated effect for a length.
        score: validation RMSE [m] of the model with that gated effect (lower is better).
        lengths: the lengths to try; ``inf`` (no gate) should be among them, so the gate can only help.

    Ties go to the longer gate (the earlier one in ``lengths``): a gate is kept only where it helps.
    """
    table = []
    best = (math.inf, lengths[0])
    for length in lengths:
        s = float(score(make_gate(length)))
        table.append({"length": length, "validation_rmse_m": s})
        if s < best[0] * (1.0 - 1e-9):
            best = (s, length)
    return best[1], table


def predictive_sigma(model, q: Tensor) -> Tensor | None:
    """Predicted standard deviation ``(N, 3)`` [m] of ``model``'s positions at joints ``q``, or None.

    Defined where the model's learned correction is a :class:`RegionGate` with a predictive standard deviation
    (the integrated method's filters); None for any other model (geometry alone, kernels, the closed loop's
    effects), which has no per-sample standard deviation.
    """
    gates = [e for e in model.effects if isinstance(e, RegionGate) and e.has_predictive]
    if not gates:
        return None
    with torch.no_grad():
        return gates[-1].predictive_std(model.robot, q)


def coverage(e: Tensor, sigma: Tensor, k: float = 2.0) -> float:
    """Share of the residual components within ``k`` predicted standard deviations, ``mean(|e| <= k sigma)``.

    Args:
        e: residuals ``(N, 3)`` [m] (prediction minus measurement, per tracker axis).
        sigma: predicted standard deviations ``(N, 3)`` [m].
    """
    if e.shape != sigma.shape or e.numel() == 0:
        raise ValueError(f"e and sigma must have the same non-empty shape, got {tuple(e.shape)}, {tuple(sigma.shape)}")
    return float((e.abs() <= k * sigma).to(e.dtype).mean())


def fit_predictive_scale(
    e: Tensor,
    a: Tensor,
    b: Tensor,
    g2: Tensor,
    target: float = 0.95,
    n_sigma: float = 2.0,
    *,
    holdout: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
) -> tuple[float, list[float]]:
    """The scale ``k`` and the floor ``f`` (per axis) of ``var = k^2 a + g^2 f^2 + b`` by maximum likelihood of the
    validation residuals ``e`` (Gaussian, independent components), then ``k`` and ``f`` widened together (never
    narrowed) by the factor :func:`calibrate_factor` gives for ``target`` within ``n_sigma`` standard deviations:
    of the validation residuals alone, or with ``holdout`` (the residuals and variance parts of another model, e.g.
    the model refitted on all training samples, on samples neither model was fitted on) of the validation and
    held-out residuals pooled, each with its own parts. A model that fits the validation block closely can still
    miss a longer stretch of the path; the held-out coverage is then calibrated, no longer an independent check.
    Never narrowed below the likelihood fit: where most residuals lie within the unscaled far part ``b`` alone,
    the pooled factor would drop the near part towards zero, and the near part is what covers a continuation
    that stays close to the training joints.

    Args:
        e: validation residuals ``(N, 3)`` [m]; a, b, g2: the parts of :meth:`RegionGate.variance_parts` there.
        holdout: ``(e, a, b, g2)`` of the held-out samples ``(M, 3)`` each, or None.

    Returns:
        ``(scale, floor)``: the scale and the floor per axis [m].
    """
    blocks = [(e, a, b, g2)] if holdout is None else [(e, a, b, g2), holdout]
    for x in blocks:
        if not (x[0].shape == x[1].shape == x[2].shape == x[3].shape) or x[0].numel() == 0 or x[0].shape[-1] != 3:
            raise ValueError(
                f"e, a, b, g2 must have the same non-empty shape (N, 3), got {tuple(x[0].shape)}, {tuple(x[1].shape)}"
            )
    e, a, b, g2 = (x.detach() for x in (e, a, b, g2))
    e2 = e.square()
    rms = float(e2.mean().sqrt().clamp_min(1e-12))
    # log parameters, started where the floor alone explains the residuals and the network's term is small
    theta = torch.tensor([math.log(1e-2)] + [math.log(rms)] * 3, dtype=e.dtype, device=e.device, requires_grad=True)
    tiny = (1e-9 * rms) ** 2

    def nll():
        var = theta[0].exp() ** 2 * a + g2 * theta[1:].exp() ** 2 + b + tiny
        return 0.5 * (var.log() + e2 / var).mean()

    _minimise(theta, nll, max_iter=200, tolerance_grad=1e-10)
    scale, floor = float(theta[0].detach().exp()), theta[1:].detach().exp()

    def near(x):  # the part of the variance the factor multiplies (squared), on a block's own parts
        return scale**2 * x[1].detach() + x[3].detach() * floor**2

    factor = calibrate_factor(
        torch.cat([x[0].detach().flatten() for x in blocks]),
        torch.cat([near(x).flatten() for x in blocks]),
        torch.cat([x[2].detach().flatten() for x in blocks]),
        target,
        n_sigma,
    )
    return scale * max(1.0, factor), (floor * max(1.0, factor)).tolist()


#: the most a widening factor (:func:`calibrate_factor`) may make the largest predicted standard deviation, in units
#: of the largest residual it is calibrated on: where the near part is almost nothing (a gate almost closed) the
#: factor that covers such residuals grows without bound as the near part vanishes, and every other sample's sigma
#: with it; capped here, the target coverage is then not reached on those residuals
FACTOR_SIGMA_RATIO = 100.0


def calibrate_factor(
    e: Tensor, near: Tensor, far: Tensor, target: float = 0.95, k: float = 2.0, max_ratio: float = FACTOR_SIGMA_RATIO
) -> float:
    """The smallest factor ``s`` with ``coverage(e, sqrt(s^2 near + far), k) >= target``, ``far`` left unscaled, at most
    the factor at which the largest scaled near part's standard deviation is ``max_ratio`` times the largest ``|e|``.

    Component ``i`` is covered for ``s >= s_i = sqrt(max(0, e_i^2 / k^2 - far_i) / near_i)``, so ``s`` is the
    ``target`` quantile of ``s_i``. A component outside ``k`` sqrt(far) with no near part cannot be covered by any
    factor; where such components keep the target out of reach, the factor is the largest finite ``s_i``. Either way
    it is then capped (:data:`FACTOR_SIGMA_RATIO`), and the coverage falls short of the target instead of every
    standard deviation growing without bound.

    Args:
        e: residuals (any shape) [m]; near, far: the scaled and the unscaled variance, same shape [m^2].
        target: the share of components within ``k`` standard deviations aimed at.
        max_ratio: the cap (inf: none).
    """
    if not (e.shape == near.shape == far.shape) or e.numel() == 0:
        raise ValueError(f"e, near, far must have the same non-empty shape, got {tuple(e.shape)}, {tuple(near.shape)}")
    excess = (e.square() / k**2 - far).clamp_min(0.0).flatten()
    near = near.flatten()
    need = torch.where(excess > 0, excess / near.clamp_min(0.0), torch.zeros_like(excess)).sqrt()
    s = float(torch.quantile(need, target, interpolation="higher"))
    if math.isinf(s) or math.isnan(s):
        finite = need[torch.isfinite(need)]
        s = float(finite.max()) if finite.numel() else 1.0
    largest = float(near.max())
    if largest > 0 and math.isfinite(max_ratio):
        s = min(s, max_ratio * float(e.abs().max()) / math.sqrt(largest))
    return s


def fit_fallback_growth(e: Tensor, d: Tensor) -> tuple[list[float], float]:
    """The fallback's residual scale ``s_fb`` (per axis) and its growth ``c`` with the distance, ``var_a(d) =
    s_fb_a^2 (1 + c d^2)``, by maximum likelihood of the geometric model's residuals ``e`` on samples after those
    it was fitted on, at their distances ``d`` from those (Gaussian, independent components).

    Args:
        e: residuals ``(N, 3)`` [m].
        d: distances ``(N,)`` to the fitting samples [spreads] (:meth:`RegionGate.distance`).

    Returns:
        ``(s_fb, c)``: the scale per axis [m] and the growth [1 / spread^2] (0 where the residuals do not grow).
    """
    if e.ndim != 2 or e.shape[1] != 3 or d.shape != (len(e),) or len(e) == 0:
        raise ValueError(f"e must be (N, 3) and d (N,) with N > 0, got {tuple(e.shape)}, {tuple(d.shape)}")
    e2, d2 = e.detach().square(), d.detach()[:, None].square()
    rms = float(e2.mean().sqrt().clamp_min(1e-12))
    theta = torch.tensor([math.log(rms)] * 3 + [math.log(1e-3)], dtype=e.dtype, device=e.device, requires_grad=True)
    tiny = (1e-9 * rms) ** 2

    def nll():
        # log parameters clamped: a growth the residuals do not support runs towards zero, not to -inf (and NaN)
        s2 = theta[:3].clamp(math.log(rms) - 30.0, math.log(rms) + 10.0).exp() ** 2
        var = s2 * (1.0 + theta[3].clamp(-40.0, 10.0).exp() * d2) + tiny
        return 0.5 * (var.log() + e2 / var).mean()

    _minimise(theta, nll, max_iter=300, tolerance_grad=1e-12)
    th = theta.detach()
    s_fb = th[:3].clamp(math.log(rms) - 30.0, math.log(rms) + 10.0).exp()
    c = float(th[3].clamp(-40.0, 10.0).exp())
    return s_fb.tolist(), c if c > 1e-12 else 0.0


def fit_fallback_scale(e: Tensor, d: Tensor, growth: float) -> list[float]:
    """The fallback's residual scale ``s_fb`` (per axis) of ``var_a(d) = s_fb_a^2 (1 + c d^2)`` with the growth ``c``
    given, by maximum likelihood of residuals ``e`` of the fallback itself at their distances ``d`` from its region:
    ``s_fb_a^2 = mean_i e_ia^2 / (1 + c d_i^2)`` (Gaussian, independent components).

    :func:`fit_fallback_growth` learns the growth from geometric models refitted on parts of the training samples,
    which reach further from their region than held-out samples do; but a geometry fitted on all training samples
    (the fallback a prediction uses) is better determined than one fitted on half of them, and its error at the
    same distance is smaller. Its own residuals on samples it was not fitted on size the scale; the refits only the
    shape.

    Args:
        e: residuals of the fallback ``(N, 3)`` [m] on samples it was not fitted on.
        d: their distances ``(N,)`` to its fitting samples [spreads] (:meth:`RegionGate.distance`).
        growth: ``c`` [1 / spread^2], e.g. from :func:`fit_fallback_growth`.

    Returns:
        ``s_fb`` per axis [m].
    """
    if e.ndim != 2 or e.shape[1] != 3 or d.shape != (len(e),) or len(e) == 0:
        raise ValueError(f"e must be (N, 3) and d (N,) with N > 0, got {tuple(e.shape)}, {tuple(d.shape)}")
    if growth < 0 or not math.isfinite(growth):
        raise ValueError(f"growth must be finite and non-negative, got {growth}")
    e2 = e.detach().square()
    return (e2 / (1.0 + growth * d.detach()[:, None].square())).mean(dim=0).sqrt().tolist()


def _minimise(theta: Tensor, nll, max_iter: int, tolerance_grad: float) -> None:
    """Minimise ``nll()`` over the leaf ``theta`` in place by L-BFGS with a strong-Wolfe line search (a negative
    log-likelihood of a few parameters): ``torch.optim.LBFGS``'s method without ``torch.optim`` (which imports
    ``torch._dynamo``), :mod:`torchcal._lbfgs`."""

    def closure():
        theta.grad = None
        loss = nll()
        loss.backward()
        return loss

    _lbfgs.minimize(closure, theta, max_iter=max_iter, tolerance_grad=tolerance_grad)
