"""The effects a calibration could lack, for one robot and one data set.

Every named effect family of :mod:`torchcal.effects` that the data could reveal becomes a
candidate: ``compliance`` per joint whose gravity torque varies over the poses (with the masses of
the robot description; without them in lumped form, :class:`~torchcal.effects.LumpedCompliance`, in the
directions the poses identify beyond the geometry), ``backlash`` per joint whose loaded flank changes (the sign of
the gravity torque for static poses, the direction of motion along a trajectory),
``cyclic`` per revolute joint (harmonics 1 and 2), ``transmission`` (degree 1: a scale error of the
reading) per prismatic joint, whose reading [m] has no turn for harmonics to repeat over, ``coupling`` of each
joint to every other joint that moves (``dq_j = c q_k``, all ``dof (dof - 1)`` ordered pairs), ``drift`` of the
instrument pose with the acquisition time ``t``, ``drift`` of the arm's scale with ``temperature``, and the
instrument's own errors (:mod:`torchcal.effects.instrument`): ``instrument:azimuth:H`` and ``instrument:elevation:H``
(the encoders' harmonic of order H, 1 to 8), ``instrument:range`` (a range offset), ``instrument:tilt`` (the trunnion
axis's and the beam's tilt) and ``instrument:beam`` (the beam's offset), offered where the data can tell them: several
stations, or one whose points span 90 degrees or more in azimuth (over the few tens of degrees a tracker a few metres
off sees the arm span, the instrument pose and the geometry take up a low harmonic: docs/closed-loop.md).
A range scale is never offered: it moves every point by ``s`` times its vector from the tracker, which is the arm's
every length scaled by ``1 + s`` and each station's position with it, so the geometry takes it up exactly whatever
the stations (``instrument:scale`` is listed as held at zero, with that reason; a length the data know, a scale bar,
would tell it).

All stations of a file are one instrument (a station column records where the one tracker stood): the file formats
have no column that names the instrument, and one tracker re-stationed is how a cell is measured; its errors are then
fitted once over every station, which is what makes them identifiable (one station alone seldom tells them).
A prismatic joint's compliance and backlash act along its axis [m], driven by the weight it carries along it.

Couplings are tried between every pair of joints, on every robot: a cable or belt routed through a joint, a wrist
differential the controller compensates with the wrong ratio, join joints whether or not the description declares a
readings map, and which pairs a mechanism joins is not written anywhere a calibration can read. Scoring all pairs
costs one Jacobian column each (the validation refits only the significant ones); their number would take power
from every other test under a plain Bonferroni (30 pairs for a 6R arm against its 20 other candidates), so the
pairs together count as one member of the Bonferroni family and share its level
(:func:`bonferroni_factors`). A pair the data cannot tell from the geometry (a coupling into a joint whose ratio the
readings map calibrates) is marked not identifiable by the score test.

A candidate is left out, with the reason recorded, where it cannot matter: a joint whose
motion does not move the probe (less than 0.1 mm per radian, or per metre), a regressor that is constant
over the data (then the effect is a joint offset or an instrument pose the geometry already
has; a gravity torque of round-off size has no loaded flank either), a variable the file does not have.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal.effects import (
    Backlash,
    Compliance,
    Context,
    Coupling,
    Cyclic,
    Drift,
    LumpedCompliance,
    TorqueCompliance,
    TrackerError,
    Transmission,
)
from torchcal.effects.base import Effect
from torchcal.effects.joint import geometric_span, lumped_basis

Tensor = torch.Tensor

#: a joint that moves the probe by less than this (RMS over the poses, m/rad) cannot show an effect
MIN_LEVER = 1e-4
#: drift variables the data may carry, the effect form each one drives, and its unit
DRIFT_FORMS = {"t": ("instrument", "s"), "temperature": ("scale", "degC")}
#: the instrument's own error terms offered (effects.instrument): the azimuth and elevation encoders' harmonics (one
#: candidate per order in :data:`INSTRUMENT_HARMONICS`), the range's offset, the axes' tilt, the beam's offset
INSTRUMENT_TERMS = ("azimuth", "elevation", "range", "tilt", "beam")
#: the encoder harmonics' orders tried; an order's candidate is the sine and cosine of that order alone
INSTRUMENT_HARMONICS = tuple(range(1, 9))
#: why a range scale is not a candidate (module docstring)
SCALE_HELD = (
    "held at zero: a range scale moves every point by s times its vector from the tracker, which is every length of "
    "the arm scaled by 1 + s and each station's position with it; the geometry takes it up exactly (a known length "
    "in the data, a scale bar, would tell it)"
)
#: the azimuth span [rad] of one station's points from which its instrument errors are offered (module docstring)
MIN_AZIMUTH_SPAN = math.pi / 2


@dataclass(frozen=True)
class Candidate:
    """One effect the model could be missing.

    Attributes:
        kind: effect kind (as report.json names it): compliance, backlash, cyclic, transmission, coupling, drift or
            instrument.
        joint: 1-based joint, or None for drift.
        variable: drift variable (``t`` or ``temperature``), an instrument term (``azimuth``, ``elevation``,
            ``range``), else None.
        reference: drift reference value (the variable at the first training sample).
        basis: a lumped compliance's identifiable directions ``(4 dof, r)`` on the training poses
            (:func:`~torchcal.effects.joint.lumped_basis`); None: the mass-based compliance.
        form: a compliance's load form: ``"torque"`` (driven by the measured torques, :class:`TorqueCompliance`),
            ``"load"`` (the lumped form plus the payload's own torque: rows at several payloads), or None.
    """

    kind: str
    joint: int | None = None
    variable: str | None = None
    reference: float = 0.0
    source: int | None = None  # coupling: the 1-based joint whose reading drives joint ``joint``'s error
    basis: Tensor | None = field(default=None, compare=False, repr=False)
    form: str | None = None
    order: int | None = None  # an instrument encoder harmonic's order

    @property
    def name(self) -> str:
        """Short name as the simulator spells it: ``compliance:2``, ``drift:t``, ``coupling:3<-2``; an encoder
        harmonic ``instrument:azimuth:3``."""
        if self.kind == "coupling":
            return f"coupling:{self.joint}<-{self.source}"
        if self.order is not None:
            return f"{self.kind}:{self.variable}:{self.order}"
        return f"{self.kind}:{self.joint if self.joint is not None else self.variable}"

    @property
    def n_params(self) -> int:
        return len(torch.nn.utils.parameters_to_vector(self.make().parameters()))

    def make(self) -> Effect:
        """A fresh effect of this form with zero parameters."""
        if self.kind == "compliance" and self.form == "torque":
            return TorqueCompliance(self.joint)
        if self.kind == "compliance":
            if self.basis is None:
                return Compliance(self.joint)
            return LumpedCompliance(self.joint, self.basis, load=self.form == "load")
        if self.kind == "backlash":
            return Backlash(self.joint, source="auto")
        if self.kind == "cyclic":
            return Cyclic(self.joint, harmonics=(1, 2))

        if self.kind == "transmission":
            return Transmission(self.joint, degree=1)
        if self.kind == "coupling":
            return Coupling(self.joint, self.source)
        if self.kind == "drift":
            return Drift(self.variable, DRIFT_FORMS[self.variable][0], reference=self.reference)
        if self.kind == "instrument":
            if self.variable in ("azimuth", "elevation"):
                return TrackerError(self.variable, (self.order,) if self.order is not None else (1, 2))
            if self.variable in ("range", "scale"):  # "scale": the true form of a range scale (never offered)
                return TrackerError("range", scale=self.variable == "scale")
            return TrackerError(self.variable)
        raise ValueError(f"unknown candidate kind {self.kind!r}")

    def regressor(self, robot, ctx: Context) -> tuple[Tensor, str]:
        """The variable the effect follows, one value per pose ``(N,)``, and its axis label (for plots)."""
        eff = self.make()
        if self.kind == "compliance" and self.form == "torque":
            return ctx.tau[:, self.joint - 1], f"measured torque at joint {self.joint} [N m]"
        if self.kind == "compliance" and self.basis is not None:
            return eff.regressor(robot, ctx)[:, 0], f"first lumped gravity mode at joint {self.joint} [rad/rad]"
        if self.kind == "compliance":
            return eff.regressor(robot, ctx), f"gravity torque at joint {self.joint} [N m]"
        if self.kind == "backlash":
            what = "motion direction" if ctx.direction is not None else "sign of the gravity torque"
            return eff.regressor(robot, ctx), f"loaded flank of joint {self.joint} ({what})"
        if self.kind == "cyclic":
            return ctx.q[:, self.joint - 1], f"q{self.joint} [rad]"

        if self.kind == "transmission":
            return ctx.q[:, self.joint - 1], f"q{self.joint} [m]"
        if self.kind == "coupling":
            return ctx.q[:, self.source - 1], f"q{self.source} [rad] (error of joint {self.joint})"
        if self.kind == "instrument":
            return _spherical(robot, ctx, self.variable)
        return eff.regressor(robot, ctx), f"{self.variable} - {self.reference:g} [{DRIFT_FORMS[self.variable][1]}]"

    def to_dict(self) -> dict:
        out = {"name": self.name, "kind": self.kind, "joint": self.joint}
        if self.source is not None:
            out["source"] = self.source
        if self.basis is not None:
            out["form"] = "lumped (no link masses)" + (" + payload torque" if self.form == "load" else "")
            out["modes"] = int(self.basis.shape[1])
        if self.form == "torque":
            out["form"] = "measured torques"
        if self.order is not None:
            out["harmonic"] = self.order
        if self.variable is not None:
            out["variable"] = self.variable
            out["form"] = DRIFT_FORMS[self.variable][0] if self.kind == "drift" else self.make().label()
        return out


def _spherical(robot, ctx: Context, term: str) -> tuple[Tensor, str]:
    """The nominal measured points' azimuth or elevation [rad] or range [m] in the instrument frame ``(N,)`` (the
    variable a term follows: a tilt the elevation, a beam offset the azimuth), and its label."""
    from torchcal.effects.model import MeasurementModel

    with torch.no_grad():
        p = MeasurementModel(robot)(ctx)
    if term in ("range", "scale"):
        return p.norm(dim=-1), "range from the instrument [m]"
    if term in ("elevation", "tilt"):
        return torch.atan2(p[:, 2], p[:, :2].norm(dim=-1)), "elevation in the instrument frame [rad]"
    return torch.atan2(p[:, 1], p[:, 0]), "azimuth in the instrument frame [rad]"


def _instrument_untold(robot, ctx: Context) -> str | None:
    """Why the data cannot tell the instrument's own errors from its pose and the geometry (None: they can): one
    station whose points span less than :data:`MIN_AZIMUTH_SPAN` in azimuth. A low encoder harmonic over a narrow span
    is a turn and a stretch the instrument pose and the arm's lengths take up, a tilt a turn, a beam offset a shift; a
    second placement of the same instrument, or a wide span, sets them apart."""
    if len(robot.stations) > 1:
        return None
    az, _ = _spherical(robot, ctx, "azimuth")
    a = torch.sort(torch.remainder(az, 2 * math.pi)).values
    gaps = torch.cat([a[1:] - a[:-1], (a[:1] + 2 * math.pi - a[-1:])]) if len(a) else a.new_ones(1) * 2 * math.pi
    span = 2 * math.pi - float(gaps.max())
    if span >= MIN_AZIMUTH_SPAN:
        return None
    return (
        f"one station, whose points span {math.degrees(span):.0f} deg in azimuth "
        f"(< {math.degrees(MIN_AZIMUTH_SPAN):.0f}): the instrument pose and the geometry take up its low encoder "
        "harmonics, its axes' tilt and its beam's offset; several stations or a wider span tell them"
    )


def _instrument(robot, ctx: Context, out: list, skip) -> None:
    """The instrument's own error terms where the data can tell them (:func:`_instrument_untold`); a range scale is
    held (:data:`SCALE_HELD`)."""
    why = _instrument_untold(robot, ctx)
    for term in INSTRUMENT_TERMS:
        if why is not None:
            skip(f"instrument:{term}", why)
        elif term in ("azimuth", "elevation"):
            out.extend(Candidate("instrument", None, term, order=k) for k in INSTRUMENT_HARMONICS)
        else:
            out.append(Candidate("instrument", None, term))
    skip("instrument:scale", SCALE_HELD)


def _varies(x: Tensor, rel: float = 1e-9) -> bool:
    return bool(len(x) > 1) and float(x.std()) > rel * (1.0 + float(x.abs().max()))


def joint_levers(robot, q: Tensor) -> Tensor:
    """RMS over the poses of ``|dp/dq_j|`` per joint ``(dof,)`` [m/rad]."""
    from torchcal.effects.kernel import joint_metric

    return joint_metric(robot, q)


def _compliance(robot, ctx: Context, j: int, tau: Tensor | None, span: Tensor | None):
    """Joint ``j``'s compliance candidate, or None with the reason, and the geometry's span (computed once)."""
    if ctx.tau is not None:
        # measured torques: the load the joint holds, whatever carries it (no masses needed)
        if _varies(ctx.tau[:, j - 1]):
            return Candidate("compliance", j, form="torque"), None, span
        return None, f"the measured torque tau{j} does not vary over the poses", span
    if tau is None:
        # no masses: the lumped form, in the directions these poses identify beyond the geometry
        span = geometric_span(robot, ctx.q) if span is None else span
        basis = lumped_basis(robot, ctx.q, j, span=span)
        if basis.shape[1] == 0:
            return None, f"no lumped gravity mode of joint {j} shows beyond the geometry on these poses", span
        load = "load" if ctx.payload is not None and _varies(ctx.payload) else None
        return Candidate("compliance", j, basis=basis, form=load), None, span
    if not _varies(tau[:, j - 1]):
        return None, f"the gravity torque at joint {j} does not vary over the poses", span
    return Candidate("compliance", j), None, span


def _couplings(robot, ctx: Context, j: int, out: list, skip) -> None:
    """The couplings ``dq_j = c q_k`` into joint ``j`` from every other joint ``k`` that moves over the data."""
    for k in range(1, robot.dof + 1):
        if k == j:
            continue  # a joint's error in its own reading is its transmission (cyclic, transmission)
        if not _varies(ctx.q[:, k - 1]):
            skip(f"coupling:{j}<-{k}", f"joint {k} does not move over the data")
        else:
            out.append(Candidate("coupling", j, source=k))


def bonferroni_factors(cands: list) -> list[int]:
    """The factor each candidate's p-value is multiplied by (module docstring: a weighted Bonferroni whose weights
    sum to one, so the family-wise level holds over all candidates).

    Every candidate is one member of the family but those of a group: the couplings together are one member, split
    evenly over their pairs, and so are each encoder's harmonics over their orders: ``M`` for a lone candidate,
    ``M P`` for one of a group of ``P``, with ``M`` the members. Objects without a ``kind`` (open forms) count as
    members.
    """
    keys = [_family(c) for c in cands]
    sizes: dict[str, int] = {}
    for k in keys:
        if k is not None:
            sizes[k] = sizes.get(k, 0) + 1
    members = sum(1 for k in keys if k is None) + len(sizes)
    return [members * (sizes[k] if k is not None else 1) for k in keys]


def _family(c) -> str | None:
    """The group a candidate shares one Bonferroni member with (:func:`bonferroni_factors`), None: its own."""
    if getattr(c, "kind", None) == "coupling":
        return "coupling"
    if getattr(c, "kind", None) == "instrument" and getattr(c, "order", None) is not None:
        return f"instrument:{c.variable}"
    return None


def candidates(robot, ctx: Context) -> tuple[list[Candidate], list[dict]]:
    """The candidate effects for ``robot`` at the samples of ``ctx`` (module docstring).

    Returns:
        The candidates, and the ones left out as ``{"name", "reason"}`` dicts.
    """
    out: list[Candidate] = []
    skipped: list[dict] = []

    def skip(name, reason):
        skipped.append({"name": name, "reason": reason})

    levers = joint_levers(robot, ctx.q)
    tau = robot.gravity_torques(ctx.q).detach() if robot.has_masses else None
    span = None  # the geometry's probe columns, for the lumped compliances of a robot without masses
    for j in range(1, robot.dof + 1):
        prismatic = robot.joint_types[j - 1] == "prismatic"
        shape = "transmission" if prismatic else "cyclic"  # the reading's own error function
        if float(levers[j - 1]) < MIN_LEVER:
            per = "m" if prismatic else "rad"
            for kind in ("compliance", "backlash", shape):
                skip(
                    f"{kind}:{j}",
                    f"joint {j} moves the probe by {float(levers[j - 1]) * 1e3:.2g} mm/{per} (< {MIN_LEVER * 1e3:g})",
                )
            continue
        cand, reason, span = _compliance(robot, ctx, j, tau, span)
        if cand is not None:
            out.append(cand)
        else:
            skip(f"compliance:{j}", reason)
        if ctx.direction is None and tau is None:
            skip(f"backlash:{j}", "static poses and no link masses: the loaded flank is unknown")
        elif ctx.direction is None and not _varies(tau[:, j - 1]):
            # a wrist joint whose link masses sit on its axis has a torque of round-off size: its sign (the flank) is
            # noise, and a 'backlash' fitted to it is an artefact of the arithmetic
            skip(f"backlash:{j}", f"the gravity torque at joint {j} is zero up to round-off: no loaded flank")
        else:
            flank = Backlash(j, source="auto").regressor(robot, ctx)
            if bool((flank == flank[0]).all()):
                skip(f"backlash:{j}", f"joint {j} rests on the same flank in every pose (a joint offset)")
            else:
                out.append(Candidate("backlash", j))
        if not _varies(ctx.q[:, j - 1]):
            skip(f"{shape}:{j}", f"joint {j} does not move over the data")
        else:
            out.append(Candidate(shape, j))
        _couplings(robot, ctx, j, out, skip)
    _instrument(robot, ctx, out, skip)
    for var in DRIFT_FORMS:
        v = ctx.t if var == "t" else ctx.temperature
        if v is None:
            skip(f"drift:{var}", f"the data have no '{var}' column")
        elif not _varies(v):
            skip(f"drift:{var}", f"'{var}' does not vary over the data")
        else:
            out.append(Candidate("drift", None, var, float(v[0])))
    return out, skipped
