"""The integrated ANN-EKF of Horvath & Neuner (2024), Sec. 2.3 and Fig. 10.

Legend (one step ``i``; equation numbers of the paper):
``x = [w; t]`` state: the correction network's flat weights ``w`` and the probe position ``t`` in the
tracker frame; ``P`` its covariance; ``u = [theta_{i-1}, theta_i]`` the joints (control);
``R_tb`` the rotation of ``T_tracker_base``; ``p(theta)`` the probe in the base frame (kinematic model).

* prediction (Eqs. 13-17): ``t_bar = t_hat + R_tb (p(theta_i) - p(theta_{i-1}))`` -- the relative
  kinematics of Eq. 14 rotated into the tracker frame -- and ``w_bar = w_hat`` (static);
* process covariance (Eq. 19): ``P_bar = P + B Q_uu B^T + Q_pp`` with ``B = dt_bar/du``;
* observation (Eq. 20): ``h = t_bar + R_tb g(theta_i; w_bar)``, ``H = [R_tb dg/dw, I]``;
* gain and update (Eqs. 7-9): ``S = q_yy R_yy + H P_bar H^T``, ``K = P_bar H^T S^-1`` by Cholesky (two
  triangular solves with the 3x3 factor), ``x_hat = x_bar + K (y - h)``, Joseph-form covariance (on the fast
  path as one rank-6 update, symmetrised every ``nis_window`` steps; on the baseline path dense and symmetrised
  every step);
* innovation statistics: ``NIS = e^T S^-1 e`` (chi-square with 3 degrees of freedom for a consistent
  filter) per step; the variance factor ``q_yy`` adapts when a window of NIS fails its chi-square band
  (the compatibility test of Sec. 2.1.3);
* ANN re-iteration (Fig. 10): every ``reiterate_every`` updated samples the network is re-fitted by LM
  to the position corrections ``R_tb^T (y_j - t_bar_j)`` of Eq. 22 and fed back as the new ``w_bar``;
* test phase: prediction without updates.

Every run carries a leading *draw* dimension D (Monte Carlo draws filtered together).

The network is any ``nn.Module`` mapping joints ``(N, dof)`` [rad] to corrections ``(N, 3)`` [m] in the base
frame. The fast path (O(n^2) per step: one ``H P`` product and one rank-6 update of ``P``, into preallocated
buffers) takes its per-step Jacobian ``dg/dw`` from reverse-mode autodiff through the module
(:class:`~torchcal.filter._kalman.ModuleJacobian`), or, for :class:`~torchcal.effects.CorrectionNet`, from its
hand-derived form, which gives the same numbers for less. The Jacobian is evaluated every step at the
predicted weights: they change with every update, so a Jacobian computed ahead of the pass would linearise at
the wrong point.
``jacobian="autograd"`` is the baseline: a per-step ``jacrev``, dense ``H`` and the textbook Joseph form,
O(n^3) per step.

The filter needs a start the relative kinematics can follow: the tracker pose and the lever arm of the robot
model must describe the measurements (the prediction rotates the kinematic increments into the tracker frame).
:meth:`EKFTrainer.run` checks that on the first ``nis_window`` training samples and raises
:class:`~torchcal.errors.EstimationError` when it fails, or, with ``start="fit"``, fits both first by the
rigid fit of :func:`~torchcal.estimate.rigid.fit_instrument_and_tool` (the paper starts from such a fit).
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from enum import Enum

import torch
from torch import nn

from torchcal import _console
from torchcal._threads import torch_threads
from torchcal.effects.learned import CorrectionNet
from torchcal.errors import EstimationError, OptionError
from torchcal.estimate.netfit import fit_net
from torchcal.estimate.rigid import fit_instrument_and_tool
from torchcal.filter._kalman import FlatModule, Gain, ModuleJacobian, NetworkJacobian, as_flat, nis_band, window_health
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor

_JACOBIANS = ("auto", "analytic", "module", "autograd")
_STARTS = ("check", "fit", "none")


@dataclass
class EKFConfig:
    """Stochastic model and schedule of the filter (SI units)."""

    sigma_w0: float = 0.05  # a-priori std of every weight (the network works in mm, weights ~ 1)
    sigma_t0: float = 1e-3  # a-priori std of the initial probe position [m]
    q_w: float = 0.0  # process noise of the weights per step
    q_t: float = 1e-7  # process noise of the probe position per step [m]
    sigma_joint: float = math.radians(0.0005)  # joint noise [rad] (Q_uu)
    sigma_tracker: float = 15e-6  # tracker noise per axis [m] (R_yy)
    reiterate_every: int = 500  # 0 disables the ANN re-iteration
    reiterate_iterations: tuple[int, int] = (100, 200)  # LM iterations: first 7 re-iterations, then the rest
    reiterate_switch: int = 7
    reiterate_method: str = "lm"
    reiterate_ftol: float = 1e-6  # the paper stops after a fixed count; we also stop once converged
    adapt_qyy: bool = True
    nis_window: int = 100
    nis_alpha: float = 0.01
    # "auto": hand-derived for CorrectionNet, reverse-mode autodiff for any other module; "analytic" (CorrectionNet
    # only); "module" (autodiff, any module); "autograd" (per-step torch.func.jacrev, dense Joseph form: the baseline)
    jacobian: str = "auto"
    # "check": raise when the start cannot work (module docstring); "fit": fit tracker pose and lever arm first;
    # "none": no check
    start: str = "check"
    start_tolerance: float = 2e-3  # largest RMS misfit of the kinematic increments over the first window [m]

    def __post_init__(self):
        if self.jacobian not in _JACOBIANS:
            raise OptionError(f"jacobian '{self.jacobian}' is not one of {list(_JACOBIANS)}")
        if self.start not in _STARTS:
            raise OptionError(f"start '{self.start}' is not one of {list(_STARTS)}")
        if self.nis_window < 1:
            raise OptionError(f"nis_window must be >= 1, got {self.nis_window}")


class FilterStatus(str, Enum):
    """How a filter pass ended for one draw (str-valued: ``report.json`` writes the plain text).

    A draw that ran through is :attr:`OK`; one that stopped carries the reason instead, a text that starts with
    ``"diverged"`` (:attr:`DIVERGED`) and says at which sample and why.
    """

    OK = "ok"
    DIVERGED = "diverged"

    def __str__(self) -> str:
        return self.value


@dataclass
class EKFResult:
    """Per-sample outputs ``(D, N, ...)`` of a filter pass, and its health."""

    geometric: Tensor  # t (predicted state) [m], tracker frame
    nongeometric: Tensor  # R_tb g(theta; w) [m], tracker frame
    nis: Tensor  # (D, N), NaN in the test phase
    q_yy: Tensor  # (D, N)
    w: Tensor  # (D, n_w) final weights
    t: Tensor  # (D, 3) final probe position (after the last update, or the last prediction)
    P: Tensor  # (D, n, n) final covariance
    n_train: int
    status: list[FilterStatus | str] = field(default_factory=list)  # per draw: OK, or "diverged at sample i: why"
    reiterations: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    robot: RobotModel | None = None  # the kinematic model of the pass (a fitted copy with start="fit")
    start_misfit: float = float("nan")  # RMS misfit of the kinematic increments over the first window [m]

    @property
    def prediction(self) -> Tensor:
        return self.geometric + self.nongeometric

    @property
    def diverged(self) -> bool:
        return any(s != FilterStatus.OK for s in self.status)


class EKFTrainer:
    """The integrated ANN-EKF (module docstring).

    Args:
        robot: kinematic model whose instrument pose and lever arm (``T_tracker_base``, ``t_flange_probe``)
            describe the measurements (fitted, e.g. by :func:`~torchcal.estimate.rigid.fit_instrument_and_tool`,
            or let ``config.start = "fit"`` do it).
        net: the correction network, any ``nn.Module`` mapping joints ``(N, dof)`` to corrections ``(N, 3)`` [m]
            in the base frame (its architecture; the weights come from ``w0`` in :meth:`run`, in the order of
            ``net.parameters()``). ``config.sigma_w0`` is one a-priori std for every weight, so scale the output
            as :class:`~torchcal.effects.CorrectionNet` does (weights of order one for sub-millimetre fields).
        config: :class:`EKFConfig`.

    Example:
        A simulated trajectory, a nominal robot whose tracker pose and lever arm are unknown, a user's network.
        The nominal start is refused; ``start="fit"`` fits the tracker pose and the lever arm first:

        >>> import torch
        >>> from torch import nn
        >>> import torchcal
        >>> from torchcal.filter import EKFConfig, EKFTrainer
        >>> from torchcal.sim import EffectSpec, SimConfig, simulate
        >>> c = simulate(SimConfig(robot="ur5", trajectory=True, samples=600, train_samples=500, seed=0,
        ...                        effects=[EffectSpec.parse("field=0.15mm")]))
        >>> q, y = torch.cat([c.train.q, c.test.q]), torch.cat([c.train.p, c.test.p])
        >>> robot = torchcal.load_robot("ur5")
        >>> _ = torch.manual_seed(0)
        >>> net = nn.Sequential(nn.Linear(6, 16, dtype=torch.float64), nn.SiLU(),
        ...                     nn.Linear(16, 3, dtype=torch.float64, bias=False))
        >>> _ = net[2].weight.data.mul_(1e-3)  # sub-millimetre corrections from weights of order one
        >>> w0 = torch.nn.utils.parameters_to_vector(net.parameters()).detach()
        >>> EKFTrainer(robot, net).run(q, y, 500, w0)
        Traceback (most recent call last):
            ...
        torchcal.errors.EstimationError: ...
        >>> res = EKFTrainer(robot, net, EKFConfig(start="fit", reiterate_every=0)).run(q, y, 500, w0)
        >>> res.status == ["ok"], res.start_misfit < 1e-3  # the fitted start predicts the first increments in 1 mm
        (True, True)
        >>> e = (res.prediction[0, :500] - y[:500]).norm(dim=-1)  # the filtered samples
        >>> float(e.square().mean().sqrt()) < 1e-4
        True
    """

    def __init__(self, robot: RobotModel, net: nn.Module, config: EKFConfig | None = None):
        self.robot = robot
        self.net = net
        self.config = config or EKFConfig()
        self._net = as_flat(net, robot.dof)
        if self.config.jacobian == "analytic" and not isinstance(net, CorrectionNet):
            raise OptionError(
                f"jacobian 'analytic' is the hand-derived Jacobian of CorrectionNet, the network is "
                f"a {type(net).__name__}; use 'auto' or 'module'"
            )

    # ------------------------------------------------------------------ kinematics, batched once
    def kinematics(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Probe positions in the base frame ``(..., N, 3)``, their joint Jacobians ``(..., N, 3, dof)``, ``R_tb``."""
        robot = self.robot
        flat = q.reshape(-1, q.shape[-1])
        with torch.no_grad():
            p, J = robot.probe_jacobian(flat)
            R = robot.T_tracker_base()[:3, :3]
        return p.reshape(*q.shape[:-1], 3), J.reshape(*q.shape[:-1], 3, q.shape[-1]), R

    def predict_geometric(self, t0: Tensor, q: Tensor) -> Tensor:
        """Relative-kinematics prediction without updates (Eqs. 14-15): ``t_i = t_0 + R (p(theta_i) - p(theta_0))``."""
        p, _, R = self.kinematics(q)
        return t0.unsqueeze(-2) + (p - p[..., :1, :]) @ R.T

    # ------------------------------------------------------------------------------- the start
    def start_misfit(self, q: Tensor, y: Tensor, w0: Tensor, n_train: int) -> float:
        """RMS misfit [m] of the filter's first predictions over the first ``nis_window`` training samples.

        The prediction is relative (Eq. 14), so what must hold is that the measured increments
        ``y_i - y_0`` match the model's ``R_tb (p(theta_i) - p(theta_0) + g_i - g_0)``: a constant offset is
        absorbed by the start position, a wrong tracker rotation or lever arm is not. The worst draw counts.

        Args:
            q: ``(D, N, dof)``; y: ``(D, N, 3)``; w0: ``(D, n_w)``.
        """
        m = min(self.config.nis_window, n_train)
        qm, ym = q[:, :m], y[:, :m]
        p, _, R = self.kinematics(qm)
        with torch.no_grad():
            g = self._net.forward_flat(w0, qm)
        model = (p - p[:, :1] + g - g[:, :1]) @ R.T
        d = (ym - ym[:, :1]) - model
        ok = torch.isfinite(d).all(dim=-1)
        if not bool(ok.any()):
            return float("nan")
        return float(max(d[k][ok[k]].square().sum(-1).mean().sqrt() for k in range(len(d)) if bool(ok[k].any())))

    def fitted_start(self, q: Tensor, y: Tensor) -> RobotModel:
        """A copy of the robot with ``T_tracker_base`` and the lever arm fitted to ``(q, y)`` (rigid fit).

        Args:
            q: joints ``(N, dof)``; y: measured positions ``(N, 3)`` [m] (rows with NaN are skipped).
        """
        keep = torch.isfinite(y).all(dim=-1)
        robot = copy.deepcopy(self.robot)
        with torch.no_grad():
            T, lever, _ = fit_instrument_and_tool(robot(q[keep]), y[keep])
            robot.instrument.set_matrix(T)
            robot.tool.nominal.copy_(lever)
        return robot

    def _start(self, q: Tensor, y: Tensor, w0: Tensor, n_train: int) -> tuple[RobotModel, float]:
        """Apply ``config.start``: the robot of the pass and the start misfit (raises when the check fails)."""
        cfg = self.config
        if cfg.start == "none":
            return self.robot, float("nan")
        if cfg.start == "fit":
            self.robot = self.fitted_start(q[0, :n_train], y[0, :n_train])
        misfit = self.start_misfit(q, y, w0, n_train)
        if not misfit <= cfg.start_tolerance:
            raise EstimationError(
                f"the filter's start does not describe the measurements: over the first {min(cfg.nis_window, n_train)}"
                f" training samples the kinematic increments misfit by {misfit * 1e3:.3g} mm RMS (tolerance "
                f"{cfg.start_tolerance * 1e3:.3g} mm). The tracker pose and the lever arm of the robot must be fitted "
                "first (torchcal.estimate.fit_instrument_and_tool on the training data, or EKFConfig(start='fit')); "
                "a network whose start output is not small (sub-millimetre) also shows here"
            )
        return self.robot, misfit

    # ------------------------------------------------------------------------ initial weights
    def pcm_weights(
        self, q: Tensor, y: Tensor, w_start: Tensor, iterations: int = 200, val_fraction: float = 0.2, seed: int = 0
    ) -> Tensor:
        """Initial weights from the position correction model: the network fitted by LM to the corrections
        ``R_tb^T (y - T_tracker_base p(theta))`` of the training samples, starting from ``w_start``, early-stopped
        on a seeded validation share. This is the paper's own suggestion (Sec. 4) for the initialisation
        problem of Sec. 3.2.

        Args:
            q, y: training joints ``(N, dof)`` and measurements ``(N, 3)``; w_start: ``(n_w,)``.
        """
        with torch.no_grad():
            p = self.robot.probe_position(q)
            corr = (y - p) @ self.robot.T_tracker_base()[:3, :3]
        perm = torch.randperm(len(q), generator=torch.Generator().manual_seed(seed))
        n_val = int(val_fraction * len(q))
        net = copy.deepcopy(self._net)
        net.set_flat(w_start)
        fit_net(
            net,
            q[perm[n_val:]],
            corr[perm[n_val:]],
            val=(q[perm[:n_val]], corr[perm[:n_val]]),
            iterations=iterations,
            ftol=1e-9,
        )
        return net.flat()

    # -------------------------------------------------------------------------------- the pass
    def run(
        self, q: Tensor, y: Tensor, n_train: int, w0: Tensor, t0: Tensor | None = None, P0: Tensor | None = None
    ) -> EKFResult:
        """Filter the first ``n_train`` samples, predict the rest.

        The pass runs with one torch thread (its kernels are small; more threads only wait on each other) and
        restores the caller's thread count.

        Args:
            q: joints ``(D, N, dof)`` or ``(N, dof)`` [rad] (readings).
            y: measured probe positions ``(D, N, 3)`` or ``(N, 3)`` [m], tracker frame.
            n_train: samples used for updates; the rest is the test phase.
            w0: initial weights ``(D, n_w)`` or ``(n_w,)``.
            t0: initial probe position ``(D, 3)``; default the first measurement.
            P0: initial covariance ``(D, n, n)``; default diagonal from ``sigma_w0``, ``sigma_t0``.

        Raises:
            EstimationError: ``config.start == "check"`` and the start cannot work (module docstring).
        """
        with torch_threads(1):
            return self._run(q, y, n_train, w0, t0, P0)

    def _run(self, q, y, n_train, w0, t0, P0) -> EKFResult:
        t_start = time.perf_counter()
        q, y, w0 = _batch(q, 3), _batch(y, 3), _batch(w0, 2)
        D = max(q.shape[0], y.shape[0], w0.shape[0])
        q, y, w0 = q.expand(D, *q.shape[1:]), y.expand(D, *y.shape[1:]), w0.expand(D, -1)
        robot, misfit = self._start(q, y, w0, n_train)
        p = _Pass(self, q, y, n_train, w0, t0, P0)
        p.filter()
        p.test_phase()
        out = p.result()
        out.robot, out.start_misfit = robot, misfit
        out.seconds = time.perf_counter() - t_start
        return out

    def _step_jacobian(self, q: Tensor, R: Tensor, D: int):
        """The fast path's per-step Jacobian (hand-derived or autodiff), or None for the baseline."""
        kind = self.config.jacobian
        if kind == "autograd":
            return None
        if kind == "analytic" or (kind == "auto" and isinstance(self._net, CorrectionNet)):
            return NetworkJacobian(self._net, q, R, D)
        return ModuleJacobian(self._net, q, R, D)

    def _reiterate(self, w: Tensor, q: Tensor, corr: Tensor, iterations: int) -> tuple[Tensor, dict]:
        """Re-fit the network per draw from its current weights; returns the new weights."""
        cfg = self.config
        out, rmse, its = [], [], []
        net = copy.deepcopy(self._net)
        for d in range(w.shape[0]):
            net.set_flat(w[d])
            res = fit_net(
                net, q[d], corr[d], method=cfg.reiterate_method, iterations=iterations, ftol=cfg.reiterate_ftol
            )
            out.append(net.flat())
            rmse.append(res.train_rmse[-1])
            its.append(res.iterations)
        return torch.stack(out), {"train_rmse_m": rmse, "lm_iterations": its}


class _Pass:
    """One pass of :meth:`EKFTrainer.run` (module docstring).

    The state ``x = [w; t]`` ``(D, n)`` is only updated in place, so ``w`` and ``t`` (and ``P``'s blocks) are
    views set up once. Per-sample outputs are sample-major ``(N, D, ...)``, so that a step writes one contiguous
    row. :meth:`filter` runs, per training sample, :meth:`predict`, :meth:`observe`, :meth:`update`, and
    :meth:`check_window` / :meth:`reiterate` at the ends of their periods.
    """

    def __init__(
        self, tr: EKFTrainer, q: Tensor, y: Tensor, n_train: int, w0: Tensor, t0: Tensor | None, P0: Tensor | None
    ):
        cfg = tr.config
        self.tr, self.cfg, self.q, self.y, self.n_train = tr, cfg, q, y, n_train
        D, N, nw = q.shape[0], q.shape[1], w0.shape[-1]
        self.D, self.N, self.nw, self.n = D, N, nw, nw + 3
        kw = self.kw = {"dtype": q.dtype, "device": q.device}
        pb, Jq, self.R = tr.kinematics(q)
        R = self.R
        self.x = torch.cat([w0, y[:, 0] if t0 is None else _batch(t0, 2).expand(D, 3)], dim=-1)  # [w; t]
        self.w, self.t, self.x1 = self.x[:, :nw], self.x[:, nw:], self.x.unsqueeze(1)
        if P0 is None:
            diag = torch.cat([torch.full((nw,), cfg.sigma_w0**2, **kw), torch.full((3,), cfg.sigma_t0**2, **kw)])
            self.P = torch.diag(diag).expand(D, self.n, self.n).clone()
        else:
            self.P = _batch(P0, 3).expand(D, self.n, self.n).clone()
        self.P_tt, self.P_ww = self.P[:, nw:, nw:], self.P.diagonal(dim1=-2, dim2=-1)[:, :nw]
        self.Ryy = torch.eye(3, **kw) * cfg.sigma_tracker**2
        # process noise of the position per step (Eq. 19): joint noise at both ends of the step, (N - 1, D, 3, 3)
        JJ = Jq @ Jq.transpose(-1, -2)
        Qt = cfg.sigma_joint**2 * R @ (JJ[:, 1:] + JJ[:, :-1]) @ R.T + torch.eye(3, **kw) * cfg.q_t**2
        self.Qt = Qt.transpose(0, 1).contiguous()
        self.step = (torch.diff(pb, dim=1) @ R.T).transpose(0, 1).contiguous()  # R (p_i - p_{i-1}), (N - 1, D, 3)
        self.yT = y.transpose(0, 1).contiguous()
        self.geo, self.ngo = torch.full((N, D, 3), float("nan"), **kw), torch.full((N, D, 3), float("nan"), **kw)
        self.nis, self.qyy_h = torch.full((N, D), float("nan"), **kw), torch.full((N, D), float("nan"), **kw)
        # the innovations and S^-1 e per step; the NIS e^T S^-1 e is formed per window (:meth:`_nis_upto`)
        self.E, self.SE = torch.zeros(N, D, 3, **kw), torch.zeros(N, D, 3, 1, **kw)
        self.nis_done = 0
        self.qyy = torch.ones(D, **kw)
        self.qR = self.qyy[:, None, None] * self.Ryy
        self.status: list[FilterStatus | str] = [FilterStatus.OK] * D
        self.alive = torch.ones(D, dtype=torch.bool, device=q.device)
        self.all_alive = True
        self.band = nis_band(cfg.nis_window, cfg.nis_alpha)
        self.reiters: list[dict] = []
        self.eye3 = torch.eye(3, **kw).expand(D, 3, 3)
        self.jac = tr._step_jacobian(q, R, D)
        self.fast = self.jac is not None
        self.kal = Gain(D, self.n, self.x)
        self.win = 0  # first sample of the current NIS window
        self.last = -1  # the last sample filtered

    def filter(self) -> None:
        cfg = self.cfg
        for i in _console.progress(range(self.n_train), desc="integrated: filter"):
            self.last = i
            if i > 0:
                self.predict(i)
            self.geo[i] = self.t
            H, e = self.observe(i)
            if not self.update(i, H, e):
                break
            if (i + 1) % cfg.nis_window == 0:
                self.check_window(i)
            if cfg.reiterate_every and (i + 1) % cfg.reiterate_every == 0 and i + 1 < self.n_train:
                self.reiterate(i)
        self.qyy_h[self.win : self.last + 1] = self.qyy
        self._nis_upto(self.last + 1)

    def _nis_upto(self, b: int) -> None:
        """The NIS ``e^T S^-1 e`` of the samples filtered since the last call, up to ``b`` (exclusive)."""
        a, self.nis_done = self.nis_done, b
        self.nis[a:b] = (self.E[a:b] * self.SE[a:b, ..., 0]).sum(dim=-1)

    def predict(self, i: int) -> None:
        """Prediction (Eqs. 15-19): the kinematic increment, its process noise; the weights are static."""
        self.t.add_(self.step[i - 1])
        self.P_tt.add_(self.Qt[i - 1])
        if self.cfg.q_w > 0:
            self.P_ww.add_(self.cfg.q_w**2)

    def observe(self, i: int) -> tuple[Tensor, Tensor]:
        """Observation (Eq. 20) and its Jacobian (Eq. 21): ``H = [R dg/dw, I]`` and the innovation ``e (D, 3)``."""
        if self.fast:
            ng, H = self.jac(self.w, i)
        else:
            g, Jg = _autograd_jacobian(self.tr._net, self.w, self.q[:, i])
            ng, H = g @ self.R.T, torch.cat([self.R @ Jg, self.eye3], dim=-1)
        self.ngo[i] = ng
        return H, torch.sub(self.yT[i], self.t, out=self.E[i]).sub_(ng)

    def update(self, i: int, H: Tensor, e: Tensor) -> bool:
        """Gain and update (Eqs. 7-9), Joseph form; False once no draw is left (``status`` says why).

        ``e (D, 3)`` is the innovation, a row of ``E``; ``S^-1 e`` goes into the row ``i`` of ``SE``.
        """
        P, qR, alive = self.P, self.qR, self.alive
        if self.fast:  # U^T = H P (P symmetric), S = H P H^T + q_yy R
            S, L, info = self.kal.gain(H, self.jac.HT, P, qR)
        else:
            Ut = H @ P
            S = H @ Ut.mT + qR
            L, info = torch.linalg.cholesky_ex(S)
        if info.item() if self.D == 1 else info.any().item():
            for d in torch.nonzero((info != 0) & alive).flatten().tolist():
                self.status[d] = f"diverged at sample {i}: innovation covariance not positive definite"
            alive &= info == 0
            self.all_alive = False
            if not bool(alive.any()):
                self.E[i] = float("nan")  # no NIS at the sample where the last draw failed
                return False
        if not self.all_alive:  # frozen draws keep their state
            L = torch.where(alive[:, None, None], L, self.eye3)
        se = self.SE[i]
        if self.fast:
            Kt = self.kal.solve(L, e.unsqueeze(-1), se)
        else:
            Kt = torch.cholesky_solve(Ut, L)
            torch.cholesky_solve(e.unsqueeze(-1), L, out=se)
        if not self.all_alive:
            Kt.mul_(alive[:, None, None])
            se.mul_(alive[:, None, None])
        if self.fast:  # x += K e = U (S^-1 e) (Eq. 9), in place
            self.x1.baddbmm_(se.mT, self.kal.Ut)
            self.kal.joseph_(P, S)
        else:  # the baseline: x += K e; (I - K H) P (I - K H)^T + K (q_yy R) K^T, dense, symmetrised every step
            self.x1.baddbmm_(e.unsqueeze(1), Kt)
            IKH = torch.eye(self.n, **self.kw) - Kt.mT @ H
            P.copy_(IKH @ P @ IKH.mT + Kt.mT @ qR @ Kt)
            P.copy_(0.5 * (P + P.mT))
        if not self.all_alive:  # a frozen draw has no NIS
            self.E[i][~alive] = float("nan")
        return True

    def check_window(self, i: int) -> None:
        """Health and the compatibility test of the window's variance factor (Sec. 2.1.3)."""
        W = self.cfg.nis_window
        self.qyy_h[self.win : i + 1] = self.qyy
        self.win = i + 1
        self._nis_upto(i + 1)
        health = window_health(self.P, self.nis[i + 1 - W : i + 1].T, self.qyy, i, self.band, self.cfg.adapt_qyy)
        for d, why in enumerate(health.reasons):
            if why is not None and bool(self.alive[d]):
                self.status[d] = why
        self.alive &= ~health.failed
        self.all_alive = bool(self.alive.all())
        self.qyy = torch.where(self.alive, health.qyy, self.qyy)
        self.qR = self.qyy[:, None, None] * self.Ryy

    def reiterate(self, i: int) -> None:
        """ANN re-iteration (Fig. 10) on the corrections of Eq. 22, ``R^T (y - t_bar)`` in the base frame."""
        cfg = self.cfg
        k = len(self.reiters)
        iters = cfg.reiterate_iterations[0 if k < cfg.reiterate_switch else 1]
        corr = (self.y[:, : i + 1] - self.geo[: i + 1].transpose(0, 1)) @ self.R
        w_new, info = self.tr._reiterate(self.w, self.q[:, : i + 1], corr, iters)
        self.w.copy_(w_new)
        self.reiters.append({"sample": i + 1, "iterations": iters, **info})

    def test_phase(self) -> None:
        """Prediction without updates for the samples after ``n_train``, all at once."""
        n_train = self.n_train
        if n_train >= self.N or not bool(self.alive.any()):
            return
        self.geo[n_train:] = self.t + torch.cumsum(self.step[n_train - 1 :], dim=0)
        with torch.no_grad():
            self.ngo[n_train:] = (self.tr._net.forward_flat(self.w, self.q[:, n_train:]) @ self.R.T).transpose(0, 1)
        self.t = self.geo[-1]

    def result(self) -> EKFResult:
        return EKFResult(
            geometric=self.geo.transpose(0, 1).contiguous(),
            nongeometric=self.ngo.transpose(0, 1).contiguous(),
            nis=self.nis.T.contiguous(),
            q_yy=self.qyy_h.T.contiguous(),
            w=self.w.clone(),
            t=self.t.clone(),
            P=self.P,
            n_train=self.n_train,
            status=self.status,
            reiterations=self.reiters,
        )


def _batch(x: Tensor, ndim: int) -> Tensor:
    return x if x.ndim == ndim else x.unsqueeze(0)


def _autograd_jacobian(net: CorrectionNet | FlatModule, w: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """Per-step ``torch.func.jacrev`` of the network output, draw by draw (the baseline path)."""
    g, J = [], []
    for d in range(w.shape[0]):
        fn = lambda ww, qq=q[d]: net.forward_flat(ww, qq[None])[0]  # noqa: E731
        J.append(torch.func.jacrev(fn)(w[d]))
        g.append(fn(w[d]))
    return torch.stack(g).detach(), torch.stack(J).detach()
