"""The joint LM refinement of geometry, instrument pose, lever arm and a correction network's weights.

The batch form of the simultaneous estimation the integrated ANN-EKF aims at (Horvath & Neuner 2024, Sec. 2.3):
the kinematic calibration has taken the share of the non-geometric field that looks geometric into the geometry,
and estimating both together can move that share back. It can also make things worse, so the state is judged on
later samples after every restart and the best one (the start included) is kept.
"""

from __future__ import annotations

import torch

from torchcal import stats as S
from torchcal.data import Measurements
from torchcal.effects import Context, MeasurementModel
from torchcal.errors import EstimationError
from torchcal.estimate.fit import errors
from torchcal.estimate.lm import LMResult, levenberg_marquardt
from torchcal.estimate.problem import FreeParameters, prior_sigmas, residual_function, whitening

Tensor = torch.Tensor

#: LM is restarted with a fresh damping every JOINT_RESTART iterations: the fit crawls along the valley where
#: geometry and network trade places, and a damping that grew in its curved stretches otherwise keeps the later
#: steps short
JOINT_RESTART = 10


def refine_jointly(
    model: MeasurementModel,
    m: Measurements,
    identifiability,
    opts,
    iterations: int,
    validation: Measurements | None = None,
) -> tuple[LMResult, dict]:
    """Weighted LM over the identifiable geometry, the instrument pose, the lever arm and the network's weights.

    With ``validation`` (later samples of the trajectory than ``m``), the parameters after the restart with the
    lowest validation RMSE are kept (none at all included: then the starting values stay); returns the LM
    result and that history.

    The model's last effect must be the :class:`LearnedEffect`. The geometric columns of the Jacobian come
    from ``torch.func.jacfwd`` over the few geometric parameters, the network's from its analytic Jacobian
    (rotated into the tracker frame and whitened), which keeps an iteration cheap with ~300 weights. The
    geometry keeps the run's a-priori sigmas; the weights have none. The normal matrix is singular (a tanh
    network has symmetric weight sets), which LM's damping handles; the result's statistics are not used.
    Steps: :func:`_joint_parameters` (what is free), :func:`_joint_problem` (residuals and Jacobian),
    :func:`_joint_restarts` (LM with restarts, judged on ``validation``).
    """
    free, n_geo = _joint_parameters(model, identifiability)
    fun, jacobian = _joint_problem(model, free, n_geo, m, opts)

    def score(history: list) -> float:
        return S.rmse(errors(model, validation, trajectory=True)) if validation is not None else -float(len(history))

    return _joint_restarts(fun, jacobian, free, iterations, score, validation is not None)


def _joint_parameters(model: MeasurementModel, identifiability) -> tuple[FreeParameters, int]:
    """The free parameters of the joint refinement: the identifiable elements of the geometry, instrument and
    tool groups (all of them without an identifiability analysis), then every weight of the model's last effect's
    network; and how many of them are geometric."""
    robot = model.robot
    keep = {} if identifiability is None else dict(zip(identifiability.names, identifiability.free.tolist()))
    sel, labels = {}, {}
    for g in ("geometry", "instrument", "tool"):
        grp = robot.groups()[g]
        mask = grp.mask.clone()
        if identifiability is not None:
            mask &= torch.tensor([keep.get(n, False) for n in grp.names], device=mask.device).reshape(mask.shape)
        sel[f"robot.{g}.delta"], labels[f"robot.{g}.delta"] = mask, grp.names
    n_geo = sum(int(mk.sum()) for mk in sel.values())
    k = len(model.effects) - 1
    for name, p in model.effects[k].net.named_parameters():
        sel[f"effects.{k}.net.{name}"] = torch.ones(p.shape, dtype=torch.bool, device=p.device)
    return FreeParameters(model, sel, labels), n_geo


def _joint_problem(model: MeasurementModel, free: FreeParameters, n_geo: int, m: Measurements, opts):
    """The whitened residual function of the joint refinement (observations, then the geometry's prior rows) and
    its Jacobian: ``jacfwd`` over the geometric columns, the network's analytic Jacobian for the weights."""
    robot, net = model.robot, model.effects[-1].net
    ctx = Context.from_measurements(m, trajectory=True)
    W = whitening(model, ctx, m.sigma, opts.sigma_tracker, opts.sigma_joint)
    prior = None
    if opts.prior_length is not None and opts.prior_angle is not None:
        units = {i.name: i.unit for i in robot.parameter_info() if i.group == "geometry"}
        prior = prior_sigmas(free, units, opts.prior_length, opts.prior_angle)
    fun = residual_function(model, free, ctx, m.p, W, prior)
    n_obs = 3 * m.n

    def jacobian(x: Tensor) -> Tensor:
        xg, xn = x[:n_geo], x[n_geo:]
        Jg = torch.func.jacfwd(lambda a: fun(torch.cat([a, xn])))(xg)  # observations and the geometry's prior
        with torch.no_grad():
            R = robot.T_tracker_base()[:3, :3]
            Jn = (W @ R @ net.jacobian_flat(xn, m.q)[1]).reshape(n_obs, -1)
        J = torch.zeros(len(Jg), len(x), dtype=x.dtype, device=x.device)
        J[:, :n_geo] = Jg
        J[:n_obs, n_geo:] = Jn  # the prior rows concern the geometry only
        return J

    return fun, jacobian


def _joint_restarts(fun, jacobian, free: FreeParameters, iterations: int, score, judged: bool) -> tuple[LMResult, dict]:
    """LM restarted with a fresh damping every JOINT_RESTART iterations (module constant); after each restart
    ``score(history)`` judges the state (lower is better), and the best one (the start included) is kept."""
    done, history, trail = 0, [], []
    best = (score(history), 0, free.vector())
    while done < iterations:
        res = levenberg_marquardt(
            fun, free.vector(), names=free.names, max_iter=min(JOINT_RESTART, iterations - done), jacobian=jacobian
        )
        if not bool(torch.isfinite(res.x).all()):
            raise EstimationError("the joint refinement of geometry and network diverged")
        free.assign(res.x)
        done += max(res.iterations, 1)
        history += res.cost_history if not history else res.cost_history[1:]
        v = score(history)
        trail.append({"iterations": done, "validation_rmse_mm": v * 1e3 if judged else None})
        if v < best[0]:
            best = (v, done, free.vector())
        if res.iterations == 0 or len(res.cost_history) < 2:
            break
    free.assign(best[2])
    res.iterations, res.cost_history = done, history
    return res, {"iterations_run": done, "kept_after_iterations": best[1], "trail": trail}
