"""Slow drift with time or temperature."""

from __future__ import annotations

import math

import torch
from torch import nn

from torchcal import _dual
from torchcal.effects.base import Context, Effect, register_range
from torchcal.errors import EstimationError, OptionError

Tensor = torch.Tensor


class Drift(Effect):
    """Slow drift of the set-up with time ``t`` or ``temperature``.

    Over a campaign the tracker stand settles and warms, the robot's base and links
    expand: the measured positions wander slowly against the model. Two forms:

    * ``target="instrument"``: the instrument pose drifts linearly,
      ``T_tracker_base(v) = T_tracker_base @ [exp(r * dv) | t * dv]`` with
      ``rates = [t, r]`` per unit of ``v`` (m and rad per second or per degC);
    * ``target="scale"``: the arm expands uniformly about its base,
      ``p_base -> p_base * (1 + c * dv)``, ``c`` per second or per degC (thermal
      expansion of aluminium links is about 2.3e-5 / degC).

    ``dv = v - reference`` with ``reference`` the variable's value at the first sample
    used for fitting, so the geometry refers to the start of the campaign.

    Time course (``form``):

    * ``"linear"`` (default): the drift grows as ``dv``;
    * ``"exponential"``: a warm-up that settles, ``g(dv) = tau (1 - exp(-dv / tau))`` in place of
      ``dv``, with the time constant ``tau`` (unit of ``v``) a fitted parameter (stored as
      ``log_tau``). ``rates`` keep their meaning (the initial rate of change); the drift settles at
      ``rates * tau``, and for ``tau`` much longer than the campaign the form tends to the linear one.

    Args:
        variable: "t" or "temperature".
        target: "instrument" or "scale".
        rates: initial rates, 6 (instrument ``[t, r]``) or 1 (scale).
        reference: value of the variable where the drift is zero.
        form: "linear" or "exponential".
        tau: initial time constant of the exponential form (unit of the variable, > 0).
        region: ``(lo, hi)`` of the time the drift was fitted on [s], its calibrated region in time (a drift in ``t``
            only): beyond it the drift holds its value at the nearer end. None: it continues as fitted. Runs written
            before the name ``region`` saved it as ``span`` (:attr:`renamed`).
    """

    kind = "drift"
    VARIABLES = ("t", "temperature")
    TARGETS = ("instrument", "scale")
    FORMS = ("linear", "exponential")
    renamed = {"span": "region"}

    def __init__(
        self,
        variable: str = "t",
        target: str = "instrument",
        rates=None,
        reference: float = 0.0,
        form: str = "linear",
        tau: float = 1800.0,
        region=None,
    ):
        super().__init__(joint=None)
        if variable not in self.VARIABLES:
            raise OptionError(f"drift variable '{variable}' is not one of {self.VARIABLES}")
        if target not in self.TARGETS:
            raise OptionError(f"drift target '{target}' is not one of {self.TARGETS}")
        if form not in self.FORMS:
            raise OptionError(f"drift form '{form}' is not one of {self.FORMS}")
        if form == "exponential" and not float(tau) > 0.0:
            raise OptionError(f"drift time constant must be positive, got {tau}")
        self.variable = variable
        self.target = target
        self.form = form
        if form == "exponential":
            self.log_tau = nn.Parameter(torch.tensor(math.log(float(tau)), dtype=torch.float64))
        self.acts_on = "instrument" if target == "instrument" else "cartesian"
        n = 6 if target == "instrument" else 1
        r = torch.zeros(n, dtype=torch.float64) if rates is None else torch.as_tensor(rates, dtype=torch.float64)
        self.rates = nn.Parameter(r.reshape(n).clone())
        self.register_buffer("reference", torch.tensor(float(reference), dtype=torch.float64))
        register_range(self, "region", region, "drift region")

    def set_region(self, t: Tensor) -> None:
        """Record the times ``t`` ``(N,)`` the drift is fitted on as its region (a drift in temperature keeps its
        law)."""
        if self.variable == "t":
            self.region = torch.stack([t.detach().min(), t.detach().max()]).to(torch.float64)

    def regressor(self, robot, ctx: Context) -> Tensor:
        """``dv (N,)``: the drift variable relative to its reference; a drift in time held at its value at the ends of
        the time it was fitted on (``region``): a linear drift is the first term of a set-up that settles, and
        continued beyond the campaign it grows without a law, while held at its ends its error stays bounded.
        Thermal expansion in temperature extends."""
        v = ctx.t if self.variable == "t" else ctx.temperature
        if v is None:
            raise EstimationError(f"drift with '{self.variable}' needs a '{self.variable}' column in the data")
        if self.region is not None:
            v = torch.minimum(torch.maximum(v, self.region[0]), self.region[1])
        return v - self.reference

    def time_course(self, dv: Tensor) -> Tensor:
        """``dv`` (linear form) or ``tau (1 - exp(-dv / tau))`` (exponential form), ``(N,)``."""
        if self.form == "linear":
            return dv
        tau = torch.exp(self.log_tau)
        return -tau * torch.expm1(_dual.div(-dv, tau))

    @property
    def tau(self) -> float | None:
        """The time constant (unit of the variable), or None for the linear form."""
        return float(torch.exp(self.log_tau.detach())) if self.form == "exponential" else None

    def scale_(self, factor: float) -> None:
        """Scale the rates only: the time constant is a shape, not a size."""
        with torch.no_grad():
            self.rates.mul_(factor)

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
        # the drift variable is a constant of the estimators' forward-mode Jacobians: it meets the rates through
        # torchcal._dual (same values; torch's Python path otherwise)
        dv = self.time_course(self.regressor(robot, ctx))
        if self.target == "instrument":
            return _dual.mul(dv[:, None], self.rates)
        if p_base is None:
            raise ValueError("scale drift needs the probe position in the base frame")
        return _dual.mul(p_base, _dual.mul(self.rates, dv)[:, None])

    def param_units(self, robot) -> dict:
        per = "s" if self.variable == "t" else "°C"
        rates = [f"m/{per}"] * 3 + [f"rad/{per}"] * 3 if self.target == "instrument" else [f"1/{per}"]
        return {"rates": rates, "log_tau": f"ln({per})", "tau": per}

    def config(self) -> dict:
        cfg = {"variable": self.variable, "target": self.target}
        if self.form != "linear":  # the linear default keeps the older config unchanged
            cfg["form"] = self.form
        if self.region is not None:
            cfg["region"] = [float(v) for v in self.region]
        return cfg

    def label(self) -> str:
        form = "" if self.form == "linear" else f", {self.form}"
        return f"drift({self.variable}, {self.target}{form})"

    def describe(self) -> dict:
        out = {
            "variable": self.variable,
            "target": self.target,
            "form": self.form,
            "rates": self.rates.detach().tolist(),
            "reference": float(self.reference),
        }
        if self.form == "exponential":
            out["tau"] = self.tau
        return out
