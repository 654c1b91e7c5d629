"""Plan a measurement campaign: the ``K`` poses that make a kinematic calibration most informative.

Candidates are given (a file of joint configurations the robot may take) or sampled within the joint limits where the
tracker sees the probe (:func:`sample_candidates`, the simulator's line-of-sight rule). Among them :func:`plan_poses`
picks ``K`` greedily by the I-optimal criterion (the mean position variance over the candidates; or the D-optimal one)
on the identifiable geometric, instrument and lever-arm parameters (:mod:`torchcal.estimate.design`), a share of the
picks (``edge_share``, default 10 %) among the candidates at the edges of the region (some joint beyond the 2.5 % or
97.5 % quantile of the candidates', as calibrate's held-out guard defines them,
:func:`~torchcal.pipeline.holdout.at_edges`): an optimal design favours poses that separate parameters, which are not
always those at the limits of where the robot will work, and a calibration is trusted there only if it was measured
there.

The prediction: the parameters' standard deviations after ``K`` poses and the predicted held-out RMSE over the
candidates (the region), for ``K`` and for a grid of sizes (the curve), with the same for ``K`` random candidates as a
reference. A learned correction's uncertainty is not a criterion yet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.estimate.design import (
    Priors,
    covariance,
    design_problem,
    greedy_design,
    information,
    log_det,
    predicted_rmse,
)
from torchcal.pipeline.holdout import HOLDOUT_EDGE, at_edges
from torchcal.robot import transforms as tf
from torchcal.sim.poses import Scene, random_poses

Tensor = torch.Tensor

#: the sizes of the curve of predicted error against K (those up to twice K or the candidates' number, K and that)
CURVE = (5, 10, 20, 30, 50, 100, 200, 300, 500, 1000, 2000, 5000, 10000)
#: where a tracker stands when nothing says where: 2.5 m in front of the base, 0.2 m above its plane (the simulator
#: draws 2-3 m and -0.3..0.5 m)
DEFAULT_TRACKER = (2.5, 0.0, 0.2)
#: the probe's lever arm on the flange when nothing says which [m] (the simulator's nominal)
DEFAULT_LEVER = (0.0, 0.0, 0.1)


@dataclass(frozen=True)
class PlanOptions:
    """What :func:`plan_poses` reads.

    Attributes:
        k: poses to pick.
        criterion: ``"I"`` (default) or ``"D"`` (:mod:`torchcal.estimate.design`).
        edge_share: share of the picks made among the candidates at the edges of the region (0: none).
        sigma_tracker: tracker noise per axis [m]; sigma_joint: joint noise [rad] (the fits' stochastic model).
        s0_sq: variance factor of the stochastic model (a run's own; 1 for simulated data).
        priors: the fits' priors.
        seed: of the random reference design.
    """

    k: int
    criterion: str = "I"
    edge_share: float = 0.1
    sigma_tracker: float = 15e-6
    sigma_joint: float = math.radians(0.0005)
    s0_sq: float = 1.0
    priors: Priors = field(default_factory=Priors)
    seed: int = 0


@dataclass
class Plan:
    """The planned poses and what they predict.

    Attributes:
        index: ``(K,)`` the chosen candidates' indices, in the order picked.
        q: ``(K, dof)`` their joints [rad].
        edge: ``(K,)`` bool, picked as an edge pose.
        names, units, sigma: the identifiable parameters and their predicted standard deviations after the ``K``
            poses [m or rad].
        held: the parameters no choice among the candidates determines (held in the fit), with the reason.
        predicted_rmse: predicted held-out RMSE over the candidates after the ``K`` poses [m].
        random_rmse: the same for ``K`` random candidates (seeded) [m].
        curve: ``[(k, predicted RMSE [m])]`` of the planned order's first ``k``.
        log_det, random_log_det: the D criterion of the planned and the random design.
    """

    index: Tensor
    q: Tensor
    edge: Tensor
    names: list[str]
    units: list[str]
    sigma: Tensor
    held: list[dict]
    predicted_rmse: float
    random_rmse: float
    curve: list[tuple[int, float]]
    log_det: float
    random_log_det: float
    n_candidates: int
    options: PlanOptions

    def to_dict(self) -> dict:
        scale = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg")}
        return {
            "k": len(self.index),
            "n_candidates": self.n_candidates,
            "criterion": f"greedy {self.options.criterion}-optimal on the whitened Jacobian of the identifiable "
            "geometry, instrument pose and lever arm, priors as the starting information",
            "edge_share": self.options.edge_share,
            "n_edge": int(self.edge.sum()),
            "stochastic_model": {
                "tracker_noise_um": self.options.sigma_tracker * 1e6,
                "joint_noise_deg": math.degrees(self.options.sigma_joint),
                "variance_factor": self.options.s0_sq,
            },
            "predicted_holdout_rmse_mm": self.predicted_rmse * 1e3,
            "random_predicted_holdout_rmse_mm": self.random_rmse * 1e3,
            "log_det": self.log_det,
            "random_log_det": self.random_log_det,
            "curve": [{"k": k, "predicted_holdout_rmse_mm": v * 1e3} for k, v in self.curve],
            "parameters": [
                {"name": n, "unit": scale[u][1], "sigma": float(s) * scale[u][0]}
                for n, u, s in zip(self.names, self.units, self.sigma.tolist())
            ],
            "held": [{"name": h["name"], "reason": h["reason"]} for h in self.held],
            "index": self.index.tolist(),
        }

    def markdown(self) -> str:
        d = self.to_dict()
        lines = [
            f"# Planned poses: {d['k']} of {d['n_candidates']} candidates",
            "",
            f"{d['criterion']}; {d['n_edge']} picked at the edges of the region.",
            "",
            f"- predicted held-out RMSE: {d['predicted_holdout_rmse_mm']:.4f} mm "
            f"({d['k']} random candidates: {d['random_predicted_holdout_rmse_mm']:.4f} mm)",
            f"- variance factor {d['stochastic_model']['variance_factor']:.3g}, tracker noise "
            f"{d['stochastic_model']['tracker_noise_um']:.3g} um",
            "",
            "| K | predicted held-out RMSE [mm] |",
            "|---:|---:|",
            *[f"| {c['k']} | {c['predicted_holdout_rmse_mm']:.4f} |" for c in d["curve"]],
            "",
            "| parameter | predicted sigma |",
            "|---|---:|",
            *[f"| {p['name']} | {p['sigma']:.3g} {p['unit']} |" for p in d["parameters"]],
            "",
        ]
        return "\n".join(lines)


def sample_candidates(
    model: MeasurementModel, n: int, seed: int, tracker_in_base: Tensor | None = None, lever: Tensor | None = None
) -> Tensor:
    """``n`` random poses ``(n, dof)`` within the joint limits that a tracker at ``tracker_in_base`` ``(3,)`` [m]
    (default :data:`DEFAULT_TRACKER`) sees with the lever arm ``lever`` ``(3,)`` [m] (default :data:`DEFAULT_LEVER`)
    (:func:`~torchcal.sim.poses.random_poses`)."""
    robot = model.robot
    dt = robot.dtype
    tb = torch.tensor(DEFAULT_TRACKER, dtype=dt) if tracker_in_base is None else tracker_in_base.to(dt)
    lv = torch.tensor(DEFAULT_LEVER, dtype=dt) if lever is None else lever.to(dt)
    try:
        return random_poses(Scene(robot, tb, lv), n, torch.Generator().manual_seed(seed))
    except RuntimeError as e:
        raise OptionError(f"{e}; give candidates in a file instead") from None


def scene_of(model: MeasurementModel) -> tuple[Tensor, Tensor]:
    """The tracker's position in the base frame ``(3,)`` and the lever arm ``(3,)`` [m] of a calibrated model."""
    robot = model.robot
    with torch.no_grad():
        return tf.invert(robot.T_tracker_base())[:3, 3].clone(), robot.t_flange_probe().clone()


def _random_index(n: int, k: int, seed: int) -> Tensor:
    return torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:k]


def plan_poses(model: MeasurementModel, q: Tensor, opts: PlanOptions) -> Plan:
    """Pick ``opts.k`` of the candidates ``q (N, dof)`` [rad] for ``model``'s robot (module docstring)."""
    if not 0.0 <= opts.edge_share <= 0.5:
        raise OptionError(f"edge_share must lie in [0, 0.5], got {opts.edge_share}")
    N = len(q)
    if not 1 <= opts.k <= N:
        raise OptionError(f"can plan 1 to {N} poses from {N} candidates, asked for {opts.k}")
    problem = design_problem(
        model, q, sigma_tracker=opts.sigma_tracker, sigma_joint=opts.sigma_joint, priors=opts.priors
    )
    edge = at_edges(q, q, HOLDOUT_EDGE)
    every = round(1.0 / opts.edge_share) if opts.edge_share > 0 else 0
    top = min(N, 2 * opts.k)
    grid = tuple(sorted({c for c in CURVE if c <= top} | {opts.k, top}))
    design = greedy_design(problem, max(grid), criterion=opts.criterion, restrict=edge, every=every, checkpoints=grid)
    curve = []
    for c in grid:
        S = covariance(design.information[c], opts.s0_sq)
        curve.append((c, predicted_rmse(problem.J, problem.noise, S, opts.s0_sq)))
    S_k = covariance(design.information[opts.k], opts.s0_sq)
    rnd = _random_index(N, opts.k, opts.seed)
    S_r = covariance(information(problem, rnd), opts.s0_sq)
    index = design.order[: opts.k]
    return Plan(
        index=index,
        q=q[index],
        edge=edge[index],
        names=problem.names,
        units=problem.units,
        sigma=S_k.diagonal().sqrt(),
        held=problem.identifiability.fixed,
        predicted_rmse=dict(curve)[opts.k],
        random_rmse=predicted_rmse(problem.J, problem.noise, S_r, opts.s0_sq),
        curve=curve,
        log_det=float(design.log_det[opts.k - 1]),
        random_log_det=log_det(problem, rnd),
        n_candidates=N,
        options=opts,
    )
