"""Slow drift with time or temperature."""

from __future__ import annotations

import torch
from torch import nn

from torchcal.effects.base import Context, Effect
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

    Args:
        variable: "t" or "temperature".
        target: "instrument" or "scale".
    """

    kind = "drift"
    VARIABLES = ("t", "temperature")
    TARGETS = ("instrument", "scale")

    def __init__(self, variable: str = "t", target: str = "instrument", rates=None, reference: float = 0.0):
        super().__init__(joint=None)
        if variable not in self.VARIABLES:
            raise OptionError(f"drift variable '{variable}' is not one of {self.VARIABLES}")
        if target not in self.TARGETS:
            raise OptionError(f"drift target '{target}' is not one of {self.TARGETS}")
        self.variable = variable
        self.target = target
        self.acts_on = "instrument" if target == "instrument" else "cartesian"
        n = 6 if target == "instrument" else 1
        r = torch.zeros(n, dtype=torch.float64) if rates is None else torch.as_tensor(rates, dtype=torch.float64)
        self.rates = nn.Parameter(r.reshape(n).clone())
        self.register_buffer("reference", torch.tensor(float(reference), dtype=torch.float64))

    def regressor(self, robot, ctx: Context) -> Tensor:
        """``dv (N,)``: the drift variable relative to its reference."""
        v = ctx.t if self.variable == "t" else ctx.temperature
        if v is None:
            raise EstimationError(f"drift with '{self.variable}' needs a '{self.variable}' column in the data")
        return v - self.reference

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
        dv = self.regressor(robot, ctx)
        if self.target == "instrument":
            return dv[:, None] * self.rates
        if p_base is None:
            raise ValueError("scale drift needs the probe position in the base frame")
        return p_base * (self.rates * dv)[:, None]

    def config(self) -> dict:
        return {"variable": self.variable, "target": self.target}

    def label(self) -> str:
        return f"drift({self.variable}, {self.target})"

    def describe(self) -> dict:
        return {"variable": self.variable, "target": self.target, "rates": self.rates.detach().tolist(),
                "reference": float(self.reference)}
