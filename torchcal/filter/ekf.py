"""The integrated ANN-EKF of Horvath & Neuner (2024), Sec. 2.3 and Fig. 10.

Legend (one step ``i``; equation numbers of the paper):
``x = [w; t]`` state: the correction network's flat weights ``w`` and the probe position ``t`` in the
tracker frame; ``P`` its covariance; ``u = [theta_{i-1}, theta_i]`` the joints (control);
``R_tb`` the rotation of ``T_tracker_base``; ``p(theta)`` the probe in the base frame (kinematic model).

* prediction (Eqs. 13-17): ``t_bar = t_hat + R_tb (p(theta_i) - p(theta_{i-1}))`` -- the relative
  kinematics of Eq. 14 rotated into the tracker frame -- and ``w_bar = w_hat`` (static);
* process covariance (Eq. 19): ``P_bar = P + B Q_uu B^T + Q_pp`` with ``B = dt_bar/du``;
* observation (Eq. 20): ``h = t_bar + R_tb g(theta_i; w_bar)``, ``H = [R_tb dg/dw, I]``;
* gain and update (Eqs. 7-9): ``S = q_yy R_yy + H P_bar H^T``, ``K = P_bar H^T S^-1`` by Cholesky,
  ``x_hat = x_bar + K (y - h)``, Joseph-form covariance (on the fast path as one rank-6 update, symmetrised
  every ``nis_window`` steps; on the baseline path dense and symmetrised every step);
* innovation statistics: ``NIS = e^T S^-1 e`` (chi-square with 3 degrees of freedom for a consistent
  filter) per step; the variance factor ``q_yy`` adapts when a window of NIS fails its chi-square band
  (the compatibility test of Sec. 2.1.3);
* ANN re-iteration (Fig. 10): every ``reiterate_every`` updated samples the network is re-fitted by LM
  to the position corrections ``R_tb^T (y_j - t_bar_j)`` of Eq. 22 and fed back as the new ``w_bar``;
* test phase: prediction without updates.

Every run carries a leading *draw* dimension D (Monte Carlo draws filtered together).
The fast path uses the network's analytic Jacobian and rank-3 covariance updates (O(n^2) per step);
``jacobian="autograd"`` uses ``torch.func.jacrev`` per step, the baseline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal.effects.learned import CorrectionNet
from torchcal.errors import OptionError
from torchcal.estimate.lm import chi2_quantile
from torchcal.estimate.netfit import fit_net
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor


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
    jacobian: str = "analytic"  # or "autograd" (per-step jacrev: the baseline)

    def __post_init__(self):
        if self.jacobian not in ("analytic", "autograd"):
            raise OptionError(f"jacobian '{self.jacobian}' is not one of ['analytic', 'autograd']")


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
    status: list[str] = field(default_factory=list)  # per draw: "ok" or "diverged at sample i: why"
    reiterations: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def prediction(self) -> Tensor:
        return self.geometric + self.nongeometric

    @property
    def diverged(self) -> bool:
        return any(s != "ok" for s in self.status)


class EKFTrainer:
    """The integrated ANN-EKF (module docstring).

    Args:
        robot: kinematic model with its instrument pose and lever arm (``T_tracker_base``, ``t_flange_probe``).
        net: the correction network (its architecture; the weights come from ``w0`` in :meth:`run`).
        config: :class:`EKFConfig`.
    """

    def __init__(self, robot: RobotModel, net: CorrectionNet, config: EKFConfig | None = None):
        self.robot = robot
        self.net = net
        self.config = config or EKFConfig()

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

    # ------------------------------------------------------------------------ initial weights
    def pcm_weights(self, q: Tensor, y: Tensor, w_start: Tensor, iterations: int = 200,
                    val_fraction: float = 0.2, seed: int = 0) -> Tensor:
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
        net = CorrectionNet(self.net.dof, self.net.hidden, dtype=q.dtype)
        net.load_state_dict(self.net.state_dict())
        net.set_flat(w_start)
        fit_net(net, q[perm[n_val:]], corr[perm[n_val:]], val=(q[perm[:n_val]], corr[perm[:n_val]]),
                iterations=iterations, ftol=1e-9)
        return net.flat()

    # -------------------------------------------------------------------------------- the pass
    def run(self, q: Tensor, y: Tensor, n_train: int, w0: Tensor, t0: Tensor | None = None,
            P0: Tensor | None = None) -> EKFResult:
        """Filter the first ``n_train`` samples, predict the rest.

        Args:
            q: joints ``(D, N, dof)`` or ``(N, dof)`` [rad] (readings).
            y: measured probe positions ``(D, N, 3)`` or ``(N, 3)`` [m], tracker frame.
            n_train: samples used for updates; the rest is the test phase.
            w0: initial weights ``(D, n_w)`` or ``(n_w,)``.
            t0: initial probe position ``(D, 3)``; default the first measurement.
            P0: initial covariance ``(D, n, n)``; default diagonal from ``sigma_w0``, ``sigma_t0``.
        """
        import time

        cfg = self.config
        t_start = time.perf_counter()
        q, y, w0 = _batch(q, 3), _batch(y, 3), _batch(w0, 2)
        D = max(q.shape[0], y.shape[0], w0.shape[0])
        q, y, w = q.expand(D, *q.shape[1:]), y.expand(D, *y.shape[1:]), w0.expand(D, -1).clone()
        N = q.shape[1]
        nw = w.shape[-1]
        n = nw + 3
        dt, dev = q.dtype, q.device
        kw = {"dtype": dt, "device": dev}
        pb, Jq, R = self.kinematics(q)
        t = (y[:, 0].clone() if t0 is None else _batch(t0, 2).expand(D, 3).clone())
        if P0 is None:
            diag = torch.cat([torch.full((nw,), cfg.sigma_w0**2, **kw), torch.full((3,), cfg.sigma_t0**2, **kw)])
            P = torch.diag(diag).expand(D, n, n).clone()
        else:
            P = _batch(P0, 3).expand(D, n, n).clone()
        Ryy = torch.eye(3, **kw) * cfg.sigma_tracker**2
        # process noise of the position per step (Eq. 19): joint noise at both ends of the step
        JJ = Jq @ Jq.transpose(-1, -2)
        Qt = cfg.sigma_joint**2 * R @ (JJ[:, 1:] + JJ[:, :-1]) @ R.T + torch.eye(3, **kw) * cfg.q_t**2
        geo_l, ngo_l, nis_l, qyy_l = [], [], [], []  # per-sample outputs, stacked at the end
        qyy = torch.ones(D, **kw)
        status = ["ok"] * D
        alive = torch.ones(D, dtype=torch.bool, device=dev)
        band = _nis_band(cfg.nis_window, cfg.nis_alpha)
        reiters = []
        eye_n = torch.eye(n, **kw)
        eye3 = torch.eye(3, **kw).expand(D, 3, 3)
        fast = cfg.jacobian == "analytic"
        step = torch.diff(pb, dim=1) @ R.T  # kinematic increments R (p_i - p_{i-1}), all at once
        if fast:
            jac = _StepJacobian(self.net, q, R, D)
        all_alive = True
        for i in range(N):
            if i > 0:  # prediction (Eqs. 15-19)
                t = t + step[:, i - 1]
                if i < n_train:
                    P[:, nw:, nw:] += Qt[:, i - 1]
                    if cfg.q_w > 0:
                        P.diagonal(dim1=-2, dim2=-1)[:, :nw] += cfg.q_w**2
            geo_l.append(t)
            if i >= n_train:  # test phase: prediction only
                ngo_l.append(self.net.forward_flat(w, q[:, i : i + 1])[:, 0] @ R.T)
                continue
            qyy_l.append(qyy)
            # observation (Eq. 20) and its Jacobian (Eq. 21)
            if fast:
                ng, H = jac(w, i)  # R g and H = [R dg/dw, I]
            else:
                g, Jg = _autograd_jacobian(self.net, w, q[:, i])
                ng = g @ R.T
            ngo_l.append(ng)
            e = y[:, i] - t - ng
            # gain and update (Eqs. 7-9) with Ut = (P H^T)^T = H P (P symmetric), S = H P H^T + q_yy R
            if fast:
                Ut = H @ P
                S = torch.baddbmm(qyy[:, None, None] * Ryy, Ut, H.transpose(-1, -2))
            else:  # the baseline: H built from the autograd Jacobian, dense products
                H = torch.cat([R @ Jg, eye3], dim=-1)
                Ut = H @ P
                S = H @ Ut.transpose(-1, -2) + qyy[:, None, None] * Ryy
            L, info = torch.linalg.cholesky_ex(S)
            if bool(info.any()):
                for d in torch.nonzero((info != 0) & alive).flatten().tolist():
                    status[d] = f"diverged at sample {i}: innovation covariance not positive definite"
                alive &= info == 0
                all_alive = False
                if not bool(alive.any()):
                    break
            if not all_alive:  # frozen draws keep their state
                L = torch.where(alive[:, None, None], L, eye3)
            Kt = torch.cholesky_solve(Ut, L)  # K^T = S^-1 U^T, (D, 3, n)
            if not all_alive:
                Kt = Kt * alive[:, None, None]
            v = torch.cholesky_solve(e.unsqueeze(-1), L)
            nis_l.append((e.unsqueeze(-2) @ v)[:, 0, 0])
            dx = (e.unsqueeze(-2) @ Kt)[:, 0]
            w = w + dx[:, :nw]
            t = t + dx[:, nw:]
            if fast:  # Joseph form as one rank-6 update: P - K U^T - U K^T + K S K^T = P + [-K, KS - U] [U, K]^T
                At = torch.cat([-Kt, S @ Kt - Ut], dim=-2)
                Bt = torch.cat([Ut, Kt], dim=-2)
                P.baddbmm_(At.transpose(-1, -2), Bt)  # in place: the GEMM accumulates into P, no copy of P
            else:
                IKH = eye_n - Kt.transpose(-1, -2) @ H
                P = IKH @ P @ IKH.transpose(-1, -2) + Kt.transpose(-1, -2) @ (qyy[:, None, None] * Ryy) @ Kt
                P = 0.5 * (P + P.transpose(-1, -2))
            # health and the compatibility test of the window's variance factor (Sec. 2.1.3)
            if (i + 1) % cfg.nis_window == 0:
                P = 0.5 * (P + P.transpose(-1, -2))  # the rank-6 update is symmetric up to round-off
                pd = P.diagonal(dim1=-2, dim2=-1)  # zero variances are fixed states; negative ones are trouble
                neg = (pd.min(dim=-1).values < -1e-9 * pd.max(dim=-1).values) & alive
                for d in torch.nonzero(neg).flatten().tolist():
                    status[d] = f"diverged by sample {i}: negative state variance"
                alive &= ~neg
                ratio = torch.stack(nis_l[-cfg.nis_window :], dim=-1).mean(dim=-1) / 3.0
                runaway = (ratio > 1e4) & alive
                for d in torch.nonzero(runaway).flatten().tolist():
                    status[d] = f"diverged at sample {i}: NIS {float(ratio[d]) * 3:.3g} far outside its chi2 band"
                alive &= ~runaway
                all_alive = bool(alive.all())
                if cfg.adapt_qyy:
                    out = (ratio < band[0]) | (ratio > band[1])
                    qyy = torch.where(out & alive, (qyy * ratio).clamp(1e-2, 1e6), qyy)
            # ANN re-iteration (Fig. 10) on the corrections of Eq. 22
            if cfg.reiterate_every and (i + 1) % cfg.reiterate_every == 0 and i + 1 < n_train:
                k = len(reiters)
                iters = cfg.reiterate_iterations[0 if k < cfg.reiterate_switch else 1]
                corr = (y[:, : i + 1] - torch.stack(geo_l, dim=1)) @ R  # R^T (y - t_bar), base frame
                w, info_r = self._reiterate(w, q[:, : i + 1], corr, iters)
                reiters.append({"sample": i + 1, "iterations": iters, **info_r})
        geo, ngo = _stack(geo_l, (D, N, 3), kw), _stack(ngo_l, (D, N, 3), kw)
        nis, qyy_hist = _stack(nis_l, (D, N), kw), _stack(qyy_l, (D, N), kw)
        return EKFResult(geo, ngo, nis, qyy_hist, w, t, P, n_train, status, reiters, time.perf_counter() - t_start)

    def _reiterate(self, w: Tensor, q: Tensor, corr: Tensor, iterations: int) -> tuple[Tensor, dict]:
        """Re-fit the network per draw from its current weights; returns the new weights."""
        cfg = self.config
        out, rmse, its = [], [], []
        net = CorrectionNet(self.net.dof, self.net.hidden, dtype=w.dtype)
        net.load_state_dict(self.net.state_dict())
        for d in range(w.shape[0]):
            net.set_flat(w[d])
            res = fit_net(net, q[d], corr[d], method=cfg.reiterate_method, iterations=iterations,
                          ftol=cfg.reiterate_ftol)
            out.append(net.flat())
            rmse.append(res.train_rmse[-1])
            its.append(res.iterations)
        return torch.stack(out), {"train_rmse_m": rmse, "lm_iterations": its}


class _StepJacobian:
    """The rotated network output ``R g`` and the observation Jacobian ``H = [R dg/dw, I]`` at one sample.

    Written straight into a preallocated ``H`` buffer: the rotation folds into the blocks
    (``R (ds x^T) = (R ds) x^T`` for the first layer, ``R (I kron a) = R kron a`` for the second),
    the constant blocks (output bias, the identity for the position) are set once, the inputs are
    normalised once. Same values as ``R @ CorrectionNet.jacobian_flat``.
    """

    def __init__(self, net: CorrectionNet, q: Tensor, R: Tensor, D: int):
        H, Dq = net.hidden, net.dof
        self.Hn, self.Dq, self.R = H, Dq, R
        self.x = (q - net.q_offset) / net.q_scale  # (D, N, dof)
        self.os = float(net.out_scale)
        self.Ros = R * self.os  # the rotation with the network's output scale folded in
        nw = net.n_weights
        self.o1, self.o2, self.o3 = H * Dq, H * Dq + H, H * Dq + H + 3 * H
        self.Hbuf = torch.zeros(D, 3, nw + 3, dtype=q.dtype, device=q.device)
        self.Hbuf[:, :, self.o3 : nw] = R * self.os  # output bias block: R os
        self.Hbuf[:, :, nw:] = torch.eye(3, dtype=q.dtype, device=q.device)  # the position block

    def __call__(self, w: Tensor, i: int) -> tuple[Tensor, Tensor]:
        Hn, Dq, Hb, Ros = self.Hn, self.Dq, self.Hbuf, self.Ros
        W2 = w[:, self.o2 : self.o3].reshape(-1, 3, Hn)
        x = self.x[:, i]
        a = torch.tanh(torch.baddbmm(w[:, self.o1 : self.o2, None], w[:, : self.o1].reshape(-1, Hn, Dq),
                                     x[:, :, None]))[..., 0]  # (D, H)
        ng = torch.baddbmm(w[:, self.o3 :, None], W2, a[:, :, None])[..., 0] @ Ros.T
        Rds = (Ros @ W2) * (1.0 - a * a)[:, None, :]  # d(R g)/dz, (D, 3, H)
        Hb[:, :, : self.o1].view(-1, 3, Hn, Dq).copy_(Rds[..., None] * x[:, None, None, :])
        Hb[:, :, self.o1 : self.o2] = Rds
        Hb[:, :, self.o2 : self.o3].view(-1, 3, 3, Hn).copy_(Ros[None, :, :, None] * a[:, None, None, :])
        return ng, Hb


def _stack(items: list[Tensor], shape: tuple, kw: dict) -> Tensor:
    """Per-sample outputs stacked along dimension 1, NaN-padded to ``shape`` (a pass stopped early, or no update)."""
    out = torch.full(shape, float("nan"), **kw)
    if items:
        out[:, : len(items)] = torch.stack(items, dim=1)
    return out


def _batch(x: Tensor, ndim: int) -> Tensor:
    return x if x.ndim == ndim else x.unsqueeze(0)


def _nis_band(window: int, alpha: float) -> tuple[float, float]:
    """Two-sided band of the mean NIS / 3 over a window (chi-square with 3 * window degrees of freedom)."""
    k = 3 * window
    return chi2_quantile(alpha / 2, k) / k, chi2_quantile(1 - alpha / 2, k) / k


def _autograd_jacobian(net: CorrectionNet, w: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """Per-step ``torch.func.jacrev`` of the network output (the baseline path)."""
    g, J = [], []
    for d in range(w.shape[0]):
        fn = lambda ww, qq=q[d]: net.forward_flat(ww, qq[None])[0]  # noqa: E731
        J.append(torch.func.jacrev(fn)(w[d]))
        g.append(fn(w[d]))
    return torch.stack(g).detach(), torch.stack(J).detach()
