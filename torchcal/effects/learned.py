"""The correction network of Horvath & Neuner (2024): joints -> position correction.

A shallow fully connected network (paper: 6-29-3, tanh hidden layer, Sec. 2.2.1) that
models what geometry cannot: the position correction of the probe in the robot base
frame, added to the geometric prediction (paper Eqs. 20 and 22:
``p_measured = p_geometric + R_tracker_base @ net(q)``).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from torchcal.effects.base import Context, Effect

Tensor = torch.Tensor


class CorrectionNet(nn.Module):
    """``(N, dof)`` joints [rad] -> ``(N, 3)`` position correction [m] in the robot base frame.

    Inputs are normalised as ``(q - q_offset) / q_scale`` (buffers, default 0 and pi) and
    the output is scaled by ``out_scale`` (buffer, default 1e-3: the network works in mm),
    so that weights of order one describe sub-millimetre fields.

    Args:
        dof: number of joints (paper: 6).
        hidden: hidden units (paper: 29).
        dtype: float64 on the calibration path.
    """

    def __init__(self, dof: int = 6, hidden: int = 29, *, out_scale: float = 1e-3, dtype=torch.float64,
                 device="cpu", seed: int | None = None):
        super().__init__()
        self.dof = dof
        self.hidden = hidden
        self.fc1 = nn.Linear(dof, hidden, dtype=dtype, device=device)
        self.fc2 = nn.Linear(hidden, 3, dtype=dtype, device=device)
        self.register_buffer("q_offset", torch.zeros(dof, dtype=dtype, device=device))
        self.register_buffer("q_scale", torch.full((dof,), math.pi, dtype=dtype, device=device))
        self.register_buffer("out_scale", torch.tensor(out_scale, dtype=dtype, device=device))
        if seed is not None:
            self.reset_parameters(torch.Generator().manual_seed(seed))

    def reset_parameters(self, generator: torch.Generator | None = None, gain: float = 1.0) -> None:
        """Glorot-normal weights, zero output layer bias; reproducible with ``generator``."""
        with torch.no_grad():
            for layer in (self.fc1, self.fc2):
                fan_in, fan_out = layer.weight.shape[1], layer.weight.shape[0]
                std = gain * math.sqrt(2.0 / (fan_in + fan_out))
                layer.weight.copy_(torch.randn(layer.weight.shape, generator=generator, dtype=torch.float64) * std)
                layer.bias.copy_(torch.randn(layer.bias.shape, generator=generator, dtype=torch.float64) * 0.1)
            self.fc2.bias.zero_()

    @property
    def n_weights(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def forward(self, q: Tensor) -> Tensor:
        x = (q - self.q_offset) / self.q_scale
        return self.fc2(torch.tanh(self.fc1(x))) * self.out_scale


class LearnedEffect(Effect):
    """The ``learned`` effect: a :class:`CorrectionNet` adding a correction in the base frame."""

    kind = "learned"
    acts_on = "cartesian"

    def __init__(self, net: CorrectionNet):
        super().__init__(joint=None)
        self.net = net

    def forward(self, robot, ctx: Context) -> Tensor:
        return self.net(ctx.q)

    def config(self) -> dict:
        return {"dof": self.net.dof, "hidden": self.net.hidden}

    def scale_(self, factor: float) -> None:
        """Scale the field linearly: the output layer only (scaling hidden weights would bend it)."""
        with torch.no_grad():
            self.net.fc2.weight.mul_(factor)
            self.net.fc2.bias.mul_(factor)

    def describe(self) -> dict:
        return {"dof": self.net.dof, "hidden": self.net.hidden, "n_weights": self.net.n_weights}
