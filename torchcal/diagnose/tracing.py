"""Open-ended tracing for the closed loop: localise the residual, identify its form, make it a candidate.

The fixed menu of :mod:`torchcal.diagnose.candidates` only finds the forms it lists. Each round of
:func:`torchcal.diagnose.loop.close_loop` therefore also localises the training residual of the current
fit (:func:`~torchcal.diagnose.localise.localise`: one penalised smooth per variable, Bonferroni over the
variables) and, at the significant variables, strongest first, chooses the form by BIC
(:func:`~torchcal.diagnose.forms.identify_form`). A form that maps to an effect class becomes an
:class:`OpenCandidate`: it behaves like a menu :class:`~torchcal.diagnose.candidates.Candidate` (same
``kind:joint`` / ``drift:variable`` name, so it replaces the menu's fixed form at the same place) and
competes in the same validation.

When the loop ends with the global test failing, :func:`unexplained_entries` says what is left and where:
the significant variables of the final model's training residual with their share of the residual
variance, the localisation evidence, the form the BIC chose there and why it did not become an effect.
"""

from __future__ import annotations

import copy
import math
import operator
from dataclasses import dataclass

import torch

from torchcal.diagnose.forms import FormChoice, identify_form
from torchcal.diagnose.localise import Localisation, Workspace, localise, workspace
from torchcal.effects import Context, MeasurementModel
from torchcal.effects.base import Effect

Tensor = torch.Tensor

#: significant variables examined for an open candidate per round (strongest first)
MAX_VARIABLES = 3


def _forwarded(path: str, doc: str) -> property:
    """A read-only property with the value at the dotted ``path`` from the instance (``"choice.kind"``)."""
    return property(operator.attrgetter(path), doc=doc)


@dataclass(frozen=True, eq=False)
class OpenCandidate:
    """An effect whose form was chosen at a localised variable (module docstring).

    Attributes:
        choice: the form chosen by BIC at the variable, with its table.
        localisation: the evidence that the residual depends on the variable.
        effect: the effect carrying the form, initialised at the form's estimate (copied by :meth:`make`).
    """

    choice: FormChoice
    localisation: Localisation
    effect: Effect

    kind = _forwarded("choice.kind", "The effect kind the form maps to (``cyclic``, ``drift``, ...).")
    joint = _forwarded("choice.variable.joint", "1-based joint of the localised variable, None for Cartesian ones.")

    @property
    def variable(self) -> str | None:
        """The drift variable (``t``, ``temperature``), as a menu candidate spells it; None for joint effects."""
        return self.choice.variable.name if self.choice.variable.joint is None else None

    @property
    def name(self) -> str:
        return f"{self.kind}:{self.joint if self.joint is not None else self.variable}"

    @property
    def n_params(self) -> int:
        return sum(p.numel() for p in self.effect.parameters())

    def make(self) -> Effect:
        return copy.deepcopy(self.effect)

    def regressor(self, robot, ctx: Context) -> tuple[Tensor, str]:
        """The localised variable at ``ctx``'s samples ``(N,)`` and its axis label (for plots)."""
        v = self.choice.variable
        if v.name.startswith("q"):
            return ctx.q[:, v.joint - 1], v.label
        if v.name.startswith("tau"):
            return robot.gravity_torques(ctx.q).detach()[:, v.joint - 1], v.label
        if v.name.startswith("flank"):
            return self.effect.regressor(robot, ctx), v.label
        return getattr(ctx, v.name), v.label

    def form_params(self) -> dict:
        """What ``params`` of the report carry besides the fitted values: the form and its order."""
        out = {"form": self.choice.form, "order": self.choice.order, "variable": self.choice.variable.name}
        if self.choice.best.tau is not None:
            out["tau_form_fit"] = {"value": self.choice.best.tau, "std": self.choice.best.tau_sigma}
        return out

    def to_dict(self) -> dict:
        out = {
            "name": self.name,
            "kind": self.kind,
            "joint": self.joint,
            "source": "localisation",
            **self.form_params(),
        }
        if self.variable is not None:
            out["variable"] = self.variable
        return out


@dataclass
class LocalisationScore:
    """The evidence of an open candidate in the shape of a :class:`~torchcal.diagnose.score.Score`."""

    localisation: Localisation
    choice: FormChoice

    statistic = _forwarded("localisation.statistic", "The localisation's test statistic (scaled chi-square).")
    k = _forwarded("localisation.edf", "Its degrees of freedom: the smooth's effective degrees of freedom.")
    log10_p = _forwarded("localisation.log10_p", "log10 of its p-value, for ranking where p underflows.")
    p_bonferroni = _forwarded("localisation.p_bonferroni", "Its p-value, Bonferroni over the variables.")

    def significant(self, alpha: float) -> bool:
        return self.localisation.significant(alpha)

    def to_dict(self) -> dict:
        loc = self.localisation.to_dict()
        return {
            "test": "localisation, then form selection by BIC",
            "p_bonferroni": loc["p_bonferroni"],
            "log10_p": loc["log10_p"],
            "statistic": loc["statistic"],
            "localisation": loc,
            "bic_change": self.choice.best.bic - next(f.bic for f in self.choice.table if f.form == "none"),
            "form": self.choice.to_dict(),
        }


def residual_workspace(model: MeasurementModel, ctx: Context, p: Tensor, fit) -> tuple[Tensor, Workspace]:
    """Training residual ``p - model(ctx)`` ``(N, 3)`` [m] and its :class:`Workspace` for ``fit`` (a
    :class:`~torchcal.estimate.fit.Fit` on the same samples: its whitening and Jacobian)."""
    with torch.no_grad():
        r = p - model(ctx)
    return r, workspace(model, ctx, r, W=fit.whitening, jacobian=fit.result.jacobian)


def localise_fit(model: MeasurementModel, ctx: Context, p: Tensor, fit) -> tuple[list[Localisation], Workspace]:
    """:func:`~torchcal.diagnose.localise.localise` of the training residual of ``fit``, strongest first."""
    r, ws = residual_workspace(model, ctx, p, fit)
    return localise(model, ctx, ws), ws


def open_candidates(
    model: MeasurementModel,
    locs: list[Localisation],
    ws: Workspace,
    alpha: float,
    exclude: set[str],
    max_variables: int = MAX_VARIABLES,
) -> tuple[list[OpenCandidate], list[dict]]:
    """Open candidates at the significant variables of ``locs`` (at most one per effect name).

    Args:
        model: the current model (drift forms are expressed in its tracker frame).
        locs: the localisation of its training residual, strongest first.
        ws: the workspace the localisation used.
        alpha: family-wise level (Bonferroni over the variables).
        exclude: effect names not to propose (already in the model, or tried and rejected).
        max_variables: significant variables examined.

    Returns:
        The candidates, strongest variable first, and per examined variable without a candidate a
        ``{"variable", "form", "reason"}`` record.
    """
    out: list[OpenCandidate] = []
    notes: list[dict] = []
    names = set(exclude)
    for loc in [x for x in locs if x.significant(alpha)][:max_variables]:
        fc = identify_form(ws, loc.variable)
        if fc.form == "none":
            notes.append({"variable": loc.name, "form": "none", "reason": "BIC prefers no effect at this variable"})
            continue
        if fc.kind is None:
            notes.append(
                {"variable": loc.name, "form": fc.form, "reason": f"no effect class for a {fc.form} form in {loc.name}"}
            )
            continue
        if fc.kind == "drift" and loc.name == "temperature":
            # the menu's temperature drift is the arm's scale; an instrument translation along temperature would
            # only compete with the time drift (temperature follows time in a warm-up)
            notes.append({"variable": loc.name, "form": fc.form, "reason": "left to the scale drift"})
            continue
        eff = fc.effect(model)
        if eff is None:
            notes.append({"variable": loc.name, "form": fc.form, "reason": "no effect class for this form"})
            continue
        cand = OpenCandidate(fc, loc, eff)
        if cand.name in names:
            notes.append(
                {"variable": loc.name, "form": fc.form, "reason": f"{cand.name} is already in the model or was tried"}
            )
            continue
        names.add(cand.name)
        out.append(cand)
    return out, notes


def unexplained_entries(
    model: MeasurementModel,
    ctx: Context,
    p: Tensor,
    fit,
    alpha: float,
    reasons: dict[str, str] | None = None,
    *,
    localised: tuple | None = None,
) -> list[dict]:
    """What the final model leaves in the training residual, strongest first (module docstring).

    Args:
        model, ctx, p: the final model, the training samples and their measured positions ``(N, 3)`` [m].
        fit: the last least-squares fit on those samples (its whitening and Jacobian).
        alpha: family-wise level of the localisation.
        reasons: per variable name, why the loop did not turn it into an effect (optional).
        localised: :func:`localise_fit` of this ``fit`` where the caller has it (the closed loop's final search round).

    Returns:
        Per significant variable: ``variable``, ``variables`` (the parts of a product such as ``q3_t``:
        ``["q3", "t"]``), ``label``, ``joint``, ``share`` (of the residual's weighted sum of squares),
        ``p_bonferroni``, ``significant``, ``form`` (the BIC choice at it, with its table), ``reason``,
        ``evidence`` (the localisation) and ``smooth`` (``grid``, ``value``, ``se``: the fitted function,
        [rad] for joint variables, [m] per tracker axis for the others). When no variable is significant
        (the global test fails but the structure is spread thinly or lives where no smooth looks), the
        strongest variable is still returned, with ``significant`` false and a reason that says so: the
        report never ends a failing global test in silence.
    """
    locs, ws = localised if localised is not None else localise_fit(model, ctx, p, fit)
    out = []
    chosen = [loc for loc in locs if loc.significant(alpha)]
    weak = not chosen and bool(locs)
    for loc in chosen or locs[:1]:
        fc = identify_form(ws, loc.variable)
        reason = (reasons or {}).get(loc.name)
        if weak:
            reason = (
                f"the global test fails, but no variable is significant at the family-wise level {alpha} "
                f"(strongest: {loc.name}, Bonferroni p = {loc.p_bonferroni:.2g}): the structure left is not "
                "localised in any one variable tested"
            )
        elif reason is None:
            if fc.form == "none":
                reason = "significant as a smooth, but no parametric form of its family beats no effect by BIC"
            elif fc.kind is None:
                reason = f"no effect class for a {fc.form} form"
            else:
                reason = f"the loop did not confirm a {fc.kind} effect here"
        d = loc.to_dict()
        out.append(
            {
                "variable": loc.name,
                "variables": loc.variable.variables,
                "label": loc.variable.label,
                "joint": loc.variable.joint,
                "share": loc.share,
                "p_bonferroni": loc.p_bonferroni,
                "significant": not weak,
                "form": {k: v for k, v in fc.to_dict().items() if k != "bic_table"}
                | {"bic_table": fc.to_dict()["bic_table"][:5]},
                "reason": reason,
                "evidence": d,
                "smooth": {
                    "grid": loc.grid.tolist(),
                    "value": loc.smooth.tolist(),
                    "se": loc.smooth_se.tolist(),
                    **({} if loc.smooth_se_shape is None else {"se_shape": loc.smooth_se_shape.tolist()}),
                    "unit": "rad" if loc.variable.kind == "joint" else "m",
                },
            }
        )
    return out


def unexplained_after_learned(
    model: MeasurementModel, fit, previous: list[dict], train, trajectory: bool, alpha: float
) -> list[dict]:
    """What stays unexplained after an accepted learned stage: the entries of the final ``model``'s training
    residual (the learned correction in place; whitening and Jacobian of ``fit``, the last least-squares fit),
    keeping the reasons of the loop's ``previous`` entries; each carries ``"after": "learned"``. The pipeline
    puts them into its diagnosis."""
    reasons = {e["variable"]: e["reason"] for e in previous}
    ctx = Context.from_measurements(train, trajectory=trajectory)
    entries = unexplained_entries(model, ctx, train.p, fit, alpha, reasons)
    for e in entries:
        e["after"] = "learned"
    return entries


def effect_form_params(model: MeasurementModel, index: int, cand: OpenCandidate, fitted: dict) -> dict:
    """``params`` of an accepted open effect: the fitted values (``fitted``), the form, its order and, for the
    exponential drift, the fitted time constant with its standard deviation (from ``log_tau``)."""
    out = {**fitted, **cand.form_params()}
    eff = model.effects[index]
    lt = fitted.get("log_tau")
    if getattr(eff, "form", None) == "exponential" and isinstance(lt, dict):
        tau = math.exp(lt["value"])
        out["tau"] = {
            "value": tau,
            "std": None if lt.get("std") is None else tau * lt["std"],
            **({"unit": eff.param_units(model.robot)["tau"]} if hasattr(eff, "param_units") else {}),
        }
    return out


__all__ = [
    "LocalisationScore",
    "OpenCandidate",
    "effect_form_params",
    "localise_fit",
    "open_candidates",
    "unexplained_after_learned",
    "residual_workspace",
    "unexplained_entries",
    "MAX_VARIABLES",
]
