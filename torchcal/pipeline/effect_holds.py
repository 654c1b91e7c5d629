"""Identifiability over effects and geometry together, after the closed loop: a direction the data cannot tell between
an effect and the geometry is held at the effect's zero.

The closed loop admits an effect where its columns are independent of the current ones (the score test), but the
geometry is analysed once, before any effect, and an effect admitted later can leave a combination with the geometry
that only the joint fit shows (:func:`torchcal.pipeline.loop.effect_trades`: a joint's cosine harmonic over a narrow
range and its offset, a coupling and a ratio of the readings map, an instrument's low harmonic and its pose). Along
such a direction the values are the priors' and the start's, not the data's: the effect would carry a share of a
geometric error, or the reverse, and a prediction away from the training poses would follow that arbitrary split.

The rule of the geometry's own after-fit check is applied to the effects: of each weak combination with a geometric
member, the effect's members are held, here at zero (the effect's nominal value, as the geometry's is its nominal
one): the geometry keeps what both explain, which is what the model without the effect would say, and the effect
keeps what only it explains. As there, a member whose fitted value the data put farther than the 0.999 quantile of
chi-square with one degree of freedom from zero (in its own posterior sigma, which the correlation already inflates)
is kept and named instead: the data reject its zero, so holding it would throw away what they tell (an azimuth
harmonic 1 of 20 urad on three stations trades with the stations' poses at 0.999 yet is fitted many sigma from zero,
and the true form's held-out error is the loop's only with it). The held elements join the run's identifiability
analysis as ``fixed`` entries with their reason (report.json's ``parameters.identifiability``), so the later stages
hold them too. A combination among effects alone is named, not held: neither side is the nominal one.
"""

from __future__ import annotations

import copy
import math

import torch

from torchcal.data import Measurements
from torchcal.effects import MeasurementModel
from torchcal.errors import EstimationError
from torchcal.estimate.fit import GEOMETRIC_GROUPS, Fit, FitOptions, effect_parameter_labels, solve
from torchcal.estimate.identifiability import CHI2_1_999, Identifiability


def _z(fit: Fit | None, name: str) -> float:
    """How many posterior sigmas the fitted value of ``name`` lies from zero (0 where ``fit`` does not estimate it);
    the variance factor counts only where it exceeds one (:func:`~torchcal.estimate.identifiability.weak_after_fit`)."""
    if fit is None or name not in fit.result.names:
        return 0.0
    i = fit.result.names.index(name)
    s0 = fit.result.sigma0_sq if math.isfinite(fit.result.sigma0_sq) and fit.result.sigma0_sq > 1.0 else 1.0
    return abs(float(fit.result.x[i])) / math.sqrt(s0 * float(fit.result.cofactor[i, i]))


def held_analysis(
    ida: Identifiability, trades: list[dict], fit: Fit | None = None
) -> tuple[Identifiability, list[str]]:
    """A copy of the analysis ``ida`` with the effect members of every trade that has a geometric member marked
    held (module docstring), and the names held; a member ``fit`` puts beyond :data:`CHI2_1_999` from zero is kept,
    and its trade lists it under ``kept`` with its distance in sigmas."""
    out = copy.deepcopy(ida)
    held: list[str] = []
    for t in trades:
        if not t["robot"]:
            continue
        for name in t["effects"]:
            if name in held or name in out.names:
                continue
            z = _z(fit, name)
            if z * z > CHI2_1_999:
                t.setdefault("kept", {})[name] = z
                continue
            held.append(name)
            out.names.append(name)
            out.free = torch.cat([out.free, out.free.new_zeros(1)])
            out.independence = torch.cat([out.independence, out.independence.new_zeros(1)])
            out.fixed.append(
                {
                    "name": name,
                    "reason": (
                        f"held at the effect's zero: the data cannot tell it from {', '.join(t['robot'])} (a "
                        f"combination correlated at {t['correlation']:.5f}: {t['direction']} hardly changes the "
                        "fit); the geometry keeps what both explain"
                    ),
                    "depends_on": list(t["robot"]),
                    # the combination's own independence: above the structural tolerance, so that a later analysis
                    # of the geometry alone (a prior update's) does not take it for a geometric dependency
                    "independence": math.sqrt(max(1.0 - t["correlation"], 0.0)),
                    "combination": list(t["members"]),
                }
            )
    return out, held


def _zero(model: MeasurementModel, names: list[str]) -> None:
    """Set the effect parameter elements ``names`` (as :func:`effect_parameter_labels` names them) to zero."""
    _, labels = effect_parameter_labels(model)
    params = dict(model.named_parameters())
    with torch.no_grad():
        for key, elements in labels.items():
            for k, element in enumerate(elements):
                if element in names:
                    params[key].view(-1)[k] = 0.0


def hold_trades(
    model: MeasurementModel,
    train: Measurements,
    ida: Identifiability,
    trades: list[dict],
    opts: FitOptions,
    *,
    trajectory: bool,
    fit: Fit | None = None,
) -> tuple[Fit | None, list[str]]:
    """Hold the effect members of ``trades`` with a geometric member at zero and refit ``model`` on ``train`` with
    the analysis ``ida`` so extended (module docstring).

    Args:
        fit: the fit the trades come from: a member it puts beyond :data:`CHI2_1_999` from zero is kept.

    Returns:
        The new fit (its ``identifiability`` the extended analysis) and the names held; ``(None, [])`` where nothing
        is to be held, or where the refit fails (the model is then as it was).
    """
    ida_held, names = held_analysis(ida, trades, fit)
    if not names:
        return None, []
    before = copy.deepcopy(model.state_dict())
    _zero(model, names)
    try:
        new = solve(
            model,
            train,
            GEOMETRIC_GROUPS,
            opts,
            "effects held",
            trajectory=trajectory,
            effects=True,
            identifiability=ida_held,
        )
    except EstimationError:
        model.load_state_dict(before)
        return None, []
    return new, names
