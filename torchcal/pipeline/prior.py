"""A calibrated run as the prior of a new one: a few new poses update what changed.

After a crash, a motor swap, a re-mounted tool, the robot is mostly what an earlier calibration found; a handful of
new poses should move only what changed. :func:`prior_from_run` turns that calibration (its model and the parameter
covariance of its last fit, read by the caller: :func:`torchcal.report.rundir.load_model`, ``load_covariance``)
into a :class:`Prior`; :func:`torchcal.pipeline.run.calibrate` with ``prior=`` then runs the kinematic fit from it.

The model (MAP, docs/reference.md, *Calibrating from a prior run*):

* the robot's geometry, instrument pose and lever arm start at the prior run's values, folded into the nominal
  (:func:`rebase`), so that every correction the new fit makes is a change from the prior, and the fit's priors
  (zero-mean pseudo-observations ``x_j / sigma_j``, :func:`torchcal.estimate.fit.solve`) are centred on it;
* ``sigma_j`` is the prior run's posterior standard deviation of the element, times :data:`INFLATION`, and never
  below a floor (:data:`FLOOR`: 10 um, 10 urad): a calibration's own sigmas (microns, microradians) describe the
  robot as it was, not how far it may have moved since, and a prior that tight would forbid the change the new
  poses are there to find. The marginal sigmas are used, not the full covariance: they are at least the
  conditional ones, so the prior is the looser of the two, and most elements sit at the floor anyway;
* the elements the prior run held (not identifiable there, absent from its covariance) stay held at its values, and
  so do a readings map's ratios: a few poses cannot determine what the prior run's many could not;
* the prior run's effects (compliance, a learned correction ...) are kept with their values and held: a few poses
  are not enough to refit them, and a crash moves the geometry, not the gravity model.

A parameter *moved* when its change exceeds :data:`MOVED_SIGMAS` prior sigmas (a chi-square test of one degree
of freedom per parameter at ``|change / sigma| > 3``, about 0.3 % false alarms each): :class:`PriorUpdate`. A
Gaussian prior pulls a real change back by the square of its size and spreads it over the correlated parameters
(theta2 against theta3, theta4 on a UR arm's parallel axes), so a prior that fails its test is *released*
(:func:`release`: fitted with the a-priori sigma of a calibration from scratch), largest first, one at a time, and
the fit repeated, as data snooping tests the worst observation and takes it out (at most :data:`MAX_RELEASED`).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch

from torchcal.effects import MeasurementModel
from torchcal.errors import OptionError
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.estimate.identifiability import Detectability
from torchcal.robot import transforms as tf
from torchcal.robot.model import DHGeometry, RobotModel

Tensor = torch.Tensor

#: the smallest a-priori sigma of an element, by unit: 10 um for lengths, 10 urad for angles (a guard against a
#: posterior sigma of numerical size; the prior run's own sigmas, scaled by its misfit, set the rest)
FLOOR = {"m": 1e-5, "rad": 1e-5}
#: the prior run's posterior sigmas are widened by this factor (its sigmas hold for the robot as it was measured)
INFLATION = 3.0
#: a parameter moved where its change exceeds this many prior sigmas
MOVED_SIGMAS = 3.0
#: the most parameters one update releases from their prior (a few poses determine a few changes)
MAX_RELEASED = 6
#: the fewest rows a calibration from a prior takes (three of them fitted at the default held-out share)
MIN_PRIOR_POSES = 5


@dataclass(frozen=True)
class Prior:
    """A prior run, ready to start a calibration: its model with its corrections folded into the nominal, the
    a-priori sigma of each element the update may change, and the prior run's corrections (for the report)."""

    model: MeasurementModel  # rebased: every correction zero, the prior run's values in the nominal
    sigma: dict[str, float]  # element name -> a-priori sigma [m or rad] of its change
    corrections: dict[str, float]  # element name -> the prior run's correction [m or rad] (about the description)
    units: dict[str, str]
    source: str = ""
    scale: float = 1.0  # the prior run's a-posteriori s0 (at least 1): how far its model misses its rows, in sigma

    @property
    def fit_sigma(self) -> dict[str, float]:
        """The sigmas the fit weighs the prior with: ``sigma / s0``. The new rows are weighted by their stated
        noise, which the prior run's model misses by ``s0``; the prior's covariance (``s0^2 N^-1``) already holds
        it, so dividing it out gives the prior the weight it has against rows as good as the model fits them:
        the MAP of rows weighted ``1 / (s0 sigma)^2`` with this prior, the same minimum."""
        return {n: s / self.scale for n, s in self.sigma.items()}


def rebase(robot: RobotModel) -> None:
    """Fold the robot's corrections into its nominal values (geometry, instrument pose, lever arm, probe rotation)
    and zero them: the same robot, whose corrections now start from here. A readings map is left as it is."""
    with torch.no_grad():
        g = robot.geometry
        if isinstance(g, DHGeometry):
            g.nominal.add_(g.delta)
        else:  # URDF origins: nominal @ exp(delta) for every joint's origin, the tip's unchanged
            g.nominal[:-1] = g.nominal[:-1] @ tf.se3_from_vector(g.delta)
        g.delta.zero_()
        robot.instrument.nominal.copy_(robot.instrument.matrix())
        robot.instrument.delta.zero_()
        robot.tool.nominal.copy_(robot.tool.vector())
        robot.tool.delta.zero_()
        if robot.tool_rotation is not None:
            robot.tool_rotation.nominal.copy_(robot.tool_rotation.matrix())
            robot.tool_rotation.delta.zero_()


#: the largest a-priori standard deviation a prior run's covariance may give a parameter, by unit: beyond a metre or
#: half a turn it knows nothing of it, and the update's normal matrix turns singular instead of saying why
MAX_PRIOR_SIGMA = {"m": 1.0, "rad": math.pi}


def _check_plausible(source: str, sigma: dict[str, float], units: dict[str, str]) -> None:
    """Refuse a prior whose standard deviations are beyond any calibration's (:data:`MAX_PRIOR_SIGMA`): a damaged
    or scaled ``covariance.pt`` (issue 35 item 10: scaled by 1e20, the update failed with 'normal matrix singular')."""
    for name, s in sigma.items():
        limit = MAX_PRIOR_SIGMA.get(units[name])
        if limit is not None and not s <= limit:
            raise OptionError(
                f"{source}: covariance.pt gives {name} a standard deviation of {s:.3g} {units[name]}, beyond any "
                f"calibration's ({limit:.3g} {units[name]}): the file is damaged or was scaled; calibrate the prior "
                "run again"
            )


def prior_from_run(
    model: MeasurementModel,
    covariance: ParameterCovariance | None,
    source: str = "the prior run",
    variance_factor: float = 1.0,
) -> Prior:
    """The :class:`Prior` of a prior run's loaded ``model`` and ``covariance`` (module docstring), with the
    a-posteriori variance factor ``s0^2`` of the fit the covariance is of (report.json ``global_test.statistic``).

    Raises:
        OptionError: the run has no covariance (its last fit's normal matrix was singular, or it was written
            before covariances were kept), or it used several stations or probes (not supported yet).
    """
    if covariance is None:
        raise OptionError(
            f"{source}: the run has no parameter covariance (covariance.pt); a prior needs the sigmas of its "
            "parameters: calibrate it again with this version"
        )
    robot = model.robot
    if robot.stations or robot.probes:
        raise OptionError(f"{source}: a prior run with several stations or probes is not supported yet")
    model = copy.deepcopy(model)
    robot = model.robot
    info = {i.name: i for i in robot.parameter_info()}
    labels = iter(covariance.labels)
    sd = covariance.matrix.diagonal().clamp(min=0).sqrt().tolist()
    sigma, k = {}, 0
    for name, idx in zip(covariance.names, covariance.index):
        for _ in idx:
            label = next(labels)
            i = info.get(label)
            if name.startswith("robot.") and i is not None and i.group != "readings":
                sigma[label] = max(INFLATION * sd[k], FLOOR[i.unit])
            k += 1
    if not sigma:
        raise OptionError(f"{source}: its covariance names none of the robot's parameters")
    _check_plausible(source, sigma, {n: info[n].unit for n in sigma})
    groups = robot.groups()
    corrections = {n: float(groups[info[n].group].delta[info[n].index].detach()) for n in sigma}
    with torch.no_grad():  # what the prior run held stays held: the update frees only what its covariance holds
        for n, i in info.items():
            if n not in sigma:
                groups[i.group].mask[i.index] = False
    if not (variance_factor > 0 and math.isfinite(variance_factor)):
        raise OptionError(f"{source}: the variance factor must be positive and finite, got {variance_factor}")
    rebase(robot)
    prior = Prior(model, sigma, corrections, {n: info[n].unit for n in sigma}, source, max(1.0, variance_factor) ** 0.5)
    robot.prior_sigma = prior.fit_sigma  # read by torchcal.estimate.fit.prior_scales: every fit of this robot is MAP
    return prior


def release(prior: Prior, names: list[str], opts) -> dict[str, float]:
    """The a-priori sigmas of ``prior`` with ``names`` released: a released element gets the a-priori sigma of a
    calibration from scratch (``opts``: :class:`~torchcal.pipeline.options.FitSettings`; the geometry's
    ``prior_length`` / ``prior_angle``, the instrument's ``prior_instrument``, the lever arm's ``prior_lever``),
    or none (inf) where those are off."""
    out = prior.fit_sigma
    info = {i.name: i for i in prior.model.robot.parameter_info()}
    for n in names:
        i = info[n]
        if i.group == "instrument" and opts.prior_instrument is not None:
            s = opts.prior_instrument[0 if i.unit == "m" else 1]
        elif i.group == "tool" and opts.prior_lever is not None:
            s = opts.prior_lever
        else:
            s = opts.prior_length if i.unit == "m" else opts.prior_angle
        out[n] = float("inf") if s is None else float(s) / prior.scale
    return out


@dataclass(frozen=True)
class PriorUpdate:
    """What the new poses changed: per element the prior run's correction, the change, its prior sigma, and
    the elements that moved (``|change| > MOVED_SIGMAS * sigma``)."""

    source: str
    rows: tuple[dict, ...]  # name, unit, prior, change, sigma, ratio
    moved: tuple[str, ...]  # released, then those beyond the threshold, largest first
    released: tuple[str, ...] = ()  # fitted without their prior (:func:`release`)
    s0: float = 1.0  # the prior run's (Prior.scale)
    threshold: float = MOVED_SIGMAS
    #: whether the rows could have told a move of each parameter (None: not analysed)
    detect: Detectability | None = None

    @property
    def worst(self) -> str | None:
        """The element not yet released whose change is the most prior sigmas beyond the threshold (None: none)."""
        rest = [r for r in self.rows if r["name"] not in self.released and r["ratio"] > self.threshold]
        return max(rest, key=lambda r: r["ratio"])["name"] if rest else None

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "moved_threshold_sigma": self.threshold,
            "floor": {"m": FLOOR["m"], "rad": FLOOR["rad"]},
            "inflation": INFLATION,
            "s0": self.s0,
            "moved": list(self.moved),
            "released": list(self.released),
            "parameters": [dict(r) for r in self.rows],
            **({"detectability": self.detect.to_dict()} if self.detect is not None else {}),
        }


def prior_update(prior: Prior, model: MeasurementModel) -> PriorUpdate:
    """The change of every element of ``prior`` in the calibrated ``model`` (whose corrections are the changes:
    the prior's values are its nominal), in units of the element's prior sigma; released are those whose sigma the
    model's robot no longer holds at the prior's (:func:`release`)."""
    info = {i.name: i for i in model.robot.parameter_info()}
    groups = model.robot.groups()
    now = getattr(model.robot, "prior_sigma", None) or {}
    released = tuple(n for n, s in prior.fit_sigma.items() if now.get(n, s) != s)
    rows = []
    for n, s in prior.sigma.items():
        change = float(groups[info[n].group].delta[info[n].index].detach())
        rows.append(
            {
                "name": n,
                "unit": prior.units[n],
                "prior": prior.corrections[n],
                "change": change,
                "sigma": s,
                "ratio": abs(change) / s,
            }
        )
    ranked = sorted(rows, key=lambda r: -r["ratio"])
    moved = tuple(r["name"] for r in ranked if r["name"] in released or r["ratio"] > MOVED_SIGMAS)
    return PriorUpdate(prior.source, tuple(rows), moved, released, prior.scale)
