"""The instrument's own errors, in its spherical coordinates: encoder harmonics in azimuth and elevation, a range
offset and scale, the tilt of its axes and the beam's offset.

A laser tracker measures a point by two encoder angles and a distance: azimuth ``az = atan2(y, x)``, elevation
``el = atan2(z, sqrt(x^2 + y^2))`` and range ``rho = |p|`` in its own frame. An encoder mounted off its axis, or a
graduation error, reads the angle with a periodic error in that angle; the interferometer or ADM reads the range with
an offset (the reflector's, a dead path) and a scale (the wavelength's compensation for the air). The terms of the
tracker error models of the literature on tracker performance evaluation (ASME B89.4.19) in the tracker's own frame,
to first order (the errors are microradians and micrometres):

* azimuth: ``d_az = sum_k a_k sin(k az) + b_k cos(k az)`` [rad], which moves the point by ``d_az`` times its distance
  from the vertical axis along the azimuth direction;
* elevation: ``d_el = sum_k a_k sin(k el) + b_k cos(k el)`` [rad], by ``d_el rho`` along the elevation direction;
* range: ``d_rho = c_0 + c_1 rho`` (``c_0`` [m], ``c_1`` [m/m]), along the line of sight;
* tilt: ``d_az = t_0 tan(el) + t_1 / cos(el)`` [rad], the trunnion (elevation) axis tilted by ``t_0`` from the
  perpendicular to the standing axis and the beam tilted by ``t_1`` from the perpendicular to the trunnion axis
  (the theodolite's trunnion-axis and collimation errors), which move the point along the azimuth direction by
  ``t_0 z + t_1 rho``; a tilt of the standing axis itself is a turn of the instrument frame, which its pose holds;
* beam: the beam passing ``e_0`` [m] beside the gimbal point along the azimuth direction and ``e_1`` [m] along the
  elevation direction: a displacement of constant size that turns with the head.

They live in the instrument's frame: where the instrument is re-stationed they move with it (a re-stationed run keeps
them), and the constant parts are the instrument pose's (a constant azimuth error is a turn about its vertical axis),
so harmonics start at order 1. A range scale over one station's points is the arm's scale about the instrument, which
the geometry's lengths and the instrument's position take up exactly: the score test finds it not identifiable there.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from torchcal import _dual
from torchcal.effects.base import Acts, Context, Effect
from torchcal.errors import OptionError

Tensor = torch.Tensor

#: the terms: the two encoders' harmonics, the range's offset and scale, the axes' tilt, the beam's offset
TERMS = ("azimuth", "elevation", "range", "tilt", "beam")
#: each term's parameter other than the harmonics' ``a, b``: its name and its units
_PARAMS = {"range": ("c", ["m", "m/m"]), "tilt": ("t", ["rad", "rad"]), "beam": ("e", ["m", "m"])}


class TrackerError(Effect):
    """One term of the instrument's own error model (module docstring), acting on the point in the tracker frame.

    Args:
        term: ``azimuth``, ``elevation`` (encoder harmonics), ``range`` (offset and scale), ``tilt`` (trunnion axis,
            beam) or ``beam`` (offset).
        harmonics: an angle term's orders, distinct positive integers (default 1 and 2).
        a, b: an angle term's sine and cosine amplitudes [rad], one per harmonic.
        c: a range term's ``(offset [m], scale [m/m])``, or ``(offset,)`` without ``scale``.
        scale: whether a range term has a scale (the closed loop's candidate has none: module docstring of
            :mod:`torchcal.diagnose.candidates`).
        t: a tilt term's ``(trunnion axis [rad], beam [rad])``.
        e: a beam term's ``(along azimuth [m], along elevation [m])``.
    """

    kind = "instrument"
    acts_on = Acts.TRACKER
    reads_instrument = True  # the point it acts on is placed by the instrument pose

    def __init__(
        self, term: str, harmonics: Sequence[int] = (1, 2), a=None, b=None, c=None, *, scale=True, t=None, e=None
    ):
        super().__init__(None)
        if term not in TERMS:
            raise OptionError(f"instrument term must be one of {', '.join(TERMS)}, got {term!r}")
        self.term = term
        self.orders: tuple[int, ...] = ()
        self.scale = bool(scale) if term == "range" else False
        if term in _PARAMS:
            name = _PARAMS[term][0]
            n = 2 if term != "range" or self.scale else 1
            setattr(self, name, nn.Parameter(_init({"c": c, "t": t, "e": e}[name], n)))
            return
        orders = tuple(int(k) for k in harmonics)
        if not orders or min(orders) < 1 or len(set(orders)) != len(orders):
            raise OptionError(f"instrument {term} harmonics must be distinct positive integers, got {list(harmonics)}")
        self.orders = orders
        self.register_buffer("harmonics", torch.tensor(orders, dtype=torch.float64))
        self.a = nn.Parameter(_init(a, len(orders)))
        self.b = nn.Parameter(_init(b, len(orders)))

    @property
    def variable(self) -> str:
        """The term, as the closed loop's candidate names it (``instrument:azimuth``)."""
        return self.term

    def angle_error(self, angle: Tensor) -> Tensor:
        """An angle term's error ``(N,)`` [rad] at the angles ``angle`` ``(N,)`` [rad]."""
        arg = angle.unsqueeze(-1) * self.harmonics
        return (_dual.mul(torch.sin(arg), self.a) + _dual.mul(torch.cos(arg), self.b)).sum(-1)

    def forward(self, robot, ctx: Context, p_tracker: Tensor | None = None) -> Tensor:
        """The displacement ``(N, 3)`` [m] of the measured points ``p_tracker`` ``(N, 3)`` [m, tracker frame]."""
        if p_tracker is None:
            raise OptionError("an instrument error acts on the point in the tracker frame (p_tracker)")
        x, y, z = p_tracker.unbind(-1)
        rho_xy = torch.sqrt(x * x + y * y).clamp(min=1e-12)
        rho = torch.sqrt(rho_xy * rho_xy + z * z)
        if self.term == "range":
            d = (self.c[1] * rho + self.c[0]) if self.scale else self.c[0].expand_as(rho)
            return (d / rho).unsqueeze(-1) * p_tracker
        az, el = torch.atan2(y, x), torch.atan2(z, rho_xy)
        e_az = torch.stack([-torch.sin(az), torch.cos(az), torch.zeros_like(az)], dim=-1)
        s, c = torch.sin(el), torch.cos(el)
        e_el = torch.stack([-s * torch.cos(az), -s * torch.sin(az), c], dim=-1)
        if self.term == "tilt":  # d_az rho_xy = t0 tan(el) rho cos(el) + t1 rho cos(el) / cos(el)
            return _dual.mul(e_az, (_dual.mul(z, self.t[0]) + _dual.mul(rho, self.t[1])).unsqueeze(-1))
        if self.term == "beam":
            return _dual.mul(e_az, self.e[0]) + _dual.mul(e_el, self.e[1])
        if self.term == "azimuth":  # along e_az, by the distance from the vertical axis
            return (self.angle_error(az) * rho_xy).unsqueeze(-1) * e_az
        return (self.angle_error(el) * rho).unsqueeze(-1) * e_el

    def param_units(self, robot) -> dict:
        if self.term in _PARAMS:
            name, units = _PARAMS[self.term]
            return {name: units[: len(getattr(self, name))]}
        return {"a": "rad", "b": "rad"}

    def config(self) -> dict:
        out = {"term": self.term, **({"harmonics": list(self.orders)} if self.orders else {})}
        return {**out, "scale": False} if self.term == "range" and not self.scale else out

    def describe(self) -> dict:
        if self.term == "range":
            c = self.c.detach()
            return {"term": "range", "offset_m": float(c[0]), **({"scale": float(c[1])} if self.scale else {})}
        if self.term == "tilt":
            t = self.t.detach()
            return {"term": "tilt", "trunnion_rad": float(t[0]), "beam_rad": float(t[1])}
        if self.term == "beam":
            e = self.e.detach()
            return {"term": "beam", "azimuth_m": float(e[0]), "elevation_m": float(e[1])}
        a, b = self.a.detach().tolist(), self.b.detach().tolist()
        return {"term": self.term, "harmonics": list(self.orders), "a_rad": a, "b_rad": b}

    def label(self) -> str:
        if self.term == "range":
            return "instrument(range offset" + (" and scale)" if self.scale else ")")
        if self.term == "tilt":
            return "instrument(axis tilt)"
        if self.term == "beam":
            return "instrument(beam offset)"
        many = "s" if len(self.orders) > 1 else ""
        return f"instrument({self.term} harmonic{many} {','.join(str(k) for k in self.orders)})"


def _init(v, n: int) -> Tensor:
    # a parameter's initial value: made on the CPU, moved with the module (.to) like every effect's
    if v is None:
        return torch.zeros(n, dtype=torch.float64, device="cpu")
    return torch.as_tensor(v, dtype=torch.float64, device="cpu").reshape(n)
