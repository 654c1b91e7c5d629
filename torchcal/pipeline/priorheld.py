"""What an update from a prior cannot see move because the prior run held it.

A prior run holds the elements its rows could not determine (a short trajectory holds theta2..theta5 and most of the
geometry: ``nearly dependent ... no better than its prior``), and :func:`~torchcal.pipeline.prior.prior_from_run`
keeps them held in the update: its fit has no column for them, so a move of one (joint 2's encoder re-mounted) is
spread over the free elements and :func:`~torchcal.estimate.identifiability.detectability`, which looks at the fit's
own columns, never names it. :func:`held_untold` names each held element whose move the free ones would take up, and
where it would go, so that "nothing moved" is never said of what the update could not have seen.

An element the prior run held because no poses tell it from the free ones (``d1`` against the instrument's height,
the last joint's against the lever arm: structurally dependent) is harmless, as its move is the free ones' move
everywhere; it is told from the others by the structural analysis over poses spread in the joint limits.
"""

from __future__ import annotations

import copy
import dataclasses

import torch

from torchcal.effects import Context
from torchcal.estimate.fit import GEOMETRIC_GROUPS, prior_scales, selection
from torchcal.estimate.identifiability import analyse
from torchcal.estimate.problem import FreeParameters, jacobian_of, residual_function, whitening
from torchcal.pipeline.options import PLAUSIBLE_ANGLE, PLAUSIBLE_LENGTH
from torchcal.pipeline.prior import FLOOR

Tensor = torch.Tensor
#: spread poses of the structural test (uniform in the joint limits, a fixed seed: the answer must not vary by run)
SPREAD_POSES, SPREAD_SEED = 60, 0


def _jacobian(model, names: list[str], m, opts, trajectory: bool) -> tuple[Tensor, list[str]]:
    """The whitened position rows' Jacobian of ``model`` at ``m`` with respect to the geometric elements ``names``
    (their masks opened on a copy), and the column names."""
    model = copy.deepcopy(model)
    groups = model.robot.groups()
    info = {i.name: i for i in model.robot.parameter_info()}
    with torch.no_grad():
        for g in GEOMETRIC_GROUPS:
            if g in groups:
                groups[g].mask.zero_()
        for n in names:
            groups[info[n].group].mask[info[n].index] = True
    sel, labels = selection(model, GEOMETRIC_GROUPS)
    sel = {k: v for k, v in sel.items() if k.split(".")[1] in GEOMETRIC_GROUPS}
    free = FreeParameters(model, sel, {k: labels[k] for k in sel})
    ctx = Context.from_measurements(m, trajectory=trajectory)
    W = whitening(model, ctx, m.sigma, opts.sigma_tracker, opts.sigma_joint)
    p = m.p if m.p is not None else torch.zeros(m.n, 3, dtype=m.q.dtype, device=m.q.device)
    return jacobian_of(residual_function(model, free, ctx, p, W))(free.vector()), list(free.names)


def _spread(m, limits: Tensor):
    """``SPREAD_POSES`` poses uniform in the joint ``limits``, each with ``m``'s first row's station and probe."""
    g = torch.Generator().manual_seed(SPREAD_SEED)
    u = torch.rand(SPREAD_POSES, limits.shape[0], generator=g, dtype=torch.float64, device="cpu").to(limits)
    rows = m.subset(torch.zeros(SPREAD_POSES, dtype=torch.long, device=m.q.device))
    return dataclasses.replace(rows, q=limits[:, 0] + u * (limits[:, 1] - limits[:, 0]), t=None)


def _structural(run, free: list[str], held: list[str]) -> dict[str, list[str]]:
    """The held elements no poses tell from the free ones (the structural test over poses spread in the joint
    limits), each with the free elements its move is (``depends_on``)."""
    opts = run.options.fit
    J, cols = _jacobian(run.model, free + held, _spread(run.train, run.model.robot.limits), opts, False)
    ida = analyse(J, cols, [cols.index(n) for n in free] + [cols.index(n) for n in held], tol=opts.rank_tol)
    return {f["name"]: list(f.get("depends_on") or []) for f in ida.fixed if f["independence"] <= opts.rank_tol}


def held_alike(run, free_names: list[str]) -> dict[str, list[str]]:
    """Per free element, the elements the prior run held that no poses tell from it (``theta1`` and the instrument's
    ``rz``: a turn of joint 1's zero is a turn of the base): where it moved, any of them may have."""
    prior = run.prior
    group = {i.name: i.group for i in run.model.robot.parameter_info()}
    free = [n for n in free_names if n in prior.sigma and group.get(n) in GEOMETRIC_GROUPS]
    if not prior.held or not free:
        return {}
    out: dict[str, list[str]] = {}
    for name, deps in _structural(run, free, list(prior.held)).items():
        for d in deps:
            out.setdefault(d, []).append(name)
    return out


def held_untold(run, free_names: list[str], k: float) -> list[dict]:
    """The elements the prior run held (:attr:`Prior.held`) whose move an update from it cannot see: each with the
    free elements a move of ``k`` a-priori sigmas of a calibration from scratch goes to (``absorbed_by``, at least
    one of their prior sigmas each, largest first) and ``misfit``, the whitened residual norm that move leaves in
    the update's rows (what the global test may notice without naming anything). Position rows only."""
    prior, opts = run.prior, run.options.fit
    held = list(prior.held)
    group = {i.name: i.group for i in run.model.robot.parameter_info()}
    # a 6-D probe's frame rotation (tool_rotation) turns no position: the position rows' columns are these groups'
    free = [n for n in free_names if n in prior.sigma and group.get(n) in GEOMETRIC_GROUPS]
    if not held or not free:
        return []
    structural = set(_structural(run, free, held))
    held = [n for n in held if n not in structural]
    if not held:
        return []
    J, cols = _jacobian(run.model, free + held, run.train, opts, run.trajectory)
    fi = torch.tensor([cols.index(n) for n in free], device=J.device)
    Jf = J[:, fi]
    fit_sigma = prior_scales(run.model, opts)
    s = torch.tensor([fit_sigma.get(n, float("inf")) for n in free], dtype=J.dtype, device=J.device)
    N = Jf.T @ Jf + torch.diag(torch.where(torch.isfinite(s), s.clamp(min=1e-300) ** -2, torch.zeros_like(s)))
    test = torch.tensor([prior.sigma[n] for n in free], dtype=J.dtype, device=J.device)
    units = {i.name: i.unit for i in run.model.robot.parameter_info()}
    out = []
    for n in held:
        base = opts.prior_length if units[n] == "m" else opts.prior_angle
        if base is not None:  # a move of the size a change has, not a tolerance's (torchcal.pipeline.prior.release)
            base = max(base, PLAUSIBLE_LENGTH if units[n] == "m" else PLAUSIBLE_ANGLE)
        size = k * float(base if base is not None else FLOOR[units[n]])
        jh = J[:, cols.index(n)] * size
        dx = torch.linalg.solve(N, Jf.T @ jh)  # the free elements' change that takes up the move (linearised)
        ratio = dx.abs() / test
        order = torch.argsort(ratio, descending=True).tolist()[:4]
        absorbed = [free[i] for i in order if float(ratio[i]) >= 1.0]
        misfit = float((jh - Jf @ dx).norm())
        out.append({"name": n, "share": 0.0, "detectable_from": None, "absorbed_by": absorbed, "rows_needed": None})
        out[-1].update({"held": True, "move": size, "misfit": misfit})
    return out
