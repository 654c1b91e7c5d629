"""Checks a run makes before and after its geometric fit: enough held-out poses, poses that can determine a
calibration, and geometric corrections of a plausible size."""

from __future__ import annotations

import dataclasses
import math

import torch

from torchcal import stats as S
from torchcal.data import Measurements
from torchcal.effects import MeasurementModel
from torchcal.errors import EstimationError, MeasurementFileError, OptionError
from torchcal.estimate.fit import Fit, errors, prior_ratios, prior_scales
from torchcal.pipeline.options import PLAUSIBLE_ANGLE, PLAUSIBLE_LENGTH, Options
from torchcal.robot.ranges import NARROW_DEG, NARROW_SHARE, NarrowJoint, narrow_joints  # noqa: F401 (their home before)

Tensor = torch.Tensor

#: fewest held-out poses a run reports an error on
MIN_HOLDOUT = 3
#: the largest geometric correction, in prior standard deviations, a calibration accepts: lengths and angles
#: (docs/prior_ratios.md: measured on legitimate data, simulated and real, and on data of another robot), and readings
#: ratios (unit 1, prior 0.1 %: 50 x is a 5 % transmission error; a track read in mm moves its ratio by 999 x)
MAX_PRIOR_RATIO = {"m": 50.0, "rad": 300.0, "1": 50.0}


def check_holdout(n: int, holdout: float) -> None:
    """Refuse a held-out fraction that leaves fewer than :data:`MIN_HOLDOUT` of ``n`` poses: a held-out RMSE of one
    or two poses is no evidence. (The command line's rule; scripts that refit on nearly everything may hold out
    less through the library.)"""
    n_hold = S.holdout_count(n, holdout)
    if n_hold < MIN_HOLDOUT:
        raise OptionError(
            f"holdout {holdout:g} (--holdout) of {n} poses holds out {n_hold}; at least {MIN_HOLDOUT} are needed for "
            f"a held-out error (holdout >= {MIN_HOLDOUT / n:.3g})"
        )


def check_poses(data: Measurements) -> None:
    """Refuse poses that cannot determine a calibration, naming the file and the cause, before any fitting: all
    rows with the same joint readings, measured positions that are one point or lie on one line, or only one joint
    moving (its circle leaves the other joints' geometry undetermined)."""
    src = data.source or "the measurements"
    q, p = data.q.detach().cpu(), data.p.detach().cpu()
    spread = q.max(dim=0).values - q.min(dim=0).values
    moving = [f"q{k + 1}" for k in range(data.dof) if float(spread[k]) > S.GROUP_TOL]
    if data.n > 1 and not moving:
        raise MeasurementFileError(
            src,
            f"all {data.n} poses have the same joint readings; a calibration needs the robot measured in many "
            "different poses",
        )
    if data.n > 1 and len(moving) == 1 and data.dof > 1:
        raise MeasurementFileError(
            src,
            f"only {moving[0]} moves across the {data.n} poses; a calibration needs poses that move the joints "
            "together (one joint's circle leaves the rest of the geometry undetermined)",
            column=moving[0],
        )
    if data.n > 2:
        centred = p - p.mean(dim=0)
        sv = torch.linalg.svdvals(centred)
        if float(sv[0]) <= 1e-9 * max(1.0, float(p.abs().max())):
            raise MeasurementFileError(src, f"all {data.n} measured positions x, y, z are the same point")
        if float(sv[1]) <= 1e-9 * float(sv[0]):
            raise MeasurementFileError(
                src,
                f"the {data.n} measured positions x, y, z lie on one straight line; the tracker's pose cannot be "
                "fitted to them (were the columns filled in by hand?)",
            )


def check_repeated_rows(data: Measurements) -> None:
    """Refuse rows that repeat another row to the last digit (joints, position, station and probe): a measurement
    does not repeat itself to every digit, a copied row does, and it counts twice in every fit, so each standard
    deviation of the run shrinks as if the rows were new measurements. Names the first copy and its original."""
    key = [data.q, data.p] + [i.to(data.q.dtype).unsqueeze(1) for i in (data.station, data.probe) if i is not None]
    first = S.first_alike(torch.cat(key, dim=1).detach().cpu())
    copies = torch.nonzero(first != torch.arange(len(first))).flatten()
    if not len(copies):
        return
    r, original = int(copies[0]), int(first[copies[0]])

    def where(i: int) -> str:
        return f"line {data.lines[i]}" if data.lines else f"row {i + 1}"

    raise MeasurementFileError(
        data.source or "the measurements",
        f"{len(copies)} row(s) repeat another row to the last digit (joints and position), the first at {where(r)} "
        f"(a copy of {where(original)}); a copied row counts twice and makes every standard deviation too small: "
        "remove the copies",
        line=data.lines[r] if data.lines else None,
    )


def check_corrections(fit: Fit, model: MeasurementModel, opts: Options, data: Measurements) -> None:
    """Stop a run whose geometric corrections are many times their priors (:data:`MAX_PRIOR_RATIO`): the data were
    measured on another robot, in other units, or the description is not the robot's. A readings map's ratios count
    too (unit 1): a ratio that moves by 100 % absorbs a reading in another unit (a track in mm) or of the other
    sign, and the run would then predict in neither."""
    # counted in the plausible size, not in the fit's own prior (a manufacturing tolerance, ten times tighter, which
    # weights the fit but says nothing of how large a correction the data determine can legitimately be)
    scale = dataclasses.replace(opts.fit, prior_length=PLAUSIBLE_LENGTH, prior_angle=PLAUSIBLE_ANGLE)
    ratios = {**prior_ratios(fit, model, scale), **_readings_ratios(fit, model, opts)}
    units = {i.name: i.unit for i in model.robot.parameter_info() if i.group in ("geometry", "readings")}
    worst = sorted(((r / MAX_PRIOR_RATIO[units[n]], r, n) for n, r in ratios.items()), reverse=True)
    if not worst or worst[0][0] <= 1.0:
        _check_one_bad_row(fit, model, data)
        return
    listed = []
    for _, r, n in worst[:3]:
        value = float(fit.result.x[fit.free.names.index(n)])
        shown = {"m": f"{value * 1e3:+.4g} mm", "rad": f"{math.degrees(value):+.4g} deg"}.get(units[n], f"{value:+.4g}")
        listed.append(f"{n} {shown} ({r:.0f} x its prior)")
    cause = (
        "Wrong robot (were the data measured on another model?), wrong units (length_unit, angle_unit: "
        "--length-unit, --angle-unit), or a description that is not this robot's"
    )
    if units[worst[0][2]] == "1":
        cause = (
            "A reading in another unit than the description's (a track in mm where the robot says m: write its "
            "ratio in the readings: block or convert the column), a reading of the other sign (try the sign of "
            "each reading in the readings: block), or a readings map that is not this robot's"
        )
    raise EstimationError(
        f"{data.source or 'the measurements'}: the geometric fit of robot '{model.robot.name}' needs corrections "
        f"many times their a-priori size: {', '.join(listed)} (limits: {MAX_PRIOR_RATIO['m']:g} x for lengths, "
        f"{MAX_PRIOR_RATIO['rad']:g} x for angles, {MAX_PRIOR_RATIO['1']:g} x for readings ratios). {cause}"
        + _standing_out(model, data)
    )


#: a row whose miss after the failed fit is this many times the median row's is named as a likely gross error
STANDS_OUT = 8.0
#: a geometric fit whose variance factor is this many times its global test's threshold, with one row standing out,
#: stops the run naming that row: under the tolerance prior one wrong reading (a gross error the screening, which
#: does not run on several stations, left in) no longer pulls the corrections to many times their plausible size
FAR_OFF = 1e3


#: the worst row is one wrong reading only where it misses by this many times the next worst row: a large effect the
#: geometry lacks (a coupling of 0.2 %, millimetres where its source joint turns most) makes many rows miss alike
#: (5.3 mm, then 4.8 and 4.6 mm on a UR5 campaign of 800 poses), a wrong reading one
ALONE = 2.0


def _check_one_bad_row(fit: Fit, model: MeasurementModel, data: Measurements) -> None:
    test = fit.global_test or {}
    stat, thr = test.get("statistic"), test.get("threshold")
    if stat is None or thr is None or not float(stat) > FAR_OFF * float(thr):
        return
    e = torch.sort(errors(model, data, False).detach().cpu(), descending=True).values
    if len(e) > 1 and not float(e[0]) > ALONE * float(e[1]):
        return  # many rows miss alike: structure the closed loop is there to find, not one wrong reading
    row = _standing_out(model, data)
    if row:
        raise EstimationError(
            f"{data.source or 'the measurements'}: the geometric fit of robot '{model.robot.name}' does not describe "
            f"the data (variance factor {float(stat):.3g}, {float(stat) / float(thr):.0f} x its threshold)" + row
        )


def _standing_out(model: MeasurementModel, data: Measurements) -> str:
    """The row the failed fit misses most, where it stands out from the rest (:data:`STANDS_OUT` x the median):
    one wrong reading pulls the geometry too, and the gross-error screening does not run on several stations."""
    e = errors(model, data, False).detach().cpu()
    if len(e) < 3:
        return ""
    worst, med = int(e.argmax()), float(e.median())
    if not float(e[worst]) > STANDS_OUT * max(med, 1e-12):
        return ""
    where = f"line {data.lines[worst]}" if data.lines else f"row {worst + 1}"
    return (
        f". Or one bad row: {where} misses by {float(e[worst]) * 1e3:.3g} mm, {float(e[worst]) / med:.0f} x the "
        f"median row's {med * 1e3:.3g} mm (a wrong reading there? the gross-error screening does not run on data "
        "of several stations)"
    )


def _readings_ratios(fit: Fit, model: MeasurementModel, opts: Options) -> dict[str, float]:
    """How many prior standard deviations each fitted readings ratio of ``fit`` moved (its prior:
    :func:`~torchcal.estimate.fit.prior_scales`, 0.1 % unless a prior run says otherwise)."""
    scales = prior_scales(model, opts.fit)
    readings = {i.name for i in model.robot.parameter_info() if i.group == "readings"}
    x = fit.result.x
    return {
        n: float(x[i].abs()) / scales[n]
        for i, n in enumerate(fit.free.names)
        if n in readings and scales.get(n, 0.0) > 0.0
    }


def narrow_note(narrow: list[NarrowJoint]) -> str | None:
    """The calibrate-time line naming the narrow joints and what they mean for predictions beyond them."""
    if not narrow:
        return None
    names = "; ".join(n.text() for n in narrow)
    return (
        f"narrow training range: {names}. Geometry and effects that only the motion of "
        + ("this joint" if len(narrow) == 1 else "these joints")
        + " would reveal cannot be told from these poses: predictions where "
        + ("it leaves its" if len(narrow) == 1 else "they leave their")
        + " training range are extrapolations (predict's extrapolation column says how far, sx, sy, sz how sure); "
        "measure poses that move " + ("it" if len(narrow) == 1 else "them") + " to calibrate there"
    )
