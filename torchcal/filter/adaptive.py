"""Adaptive geometry inside the integrated ANN-EKF: the "future work" of Horvath & Neuner (2024), Sec. 4.

The filter of :mod:`torchcal.filter.ekf` needs the geometry, the instrument pose and the lever arm to be known.
Here the identifiable geometric corrections join the state and are estimated together with the network.

Legend (one step ``i``; equation numbers of the paper):
``x = [w; t; gamma]`` state: the network's weights ``w`` (those with a non-zero prior: by default the output
layer), the probe position ``t`` in the tracker frame and the identifiable geometric corrections ``gamma`` (robot
geometry chosen by the identifiability analysis, the lever arm ``t_flange_probe``, the instrument rotation ``r``),
with an optional correlated-misfit state ``d`` between ``t`` and ``gamma``; ``P`` its covariance;
``R(gamma) = R_nom exp(r)``
the rotation of ``T_tracker_base``; ``p(theta; gamma)`` the probe in the base frame; ``u = R(gamma) p`` the probe
rotated into the tracker frame; ``g(theta; w)`` the network's correction in the base frame.

* prediction (Eq. 14 extended, 15-17): ``t_i = t_{i-1} + u(theta_i; gamma) - u(theta_{i-1}; gamma)``,
  ``w`` and ``gamma`` static; ``F = dx_i/dx_{i-1}`` is the identity but for the block
  ``dt_i/dgamma = U_i - U_{i-1}`` with ``U = du/dgamma``;
* covariance prediction (Eq. 19): ``P = F P F^T (+ Q)``, done as two rank-3 row/column updates;
* observation (Eq. 20): ``h = t + R(gamma) g(theta_i; w)``, ``H = [R dg/dw, I, dh/dgamma]`` where only the
  instrument rotation has a ``gamma`` column in ``h`` (``-[R g]x R``, of order 1e-4 m/rad);
* observation covariance: ``R_i = q_yy sigma_tracker^2 I + sigma_joint^2 R J_i J_i^T R^T`` (joint noise
  at the probe, ``J_i = dp/dtheta``);
* gain and update (Eqs. 7-9): ``S = H P H^T + R_i``, ``K = P H^T S^-1`` by Cholesky, ``x = x + K (y - h)``,
  Joseph-form covariance as one rank-6 update, symmetrised every ``nis_window`` steps;
* innovation statistics: ``NIS = e^T S^-1 e`` (chi-square, 3 degrees of freedom) per step; the variance factor
  ``q_yy`` adapts when a window's mean NIS leaves its chi-square band (Sec. 2.1.3), as in the plain filter.

Design decisions
----------------
*State and the instrument translation.* The relative prediction keeps the paper's state ``[w; t]``; the instrument
translation cancels from it (Sec. 2.3.2) and is brought back by back-substitution,
``t_tracker_base = t_i - R(gamma) p(theta_i; gamma)``, with its covariance from ``P`` (:attr:`AdaptiveResult.
instrument_translation`). The joint reading noise is white in the readings, so it enters every observation
once (``R_i`` above) and ``t`` gets no process noise (``q_t = 0``): ``t_i - u(theta_i; gamma)`` is then the
constant instrument translation, the relative and the absolute formulation are the same model, and the filter
on the (almost linear) static unknowns ``[w; t_0; gamma]`` is recursive least squares -- the same estimate and
covariance as the batch adjustment. The plain filter's process noise ``B Q_uu B^T`` per step (Eq. 19) would
instead let ``t`` random-walk by ``sigma sqrt(i)`` and absorb the slowly varying geometric signal that
``gamma`` must be estimated from.

*Linearisation.* ``u`` and ``U = du/dgamma`` come from one batched ``torch.func.jacfwd`` per block of
``relinearise_every`` samples (default 500, the paper's re-iteration period), at the estimate current at the
block's start; inside a block the prediction uses ``u + U (gamma - gamma_lin)``. The increments telescope, so
the error of ``t`` is the second-order remainder of ``u`` over a block, ``~ |gamma - gamma_lin|^2 x 1 m``:
geometric errors are ~1e-4 (m or rad), so even the first block, linearised at the nominal geometry, is good to
~1e-7 m, far below a laser tracker's noise, and later blocks move ``gamma`` by much less. Every pass measures
that remainder at its final estimate (:attr:`AdaptiveResult.relinearisations`), so the claim is checked on every
run. Relinearising more often buys
nothing measurable; the cost is one batched ``jacfwd`` over the trajectory per pass whatever the block size.

*Keeping geometry and network apart.* The network can mimic part of the geometry; what the data cannot separate,
only priors can. (1) The output bias is held at zero (variance 0): a constant correction is exactly the
instrument translation. (2) The network starts from zero output (output layer zero), so it holds no geometry at
the start. (3) The hidden layer is held fixed by default (``sigma_hidden = 0``): the network is then a linear
model on random tanh features (:func:`random_features`), the observation is linear in its output layer, and the
filter is an exact Kalman filter for ``[w_out; t_0; gamma]`` (Bayesian regression on features and geometry
jointly). (4) The output layer has a Gaussian prior whose scale is a stated a-priori size of the non-geometric
correction (``sigma_field``, RMS per axis over the training poses; 0.5 mm), the geometry one of 1 mm / 0.1 deg:
the part of the signal that both could explain is shared as these priors say, and -- the point -- the shared
uncertainty shows in ``P``: the geometry's standard deviations grow where the network could stand in for it
(``scripts/adaptive_geometry.py`` measures by how much), instead of the network silently biasing the geometry or
the geometry silently absorbing the field. (5) No LM re-iteration of the network
(Fig. 10): a refit to the corrections would pull the geometric part of the residual into the weights without
touching ``P``.

What is left is the network's misfit to the field, which the filter treats as white noise; it is correlated
along the trajectory, so with too few features the geometry's standard deviations come out too small: the
paper's 29 features with Glorot gain 1 leave a misfit several times the tracker noise on a sub-millimetre field,
and the geometry's errors then reach many of its standard deviations. Many features with a larger gain (the
default of :func:`random_features`) leave a misfit of the order of the noise; ``sigma_misfit`` adds the misfit
as a first-order Gauss-Markov state ``d`` (``d_i = phi d_{i-1} + noise``, correlation length
``misfit_samples``, observed with ``H_d = I``) where a smaller network must be used. Letting the hidden layer
move (``sigma_hidden > 0``, the hand-derived per-step Jacobian of :mod:`torchcal.filter._kalman`) makes the
model non-linear again: the network and the back-substituted instrument translation can then trade a constant
offset that the data cannot separate, so it is off by default. ``scripts/adaptive_geometry.py`` measures these
effects.

*Passes.* One pass is a filter: each block is linearised at the running estimate, so the first block is
linearised at the start (nominal) geometry. That costs a fraction of a standard deviation in weakly determined
parameters against the converged batch solution (:meth:`AdaptiveEKF.batch`). ``passes = 2`` runs the filter again from
the same priors, linearised at the first pass's result: a Gauss-Newton step, after which the filter agrees with
batch least squares (noise-free data: the biases to 1e-9).

The joints of the whole trajectory are used up front (identifiability analysis, the feature scale of the prior,
the joint noise term): they are the robot program, known before the run.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field

import torch
from torch import nn

from torchcal import _console
from torchcal._threads import torch_threads
from torchcal.effects.learned import CorrectionNet
from torchcal.errors import EstimationError, OptionError, ShapeError
from torchcal.estimate.identifiability import DEFAULT_TOL, analyse, preference_order
from torchcal.estimate.lm import FitStatus
from torchcal.filter._kalman import NetworkJacobian, joseph_update_, nis_band, window_health
from torchcal.filter.ekf import FilterStatus
from torchcal.robot import transforms as tf
from torchcal.robot.model import ParameterInfo, RobotModel

Tensor = torch.Tensor

_ROTATION = ("rx", "ry", "rz")


@dataclass
class AdaptiveConfig:
    """Stochastic model and schedule of the adaptive filter (SI units)."""

    sigma_length: float = 1e-3  # a-priori std of length corrections (geometry, lever arm) [m]
    sigma_angle: float = math.radians(0.1)  # a-priori std of angle corrections (geometry, instrument rotation) [rad]
    sigma_t0: float = 1e-3  # a-priori std of the initial probe position [m]
    sigma_field: float = 5e-4  # a-priori RMS per axis of the network's correction over the training poses [m]
    sigma_hidden: float = 0.0  # a-priori std of the hidden-layer weights around their start (0: fixed features)
    q_t: float = 0.0  # process noise of the probe position per step [m] (module docstring: keep 0)
    q_w: float = 0.0  # process noise of the weights per step
    sigma_joint: float = math.radians(0.0005)  # joint reading noise [rad]
    sigma_tracker: float = 15e-6  # tracker noise per axis [m]
    sigma_misfit: float = 0.0  # std of the network's correlated misfit, a Gauss-Markov state (0: none) [m]
    misfit_samples: float = 50.0  # its correlation length along the trajectory [samples]
    relinearise_every: int = 500  # samples per linearisation block
    passes: int = 1  # > 1: iterated filter, later passes linearised at the previous pass's result (Gauss-Newton)
    rank_tol: float = DEFAULT_TOL  # identifiability threshold (torchcal.estimate.identifiability)
    adapt_qyy: bool = True
    nis_window: int = 100
    nis_alpha: float = 0.01

    def __post_init__(self):
        for name in ("sigma_length", "sigma_angle", "sigma_t0", "sigma_tracker"):
            if not getattr(self, name) > 0:
                raise OptionError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("sigma_field", "sigma_hidden", "q_t", "q_w", "sigma_joint", "sigma_misfit"):
            if not getattr(self, name) >= 0:
                raise OptionError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.misfit_samples > 0:
            raise OptionError(f"misfit_samples must be positive, got {self.misfit_samples}")
        if min(self.relinearise_every, self.nis_window, self.passes) < 1:
            raise OptionError(
                f"relinearise_every, nis_window and passes must be >= 1, got {self.relinearise_every}, "
                f"{self.nis_window} and {self.passes}"
            )


@dataclass
class AdaptiveResult:
    """Geometry estimates with their standard deviations, per-sample outputs ``(N, ...)`` and the filter's health.

    ``gamma`` are values of the robot's correction parameters (``RobotModel.groups()[group].delta`` elements
    named in ``names``), not increments; their a-priori values are ``gamma0``.
    """

    names: list[str]
    units: list[str]  # "m" or "rad"
    gamma0: Tensor  # (k,) values at the start
    gamma: Tensor  # (k,) final estimates
    gamma_std: Tensor  # (k,) from P
    instrument_translation: Tensor  # (3,) back-substituted instrument.tx, ty, tz [m] (Instrument.delta convention)
    instrument_translation_std: Tensor  # (3,)
    geometric: Tensor  # (N, 3) t (predicted state) [m], tracker frame
    nongeometric: Tensor  # (N, 3) R g(theta; w) [m], tracker frame
    nis: Tensor  # (N,), NaN in the test phase
    q_yy: Tensor  # (N,), NaN in the test phase
    w: Tensor  # (n_w,) final weights (all of them)
    active: Tensor  # indices of the weights in the state (the others were held at their start)
    t: Tensor  # (3,) probe position after the last update
    P: Tensor  # (n, n) final covariance, state order [w[active]; t; d (if sigma_misfit > 0); gamma]
    n_train: int
    status: FilterStatus | str = FilterStatus.OK  # OK, or "diverged at sample i: why"
    relinearisations: list[dict] = field(default_factory=list)  # per pass: the linearisation's remainder
    seconds: float = 0.0
    parameters: list[ParameterInfo] = field(default_factory=list)

    @property
    def prediction(self) -> Tensor:
        return self.geometric + self.nongeometric

    @property
    def diverged(self) -> bool:
        return self.status != FilterStatus.OK

    @property
    def gamma_covariance(self) -> Tensor:
        k = len(self.names)
        return self.P[-k:, -k:] if k else self.P[:0, :0]

    def apply(self, robot: RobotModel) -> RobotModel:
        """A copy of ``robot`` with the estimated corrections and the back-substituted translation written in."""
        out = copy.deepcopy(robot)
        groups = out.groups()
        with torch.no_grad():
            for info, v in zip(self.parameters, self.gamma):
                groups[info.group].delta[info.index] = v
            out.instrument.delta[:3] = self.instrument_translation
        return out


@dataclass
class BatchGeometry:
    """Result of :meth:`AdaptiveEKF.batch`: the geometry by batch least squares; ``covariance`` is in the order
    ``[instrument translation (3); gamma (k)]`` and not scaled by ``sigma0_sq``."""

    names: list[str]
    gamma: Tensor
    gamma_std: Tensor
    instrument_translation: Tensor
    instrument_translation_std: Tensor
    covariance: Tensor
    sigma0_sq: float
    iterations: int
    status: str


def random_features(
    dof: int = 6, hidden: int = 128, gain: float = 5.0, seed: int = 0, device: torch.device | str = "cpu"
) -> CorrectionNet:
    """The correction network the adaptive filter is meant for: a fixed random tanh layer and a zero output layer.

    With the hidden layer fixed (``sigma_hidden = 0``) the network is a linear model on ``hidden`` random
    features, so the filter stays a linear Kalman filter and its covariance honest (module docstring). Random
    features need to be many and non-linear to cover what training the hidden layer would otherwise buy: with
    ``gain = 5`` the pre-activations are of order one over the joint range (the default Glorot gain 1 leaves
    ``tanh`` almost linear), and 128 of them fit a sub-millimetre field several times more closely than the
    paper's 29 (``scripts/adaptive_geometry.py``).

    Args:
        dof: joints; hidden: features; gain: Glorot gain of the hidden layer; seed: reproducible draw (on the CPU's
            generator, so the same features on every device); device: where the network lives (the data's).
    """
    net = CorrectionNet(dof, hidden, device=device)
    net.reset_parameters(torch.Generator().manual_seed(seed), gain=gain)
    with torch.no_grad():
        net.fc2.weight.zero_()
        net.fc2.bias.zero_()
    return net


class _Probe(nn.Module):
    """The probe in the tracker frame, ``T_tracker_base p(theta)``, or only rotated into it, ``u = R p(theta)``."""

    def __init__(self, robot: RobotModel):
        super().__init__()
        self.robot = robot

    def forward(self, q: Tensor, translate: bool = False) -> Tensor:
        if translate:
            return self.robot.probe_position(q)
        return self.robot.probe_in_base(q) @ self.robot.T_tracker_base()[:3, :3].T


class AdaptiveEKF:
    """The integrated ANN-EKF with the identifiable geometry in its state (module docstring).

    Args:
        robot: the kinematic model at the start: nominal geometry, an instrument pose and a lever arm within their
            a-priori standard deviations of the truth (e.g. from
            :func:`torchcal.estimate.rigid.fit_instrument_and_tool` on the training data).
        net: the correction network (architecture and hidden layer; its output layer is started at zero), or
            None for a geometry-only filter (state ``[t; gamma]``: recursive kinematic calibration).
        config: :class:`AdaptiveConfig`.
        parameters: the geometric corrections to estimate; default: the identifiable ones at the training poses
            (:meth:`identify`).
    """

    def __init__(
        self,
        robot: RobotModel,
        net: CorrectionNet | None = None,
        config: AdaptiveConfig | None = None,
        parameters: list[ParameterInfo] | None = None,
    ):
        self.robot = robot
        self.net = net
        self.config = config or AdaptiveConfig()
        self.parameters = parameters
        self._module = _Probe(robot)

    # ------------------------------------------------------------------------------ parameters
    def identify(self, q: Tensor, max_poses: int = 1000) -> list[ParameterInfo]:
        """The identifiable corrections at joints ``q (N, dof)``, instrument translation excluded.

        Candidates are the free geometry elements (``mask``), the six instrument and the three lever-arm
        components; the analysis (:func:`torchcal.estimate.identifiability.analyse`, instrument first, then the
        lever arm, then the geometry from base to tip) runs on the Jacobian of the tracker-frame probe position at
        up to ``max_poses`` evenly spaced poses (the dependencies it removes are structural, so a thinned
        trajectory finds the same set). The instrument translation is always identifiable and is carried by
        ``t``, so it is not returned.

        Raises:
            EstimationError: when an instrument translation component is not identifiable (degenerate poses).
        """
        robot = self.robot
        q = q[torch.linspace(0, len(q) - 1, min(len(q), max_poses)).round().long()]
        cands = [i for i in robot.parameter_info() if i.group != "geometry" or bool(robot.geometry.mask[i.index])]
        index = _Index(robot, cands)

        def fn(x):
            return torch.func.functional_call(self._module, index.params(x, prefix="robot."), (q, True)).reshape(-1)

        with torch.no_grad():
            J = torch.func.jacfwd(fn)(index.values())
        names = [i.name for i in cands]
        ida = analyse(J, names, preference_order(names), tol=self.config.rank_tol)
        keep = dict(zip(names, ida.free.tolist()))
        lost = [n for n in ("instrument.tx", "instrument.ty", "instrument.tz") if not keep[n]]
        if lost:
            raise EstimationError(
                f"the instrument translation ({', '.join(lost)}) is not identifiable at these "
                "poses; the adaptive filter carries it in t and needs it"
            )
        return [i for i in cands if keep[i.name] and i.name not in ("instrument.tx", "instrument.ty", "instrument.tz")]

    def initial_weights(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Start weights (the network's, output layer zeroed) and their a-priori std ``(n_w,)`` each.

        The output layer's std is ``sigma_field / (out_scale sqrt(mean_i sum_h a_h(theta_i)^2))`` with ``a`` the
        hidden activations at the joints ``q``: then ``sigma_field`` is the prior RMS per axis of the correction
        over those poses. The output bias is held at zero (variance 0: it is the instrument translation).
        """
        net = self.net
        if net is None:
            return q.new_zeros(0), q.new_zeros(0)
        cfg = self.config
        w = net.flat()
        Hn, Dq = net.hidden, net.dof
        o2, o3 = Hn * Dq + Hn, Hn * Dq + 4 * Hn  # ends of the hidden layer and of the output weights
        w[o2:] = 0.0
        with torch.no_grad():
            a = torch.tanh(((q - net.q_offset) / net.q_scale) @ net.fc1.weight.T + net.fc1.bias)
        feat = float(a.square().sum(-1).mean().sqrt())
        sig = torch.zeros_like(w)
        sig[:o2] = cfg.sigma_hidden
        sig[o2:o3] = cfg.sigma_field / (float(net.out_scale) * max(feat, 1e-12))
        return w, sig

    # -------------------------------------------------------------------------------- the pass
    def run(
        self,
        q: Tensor,
        y: Tensor,
        n_train: int,
        w0: Tensor | None = None,
        sigma_w0: Tensor | None = None,
        t0: Tensor | None = None,
    ) -> AdaptiveResult:
        """Filter the first ``n_train`` samples, predict the rest with the final state.

        With ``config.passes > 1`` the pass is repeated from the same priors, linearised throughout at the previous
        pass's result (module docstring); the outputs are those of the last pass. The pass runs with one torch
        thread (its kernels are small) and restores the caller's thread count.

        Args:
            q: joint readings ``(N, dof)`` [rad] along a continuous trajectory.
            y: measured probe positions ``(N, 3)`` [m], tracker frame.
            n_train: samples used for updates; the rest is the test phase.
            w0, sigma_w0: start weights and their a-priori std ``(n_w,)``; default :meth:`initial_weights`.
            t0: initial probe position ``(3,)``; default the model's ``probe_position(q[0])``.

        Returns:
            :class:`AdaptiveResult`; a divergence stops the pass and is reported in its ``status``.
        """
        t_start = time.perf_counter()
        with torch_threads(1):
            setup = self._setup(q, y, n_train, w0, sigma_w0, t0)
            lin_point = None  # pass 1: linearise at the running estimate; later passes: at the last pass's result
            relin = []
            for k in range(self.config.passes):
                p = _Pass(self, setup, lin_point)
                status = p.filter()
                relin.append(self._remainders(setup.index, p.blocks, p.xg, q, k + 1))
                if status != FilterStatus.OK:
                    break
                lin_point = p.xg.clone()
            result = self._finish(setup, p, relin)
        result.seconds = time.perf_counter() - t_start
        return result

    def _setup(
        self, q: Tensor, y: Tensor, n_train: int, w0: Tensor | None, sigma_w0: Tensor | None, t0: Tensor | None
    ) -> _Setup:
        """What every pass shares: the checked inputs, the parameters, the priors, the state's layout, the
        observation noise and the network's form."""
        cfg, robot, net = self.config, self.robot, self.net
        self._check(q, y, n_train)
        kw = {"dtype": q.dtype, "device": q.device}
        params = self.parameters if self.parameters is not None else self.identify(q[:n_train])
        if w0 is None or sigma_w0 is None:
            w_def, s_def = self.initial_weights(q[:n_train])
            w0 = w_def if w0 is None else w0
            sigma_w0 = s_def if sigma_w0 is None else sigma_w0
        if net is not None and w0.shape != (net.n_weights,) or sigma_w0.shape != w0.shape:
            raise ShapeError(
                f"w0 and sigma_w0 must have shape ({len(w0) if net is None else net.n_weights},), got "
                f"{tuple(w0.shape)} and {tuple(sigma_w0.shape)}"
            )
        active = torch.nonzero(sigma_w0 > 0).flatten()  # weights in the state; the others are held (variance 0)
        nd = 3 if cfg.sigma_misfit > 0 else 0
        index = _Index(robot, params)
        with torch.no_grad():
            R0 = robot.T_tracker_base()[:3, :3]
            t_first = (robot.probe_position(q[0]) if t0 is None else t0).clone()
            _, Jq = robot.probe_jacobian(q[:n_train])
        RJ = R0 @ Jq
        first_gamma = len(active) + 3 + nd  # the state column of the first geometric parameter
        rot = [
            (first_gamma + j, _ROTATION.index(p.name[-2:]))
            for j, p in enumerate(params)
            if p.group == "instrument" and p.name[-2:] in _ROTATION
        ]
        s = _Setup(
            q=q,
            y=y,
            n_train=n_train,
            kw=kw,
            params=list(params),
            index=index,
            w0=w0,
            sigma_w0=sigma_w0,
            active=active,
            nd=nd,
            unit_sig=torch.tensor([cfg.sigma_length if p.unit == "m" else cfg.sigma_angle for p in params], **kw),
            gamma0=index.values(),
            t0=t_first,
            Ryy_q=cfg.sigma_joint**2 * RJ @ RJ.transpose(-1, -2),
            rot_cols=[c for c, _ in rot],
            rot_axes=[a for _, a in rot],
        )
        nw = s.nw
        if net is not None:
            Hn, Dq = net.hidden, net.dof
            s.Hn, s.o2, s.o3 = Hn, Hn * Dq + Hn, Hn * Dq + 4 * Hn
            if nw and int(active.min()) >= s.o2 and int(active.max()) < s.o3:  # fixed hidden layer: linear in W2
                with torch.no_grad():
                    s.features = torch.tanh(
                        ((q - net.q_offset) / net.q_scale) @ w0[: Hn * Dq].view(Hn, Dq).T + w0[Hn * Dq : s.o2]
                    )  # (N, H)
                s.w2_cols = active - s.o2
                s.direct = nw == 3 * Hn  # the whole output layer: its Jacobian block is written in place
        return s

    def _finish(self, s: _Setup, p: _Pass, relin: list[dict]) -> AdaptiveResult:
        """Back-substitute the instrument translation, predict the test phase, collect the result."""
        q, n_train, kw = s.q, s.n_train, s.kw
        P = 0.5 * (p.P + p.P.T)
        t, gamma = p.xt.clone(), p.xg.clone()
        with torch.no_grad():
            u_end, U_end = self._linearise(s.index, gamma, q[p.last :])  # exact u at the final gamma
            R_end = s.index.rotation(gamma)
        # back-substitution: c = t - R(gamma) p(theta_last; gamma) = R_nom t_delta + t_nom
        T_nom = self.robot.instrument.nominal
        G = torch.cat([torch.eye(3, **kw), -U_end[0]], dim=1)  # dc/d[t; gamma]
        tg = torch.cat([torch.arange(s.nw, s.nw + 3), torch.arange(s.ig.start, s.n)])
        C = G @ P[tg][:, tg] @ G.T
        trans = T_nom[:3, :3].T @ (t - u_end[0] - T_nom[:3, 3])
        trans_std = (T_nom[:3, :3].T @ C @ T_nom[:3, :3]).diagonal().clamp(min=0).sqrt()
        if p.status == FilterStatus.OK:  # test phase: the relative kinematics at the final gamma, no updates
            p.geo[n_train:] = t + u_end[1:] - u_end[0]
            p.ngo[n_train:] = 0.0 if self.net is None else self.net.forward_flat(p.w_full, q[n_train:]) @ R_end.T
        return AdaptiveResult(
            names=[i.name for i in s.params],
            units=[i.unit for i in s.params],
            gamma0=s.gamma0,
            gamma=gamma,
            gamma_std=P.diagonal()[s.ig].clamp(min=0).sqrt(),
            instrument_translation=trans,
            instrument_translation_std=trans_std,
            geometric=p.geo,
            nongeometric=p.ngo,
            nis=p.nis,
            q_yy=p.qyy_h,
            w=p.w_full,
            active=s.active,
            t=t,
            P=P,
            n_train=n_train,
            status=p.status,
            relinearisations=relin,
            parameters=list(s.params),
        )

    # ------------------------------------------------------------------- the batch counterpart
    def batch(
        self,
        q: Tensor,
        y: Tensor,
        parameters: list[ParameterInfo] | None = None,
        iterations: int = 10,
        tol: float = 1e-13,
        priors: bool = True,
    ) -> BatchGeometry:
        """Batch weighted least squares of the geometry alone with the filter's stochastic model.

        Gauss-Newton over ``[instrument translation; gamma]`` with the filter's priors on ``gamma`` and the same
        observation covariance (tracker and joint noise, ``q_yy = 1``). A geometry-only filter (``net=None``)
        computes the same estimate recursively; on noise-free, effect-free data from a known robot it gives the
        truth expressed in these parameters (the non-identifiable corrections absorbed into the others; use
        ``priors=False`` there, so that nothing pulls the exact fit).

        Args:
            q, y: joints ``(N, dof)`` [rad] and measured positions ``(N, 3)`` [m].
            parameters: default :attr:`parameters` or :meth:`identify`.
            priors: include the filter's a-priori information on ``gamma``.
        """
        self._check(q, y, len(q))
        params = parameters or self.parameters or self.identify(q)
        trans = [
            i for i in self.robot.parameter_info() if i.name in ("instrument.tx", "instrument.ty", "instrument.tz")
        ]
        index = _Index(self.robot, trans + list(params))
        z0 = index.values()
        prior = self._batch_prior(params, q) * float(priors)
        W = self._batch_whitening(q)

        def fn(z):
            out = torch.func.functional_call(self._module, index.params(z, prefix="robot."), (q, True))
            return out, out

        z, Lc, n_it, status = _gauss_newton(fn, z0, y, W, prior, iterations, tol)
        with torch.no_grad():
            f = torch.func.functional_call(self._module, index.params(z, prefix="robot."), (q, True))
        r = (W @ (y - f).unsqueeze(-1)).reshape(-1)
        cov = torch.cholesky_inverse(Lc)
        std = cov.diagonal().sqrt()
        return BatchGeometry(
            names=[p.name for p in params],
            gamma=z[3:],
            gamma_std=std[3:],
            instrument_translation=z[:3],
            instrument_translation_std=std[:3],
            covariance=cov,
            sigma0_sq=float(r.square().sum()) / max(len(r) - len(z), 1),
            iterations=n_it,
            status=status,
        )

    def _batch_prior(self, params: list[ParameterInfo], q: Tensor) -> Tensor:
        """The filter's prior weights of the batch's parameters: none on the instrument translation, ``1 / sigma^2``
        on each correction (the filter's a-priori information)."""
        cfg = self.config
        kw = {"dtype": q.dtype, "device": q.device}
        weights = [1.0 / (cfg.sigma_length if p.unit == "m" else cfg.sigma_angle) ** 2 for p in params]
        return torch.cat([torch.zeros(3, **kw), torch.tensor(weights, **kw)])

    def _batch_whitening(self, q: Tensor) -> Tensor:
        """``L^-1`` ``(N, 3, 3)`` of the filter's observation covariance per pose (tracker and joint noise)."""
        cfg, robot = self.config, self.robot
        kw = {"dtype": q.dtype, "device": q.device}
        with torch.no_grad():
            RJ = robot.T_tracker_base()[:3, :3] @ robot.probe_jacobian(q)[1]
            C = cfg.sigma_tracker**2 * torch.eye(3, **kw) + cfg.sigma_joint**2 * RJ @ RJ.transpose(-1, -2)
            L = torch.linalg.cholesky(C)
        return torch.linalg.solve_triangular(L, torch.eye(3, **kw).expand_as(C), upper=False)

    # ----------------------------------------------------------------------------- internals
    def _check(self, q: Tensor, y: Tensor, n_train: int) -> None:
        robot = self.robot
        if q.ndim != 2 or q.shape[1] != robot.dof:
            raise ShapeError(f"q must have shape (N, {robot.dof}) for robot '{robot.name}', got {tuple(q.shape)}")
        if y.shape != (q.shape[0], 3):
            raise ShapeError(f"y must have shape ({q.shape[0]}, 3) to match q, got {tuple(y.shape)}")
        if q.dtype != robot.dtype or y.dtype != robot.dtype:
            raise ShapeError(f"q and y must be {robot.dtype} like the robot, got {q.dtype} and {y.dtype}")
        if not 1 <= n_train <= q.shape[0]:
            raise OptionError(f"n_train must lie in [1, {q.shape[0]}], got {n_train}")

    def _remainders(self, index: _Index, blocks: list, gamma: Tensor, q: Tensor, n_pass: int) -> dict:
        """What the linearisation of a pass got wrong in ``t``, evaluated at the pass's final ``gamma``.

        Per block, the exact increment of ``u`` from its first to its last row minus the linearised one
        ``u_l - u_f + (U_l - U_f)(gamma - gamma_lin)``: the second-order remainder the state ``t`` carries.
        """
        rows = torch.cat([torch.tensor([b[0], b[0] + len(b[2]) - 1]) for b in blocks])
        u_exact, _ = self._linearise(index, gamma, q[rows])
        rem, change = [], []
        for j, (_lo, g_lin, u, U) in enumerate(blocks):
            d = gamma - g_lin
            lin = u[-1] - u[0] + (U[-1] - U[0]) @ d
            rem.append(u_exact[2 * j + 1] - u_exact[2 * j] - lin)
            change.append(float(d.abs().max()) if len(d) else 0.0)
        rem = torch.stack(rem)
        return {
            "pass": n_pass,
            "blocks": len(blocks),
            "max_abs_gamma_change": max(change),
            "max_block_remainder_m": float(rem.norm(dim=-1).max()),
            "total_remainder_m": float(rem.sum(0).norm()),
        }

    def _linearise(self, index: _Index, gamma: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        """``u(theta; gamma) (M, 3)`` and ``U = du/dgamma (M, 3, k)`` at joints ``q (M, dof)``, one batched jacfwd."""

        def fn(g):
            out = torch.func.functional_call(self._module, index.params(g, prefix="robot."), (q,))
            return out, out

        with torch.no_grad():
            U, u = torch.func.jacfwd(fn, has_aux=True)(gamma)
        return u, U


class _Index:
    """Map between a flat vector of selected correction elements and the robot's parameter groups."""

    def __init__(self, robot: RobotModel, params: list[ParameterInfo]):
        self.robot = robot
        self.groups: dict[str, tuple[list[int], Tensor]] = {}
        shapes = {name: g.delta.shape for name, g in robot.groups().items()}
        for j, p in enumerate(params):
            pos, flat = self.groups.setdefault(p.group, ([], []))
            pos.append(j)
            flat.append(int(torch.tensor(p.index).dot(torch.tensor(_strides(shapes[p.group])))))
        self.groups = {g: (torch.tensor(pos), torch.tensor(flat)) for g, (pos, flat) in self.groups.items()}
        self.k = len(params)

    def values(self) -> Tensor:
        out = torch.zeros(self.k, dtype=self.robot.dtype, device=self.robot.device)
        for g, (pos, flat) in self.groups.items():
            out[pos] = self.robot.groups()[g].delta.detach().flatten()[flat]
        return out

    def params(self, x: Tensor, prefix: str = "") -> dict[str, Tensor]:
        """Group ``delta`` tensors with ``x`` put in the selected places (differentiable in ``x``)."""
        out = {}
        for g, (pos, flat) in self.groups.items():
            d = self.robot.groups()[g].delta.detach()
            out[f"{prefix}{g}.delta"] = d.flatten().index_put((flat,), x[pos]).reshape(d.shape)
        return out

    def rotation(self, x: Tensor) -> Tensor:
        """``R(gamma)`` of ``T_tracker_base`` with the selected instrument rotation set from ``x``."""
        inst = self.params(x).get("instrument.delta", self.robot.instrument.delta.detach())
        return self.robot.instrument.nominal[:3, :3] @ tf.so3_exp(inst[3:])


@dataclass
class _Setup:
    """What every pass of :meth:`AdaptiveEKF.run` shares (built by :meth:`AdaptiveEKF._setup`).

    State layout ``x = [w[active]; t; d; gamma]`` with the slices ``iw, it, id_, ig``; ``features`` are the
    fixed hidden layer's activations ``(N, H)`` when only output weights are in the state (``direct`` when all of
    them are), else None.
    """

    q: Tensor
    y: Tensor
    n_train: int
    kw: dict
    params: list[ParameterInfo]
    index: _Index
    w0: Tensor
    sigma_w0: Tensor
    active: Tensor  # the weights in the state (nw,)
    nd: int  # misfit states: 3, or 0 without them
    unit_sig: Tensor  # a-priori sigma of each geometric parameter, by its unit [m or rad] (k,)
    gamma0: Tensor  # the geometric parameters at the start (k,)
    t0: Tensor  # the probe position at the first sample (3,)
    Ryy_q: Tensor  # joint noise at the probe per training sample (N_train, 3, 3)
    rot_cols: list[int]  # state columns of the instrument rotation
    rot_axes: list[int]  # and their axes
    features: Tensor | None = None
    w2_cols: Tensor | None = None
    direct: bool = False
    Hn: int = 0
    o2: int = 0  # end of the hidden layer in the flat weights
    o3: int = 0  # end of the output weights

    @property
    def nw(self) -> int:
        """Weights in the state."""
        return len(self.active)

    @property
    def n(self) -> int:
        """The state's size: weights, probe position, misfit, geometric parameters."""
        return self.nw + 3 + self.nd + len(self.params)

    @property
    def iw(self) -> slice:
        return slice(0, self.nw)

    @property
    def it(self) -> slice:
        return slice(self.nw, self.nw + 3)

    @property
    def id_(self) -> slice:
        return slice(self.nw + 3, self.nw + 3 + self.nd)

    @property
    def ig(self) -> slice:
        return slice(self.nw + 3 + self.nd, self.n)


class _Pass:
    """One filter pass over the training samples: the state, its covariance and the per-sample outputs.

    :meth:`filter` runs the steps of the module docstring per sample: :meth:`relinearise` (at block starts),
    :meth:`predict`, :meth:`observe`, :meth:`update`, and :meth:`check_window` at the end of each NIS window.
    ``x`` is only ever updated in place, so its blocks ``xw, xt, xd, xg`` (and ``P``'s row and column blocks)
    are views set up once.
    """

    def __init__(self, flt: AdaptiveEKF, s: _Setup, lin_point: Tensor | None):
        cfg, kw = flt.config, s.kw
        self.flt, self.s, self.cfg, self.net, self.lin_point = flt, s, cfg, flt.net, lin_point
        self.phi = math.exp(-1.0 / cfg.misfit_samples)  # Gauss-Markov misfit: d_i = phi d_{i-1} + noise
        self.band = nis_band(cfg.nis_window, cfg.nis_alpha)
        self.w_full = s.w0.clone()
        self.x = torch.cat([s.w0[s.active], s.t0, torch.zeros(s.nd, **kw), s.gamma0])
        self.P = torch.diag(
            torch.cat(
                [
                    s.sigma_w0[s.active],
                    torch.full((3,), cfg.sigma_t0, **kw),
                    torch.full((s.nd,), cfg.sigma_misfit, **kw),
                    s.unit_sig,
                ]
            ).square()
        )
        x, P = self.x, self.P
        self.xw, self.xt, self.xd, self.xg = x[s.iw], x[s.it], x[s.id_], x[s.ig]
        self.Pt_rows, self.Pg_rows, self.Pt_cols, self.Pg_cols = P[s.it, :], P[s.ig, :], P[:, s.it], P[:, s.ig]
        self.eye3, self.zero3 = torch.eye(3, **kw), torch.zeros(3, **kw)
        self.H = torch.zeros(3, s.n, **kw)
        self.H[:, s.it] = self.eye3
        self.H[:, s.id_] = self.eye3[:, : s.nd]
        self.W2 = self.xw.view(3, s.Hn) if s.direct else None
        self.Hw = self.H[:, s.iw].view(3, 3, s.Hn) if s.direct else None
        self.qyy = 1.0
        self.status: FilterStatus | str = FilterStatus.OK
        N = len(s.q)
        self.geo = torch.full((N, 3), float("nan"), **kw)
        self.ngo = torch.full((N, 3), float("nan"), **kw)
        self.nis = torch.full((N,), float("nan"), **kw)
        self.qyy_h = torch.full((N,), float("nan"), **kw)
        self.blocks = []  # (first row's sample, gamma_lin, u, U) of each linearisation block
        self.last = 0  # the last sample filtered

    def filter(self) -> FilterStatus | str:
        """Run the pass; returns its status (OK, or why it stopped)."""
        s, cfg = self.s, self.cfg
        for i in _console.progress(range(s.n_train), desc="integrated: filter"):
            self.last = i
            if i % cfg.relinearise_every == 0:
                self.relinearise(i)
            if i > 0:
                self.predict(i)
            self.geo[i] = self.xt
            self.qyy_h[i] = self.qyy
            e = self.observe(i)
            if not self.update(i, e):
                break
            if (i + 1) % cfg.nis_window == 0 and not self.check_window(i):
                break
        self.w_full[s.active] = self.xw
        return self.status

    def relinearise(self, i: int) -> None:
        """Linearise ``u`` over the block starting at sample ``i`` (module docstring, *Linearisation*)."""
        s, net = self.s, self.net
        self.g_lin = self.xg.clone() if self.lin_point is None else self.lin_point
        self.lo = max(i - 1, 0)  # rows: the sample before the block, then the block
        hi = min(i + self.cfg.relinearise_every, s.n_train)
        u, U = self.flt._linearise(s.index, self.g_lin, s.q[self.lo : hi])
        self.blocks.append((self.lo, self.g_lin, u, U))
        self.du, self.dU = u.diff(dim=0), U.diff(dim=0)  # the block's increments (row j: sample lo + j + 1)
        with torch.no_grad():
            R_lin = s.index.rotation(self.g_lin)
        self.R_axes = R_lin[:, s.rot_axes]
        if s.features is not None:
            self.Ros = R_lin * float(net.out_scale)
            self.ng_bias = self.Ros @ self.w_full[s.o3 :]
        elif net is not None:
            self.jac = NetworkJacobian(net, s.q[None], R_lin, 1)

    def predict(self, i: int) -> None:
        """Prediction (Eqs. 14-19): ``t += du + dU (gamma - gamma_lin)``, ``P = F P F^T`` (+ Q)."""
        cfg, s, P = self.cfg, self.s, self.P
        j = i - self.lo - 1
        self.xt += self.du[j] + self.dU[j] @ (self.xg - self.g_lin)
        self.Pt_rows += self.dU[j] @ self.Pg_rows  # F = I + (rows t, columns gamma: dU)
        self.Pt_cols += self.Pg_cols @ self.dU[j].T
        if s.nd:  # the correlated misfit decays towards zero
            phi = self.phi
            self.xd *= phi
            P[s.id_, :] *= phi
            P[:, s.id_] *= phi
            P[s.id_, s.id_] += (1.0 - phi**2) * cfg.sigma_misfit**2 * self.eye3
        if cfg.q_t > 0:
            P[s.it, s.it] += cfg.q_t**2 * self.eye3
        if cfg.q_w > 0:
            P.diagonal()[s.iw] += cfg.q_w**2

    def observe(self, i: int) -> Tensor:
        """Observation (Eq. 20) and its Jacobian (Eq. 21) into ``H``; returns the innovation ``e (3,)``."""
        s, H = self.s, self.H
        if s.direct:  # fixed features, the whole output layer in the state
            a = s.features[i]
            ng = self.Ros @ (self.W2 @ a) + self.ng_bias
            torch.mul(self.Ros[:, :, None], a, out=self.Hw)
        elif s.features is not None:
            a = s.features[i]
            self.w_full[s.active] = self.xw
            ng = self.Ros @ (self.w_full[s.o2 : s.o3].view(3, s.Hn) @ a) + self.ng_bias
            H[:, s.iw] = torch.kron(self.Ros, a[None, :])[:, s.w2_cols]
        elif self.net is not None:
            self.w_full[s.active] = self.xw
            ng, Hwt = self.jac(self.w_full[None], i)
            ng = ng[0]
            H[:, s.iw] = Hwt[0, :, s.active]
        else:
            ng = self.zero3
        if s.rot_cols:
            H[:, s.rot_cols] = _rotation_columns(self.R_axes, ng)
        self.ngo[i] = ng
        return s.y[i] - self.xt - ng - self.xd if s.nd else s.y[i] - self.xt - ng

    def update(self, i: int, e: Tensor) -> bool:
        """Gain and update (Eqs. 7-9) with the Joseph form; False (and ``status``) when ``S`` is not PD."""
        H, P = self.H, self.P
        Ut = H @ P
        S = torch.addmm(self.s.Ryy_q[i], Ut, H.T).add_(self.eye3, alpha=self.qyy * self.cfg.sigma_tracker**2)
        L, info = torch.linalg.cholesky_ex(S)
        if int(info) != 0:
            self.status = f"diverged at sample {i}: innovation covariance not positive definite"
            return False
        Kt = torch.cholesky_solve(Ut, L)  # K^T = S^-1 H P, (3, n)
        v = torch.cholesky_solve(e[:, None], L)
        self.nis[i] = e @ v[:, 0]
        self.x += e @ Kt
        joseph_update_(P, Ut, Kt, S)
        return True

    def check_window(self, i: int) -> bool:
        """End of a NIS window (:func:`~torchcal.filter._kalman.window_health`); False (and ``status``) on
        divergence, else the variance factor adapted."""
        W = self.cfg.nis_window
        health = window_health(
            self.P[None],
            self.nis[None, i + 1 - W : i + 1],
            torch.tensor([self.qyy], dtype=self.P.dtype, device=self.P.device),
            i,
            self.band,
            self.cfg.adapt_qyy,
        )
        if bool(health.failed[0]):
            self.status = health.reasons[0]
            return False
        self.qyy = float(health.qyy[0])
        return True


def _rotation_columns(R_axes: Tensor, ng: Tensor) -> Tensor:
    """Columns ``d(R exp(r) g)/dr_a`` ``(3, m)`` of the observation for the instrument rotation ``r``.

    ``d/dr (R exp(r) g) = -R [g]x = -[R g]x R`` (first order in ``r``, whose size is ~1e-4 rad), so the column of
    component ``a`` is ``R e_a x (R g)``. ``R_axes = R[:, axes] (3, m)``; ``ng = R g (3,)`` the rotated network
    output.
    """
    return torch.linalg.cross(R_axes, ng[:, None].expand_as(R_axes), dim=0)


def _strides(shape: torch.Size) -> list[int]:
    out, s = [], 1
    for d in reversed(shape):
        out.append(s)
        s *= d
    return out[::-1]


def _gauss_newton(fn, z0: Tensor, y: Tensor, W: Tensor, prior: Tensor, iterations: int, tol: float):
    """Gauss-Newton of the whitened residual ``W (y - f(z))`` with prior weights ``prior`` on ``z - z0``.

    Returns ``(z, Cholesky factor of the last normal matrix, iterations, status)``; raises where the normal matrix
    is not positive definite."""
    z = z0.clone()
    status = FitStatus.MAX_ITERATIONS
    n_it = 0
    for it in range(1, iterations + 1):
        n_it = it
        with torch.no_grad():
            Jz, f = torch.func.jacfwd(fn, has_aux=True)(z)
        A = (W @ Jz).reshape(-1, len(z))
        r = (W @ (y - f).unsqueeze(-1)).reshape(-1)
        Nm = A.T @ A + torch.diag(prior)
        g = A.T @ r - prior * (z - z0)
        Lc, info = torch.linalg.cholesky_ex(Nm)
        if int(info) != 0:
            raise EstimationError(
                "batch geometry: normal matrix not positive definite (parameters not identifiable at these poses?)"
            )
        dz = torch.cholesky_solve(g[:, None], Lc)[:, 0]
        z = z + dz
        if float(dz.abs().max()) < tol:
            status = FitStatus.CONVERGED
            break
    return z, Lc, n_it, status
