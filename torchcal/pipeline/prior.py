"""A calibrated run as the prior of a new one: a few new poses update what changed.

After a crash, a motor swap, a re-mounted tool, the robot is mostly what an earlier calibration found; a handful of
new poses should move only what changed. :func:`prior_from_run` turns that calibration (its model and the parameter
covariance of its last fit, read by the caller: :func:`torchcal.use.rundir.load_model`, ``load_covariance``)
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
from torchcal.pipeline.options import PLAUSIBLE_ANGLE, PLAUSIBLE_LENGTH
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
    #: the geometric elements the prior run held (free in its parameterisation, absent from its covariance): the
    #: update holds them too, so it cannot name their move (:func:`torchcal.pipeline.priorheld.held_untold`)
    held: tuple[str, ...] = ()
    #: the prior run's report.json ``effects``: the update carries its effects, held as they were fitted
    effects: tuple[dict, ...] = ()

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
    or scaled ``covariance.pt`` (whose update would otherwise end in a bare 'normal matrix singular')."""
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
            before covariances were kept). A run of several stations or probes is matched to the new rows by
            :func:`for_data`.
    """
    if covariance is None:
        raise OptionError(
            f"{source}: the run has no parameter covariance (covariance.pt); a prior needs the sigmas of its "
            "parameters: calibrate it again with this version"
        )
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
    geometric = ("geometry", "instrument", "tool")  # a readings map's ratios are held by design, not by the data
    held = tuple(
        n for n, i in info.items() if n not in sigma and i.group in geometric and bool(groups[i.group].mask[i.index])
    )
    with torch.no_grad():  # what the prior run held stays held: the update frees only what its covariance holds
        for n, i in info.items():
            if n not in sigma:
                groups[i.group].mask[i.index] = False
    if not (variance_factor > 0 and math.isfinite(variance_factor)):
        raise OptionError(f"{source}: the variance factor must be positive and finite, got {variance_factor}")
    rebase(robot)
    units = {n: info[n].unit for n in sigma}
    prior = Prior(model, sigma, corrections, units, source, max(1.0, variance_factor) ** 0.5, held)
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
        else:  # a change is no tolerance: at least the plausible size (a crash moves a zero by more)
            s = opts.prior_length if i.unit == "m" else opts.prior_angle
            s = None if s is None else max(s, PLAUSIBLE_LENGTH if i.unit == "m" else PLAUSIBLE_ANGLE)
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
    #: per moved element, the elements the prior run held that no poses tell from it (any of them may have moved)
    alike: tuple[tuple[str, tuple[str, ...]], ...] = ()

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
            **({"moved_or_held_alike": {n: list(a) for n, a in self.alike}} if self.alike else {}),
            "released": list(self.released),
            "parameters": [dict(r) for r in self.rows],
            # what the rows cannot tell and where its move would go, at the top: "moved" is the rest of the answer
            **({"confounded": self.detect.confounded} if self.detect is not None else {}),
            **({"detectability": self.detect.to_dict()} if self.detect is not None else {}),
        }


def moved_words(moved, alike: dict) -> str:
    """The moved elements in words, each with the held ones no poses tell from it (``alike``); empty: none."""
    told = [n + (f" (or {', '.join(alike[n])}, which no poses tell from it)" if n in alike else "") for n in moved]
    return ", ".join(told)


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


def for_data(prior: Prior, data) -> Prior:
    """``prior`` for the rows of ``data`` (:class:`~torchcal.data.Measurements`): its stations and probes matched by
    label to the prior run's. A matched station (probe) keeps the prior's pose (lever arm) and a-priori sigmas; a new
    one is fitted from scratch (the calibration's own a-priori sigma), its pose started by a rigid fit of its rows
    (its lever arm at the mean of the prior's). A learned correction per station and probe keeps the groups whose
    station and probe are matched. A prior of one placement and one probe with rows of one is returned as it is.

    Raises:
        OptionError: rows with no ``station`` (``probe``) column for a prior run of several: which is theirs is
            unknown.
    """
    robot = prior.model.robot
    stations, probes = _labels(data, "station"), _labels(data, "probe")
    if not robot.stations and not robot.probes and not stations[0] and not probes[0]:
        return prior
    model = copy.deepcopy(prior.model)
    sigma, corrections, units = dict(prior.sigma), dict(prior.corrections), dict(prior.units)
    st_map = _match(prior, robot.stations, stations, "station", sigma=sigma, corrections=corrections, units=units)
    pr_map = _match(prior, robot.probes, probes, "probe", sigma=sigma, corrections=corrections, units=units)
    _rebuild(
        model.robot,
        robot,
        st_map=st_map,
        pr_map=pr_map,
        st_names=stations[0],
        pr_names=probes[0],
        free=set(sigma),
    )
    _regroup(model, st_map, pr_map)
    _place_new(model.robot, data, st_map)
    # the geometry's held elements keep their names; a station's are renamed or new (fitted), so only those stay
    kept = {i.name for i in model.robot.parameter_info()} - set(sigma)
    out = Prior(model, sigma, corrections, units, prior.source, prior.scale, tuple(n for n in prior.held if n in kept))
    model.robot.prior_sigma = out.fit_sigma
    return out


def _labels(data, key: str) -> tuple[tuple[str, ...], str | None]:
    """The rows' names of ``key`` when they name several (else ()), and the one name they give otherwise (or None)."""
    index, names = getattr(data, key), getattr(data, f"{key}_names")
    if index is None:
        return (), None
    used = [names[int(i)] for i in torch.unique(index)]
    return (tuple(names), None) if len(used) > 1 else ((), used[0])


def _element(names: tuple[str, ...], k: int | None, group: str, column: str) -> str:
    return f"{group}[{names[k]}].{column}" if names else f"{group}.{column}"


def _match(prior: Prior, old: tuple[str, ...], target, key: str, *, sigma, corrections, units) -> list[int | None]:
    """For each new station (probe) the prior's index it matches by label (None: new), renaming the a-priori sigmas,
    corrections and units of the matched elements to the new names (and dropping the rest of the group's)."""
    names, single = target
    group, columns = ("instrument", ("tx", "ty", "tz", "rx", "ry", "rz")) if key == "station" else ("tool", "xyz")
    if names:
        mapping = [old.index(n) if n in old else None for n in names]
    elif old:
        if single is None:
            raise OptionError(
                f"{prior.source}: the prior run has {key}s {', '.join(old)}; the rows have no {key} column: name "
                f"each row's {key}"
            )
        mapping = [old.index(single) if single in old else None]
    else:
        mapping = [0 if not names else None]
    renamed = {}
    for j, k in enumerate(mapping):
        for c in columns:
            src = _element(old, k, group, c) if k is not None else None
            if src is not None and src in sigma:
                renamed[_element(names, j, group, c)] = (sigma[src], corrections[src], units[src])
    for n in [n for n in sigma if n.startswith((f"{group}.", f"{group}["))]:
        del sigma[n], corrections[n], units[n]
    for n, (s, c, u) in renamed.items():
        sigma[n], corrections[n], units[n] = s, c, u
    return mapping


def _rebuild(robot: RobotModel, old: RobotModel, *, st_map, pr_map, st_names, pr_names, free: set[str]) -> None:
    """The instrument and tool of ``robot`` for the new stations and probes: matched ones at the prior's values,
    their elements the prior held held still; new ones free (poses at the identity until :func:`_place_new`)."""
    from torchcal.robot.model import Instrument, Tool

    T_old, t_old = old.instrument.matrix().detach(), old.tool.vector().detach()
    eye = torch.eye(4, dtype=T_old.dtype, device=T_old.device)  # a new station's start, until _place_new
    T = [T_old if k is not None and T_old.dim() == 2 else T_old[k] if k is not None else eye for k in st_map]
    mean = t_old if t_old.dim() == 1 else t_old.mean(0)
    t = [t_old if k is not None and t_old.dim() == 1 else t_old[k] if k is not None else mean for k in pr_map]
    robot.instrument = Instrument(torch.stack(T) if st_names else T[0], robot.dtype, robot.device, st_names or None)
    robot.tool = Tool(torch.stack(t) if pr_names else t[0], robot.dtype, robot.device, pr_names or None)
    with torch.no_grad():
        for grp, mapping in ((robot.instrument, st_map), (robot.tool, pr_map)):
            flat = grp.mask.reshape(len(mapping), -1) if grp.mask.dim() == 2 else grp.mask.reshape(1, -1)
            names = list(grp.names)
            for j, k in enumerate(mapping):
                if k is None:
                    continue
                for c in range(flat.shape[1]):
                    flat[j, c] = names[j * flat.shape[1] + c] in free


def _regroup(model: MeasurementModel, st_map, pr_map) -> None:
    """A learned correction per station and probe keeps the groups of matched stations and probes, re-indexed."""
    from torchcal.effects.grouped import GroupedCorrection

    st = {k: j for j, k in enumerate(st_map) if k is not None}
    pr = {k: j for j, k in enumerate(pr_map) if k is not None}
    for i, e in reversed(list(enumerate(model.effects))):
        if not isinstance(e, GroupedCorrection):
            continue
        keep = [g for g, (s, p) in enumerate(e.groups) if s in st and p in pr]
        if not keep:
            del model.effects[i]
            continue
        regions = None if e.regions is None else [e.regions[g] for g in keep]
        groups = [(st[e.groups[g][0]], pr[e.groups[g][1]]) for g in keep]
        model.effects[i] = GroupedCorrection(groups, [e.inner[g] for g in keep], regions)


def _place_new(robot: RobotModel, data, st_map) -> None:
    """Start each new station's pose with a rigid fit of its rows (the prior's geometry and lever arms)."""
    from torchcal.estimate.rigid import rigid_fit

    new = [j for j, k in enumerate(st_map) if k is None]
    if not new:
        return
    with torch.no_grad():
        pb = robot.probe_in_base(data.q, data.probe if robot.probes else None)
        for j in new:
            rows = data.station == j if robot.stations else torch.ones(data.n, dtype=torch.bool, device=data.q.device)
            T = rigid_fit(pb[rows], data.p[rows])
            if robot.stations:
                robot.instrument.nominal[j] = T
            else:
                robot.instrument.nominal.copy_(T)
