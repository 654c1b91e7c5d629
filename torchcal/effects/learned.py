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
from torchcal.errors import ShapeError

Tensor = torch.Tensor


class CorrectionNet(nn.Module):
    """``(N, dof)`` joints [rad] -> ``(N, 3)`` position correction [m] in the robot base frame.

    Inputs are normalised as ``(q - q_offset) / q_scale`` (buffers, default 0 and pi) and
    the output is scaled by ``out_scale`` (buffer, default 1e-3: the network works in mm),
    so that weights of order one describe sub-millimetre fields.

    Args:
        dof: number of joints (paper: 6).
        hidden: hidden units (paper: 29).
        dtype: must be float64 (the calibration path is float64; anything else raises ShapeError).

    Raises:
        ShapeError: ``dtype`` is not float64; at call time, ``q`` is not float64.
    """

    def __init__(
        self,
        dof: int = 6,
        hidden: int = 29,
        *,
        out_scale: float = 1e-3,
        dtype=torch.float64,
        device="cpu",
        seed: int | None = None,
    ):
        if dtype != torch.float64:
            raise ShapeError(f"CorrectionNet computes in float64 (the calibration path), got dtype={dtype}")
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

    def flat(self) -> Tensor:
        """The weights as one vector ``(n_weights,)``: fc1.weight (row-major), fc1.bias, fc2.weight, fc2.bias."""
        return torch.nn.utils.parameters_to_vector(self.parameters()).detach().clone()

    def set_flat(self, w: Tensor) -> None:
        torch.nn.utils.vector_to_parameters(w.detach().clone(), self.parameters())

    def _unpack(self, w: Tensor):
        H, D = self.hidden, self.dof
        i = 0
        W1 = w[..., i : i + H * D].reshape(*w.shape[:-1], H, D)
        i += H * D
        b1 = w[..., i : i + H]
        i += H
        W2 = w[..., i : i + 3 * H].reshape(*w.shape[:-1], 3, H)
        i += 3 * H
        return W1, b1, W2, w[..., i : i + 3]

    def forward_flat(self, w: Tensor, q: Tensor) -> Tensor:
        """Output ``(..., N, 3)`` for flat weights ``w (..., n_weights)`` and joints ``q (..., N, dof)``."""
        self._check_q(q)
        W1, b1, W2, b2 = self._unpack(w)
        x = (q - self.q_offset) / self.q_scale
        a = torch.tanh(x @ W1.transpose(-1, -2) + b1.unsqueeze(-2))
        return (a @ W2.transpose(-1, -2) + b2.unsqueeze(-2)) * self.out_scale

    def jacobian_flat(self, w: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        """Output and its analytic Jacobian with respect to the flat weights.

        Args:
            w: ``(..., n_weights)``; q: ``(..., N, dof)``.

        Returns:
            ``g (..., N, 3)`` and ``dg/dw (..., N, 3, n_weights)`` in the order of :meth:`flat`.
        """
        W1, b1, W2, b2 = self._unpack(w)
        x = (q - self.q_offset) / self.q_scale  # (..., N, D)
        a = torch.tanh(x @ W1.transpose(-1, -2) + b1.unsqueeze(-2))  # (..., N, H)
        g = (a @ W2.transpose(-1, -2) + b2.unsqueeze(-2)) * self.out_scale
        os = self.out_scale
        ds = (1.0 - a * a).unsqueeze(-2) * W2.unsqueeze(-3) * os  # (..., N, 3, H): dg_k/dz_m
        dW1 = ds.unsqueeze(-1) * x.unsqueeze(-2).unsqueeze(-2)  # (..., N, 3, H, D)
        eye3 = torch.eye(3, dtype=w.dtype, device=w.device)
        dW2 = eye3.unsqueeze(-1) * a.unsqueeze(-2).unsqueeze(-2) * os  # (..., N, 3, 3, H)
        db2 = (eye3 * os).expand(*a.shape[:-1], 3, 3)
        J = torch.cat([dW1.flatten(-2), ds, dW2.flatten(-2), db2], dim=-1)
        return g, J

    def _check_q(self, q: Tensor) -> None:
        if q.dtype != self.q_scale.dtype:
            raise ShapeError(
                f"q has dtype {q.dtype}, but the CorrectionNet is {self.q_scale.dtype}; torchcal "
                "computes in float64 and never converts silently"
            )

    def forward(self, q: Tensor) -> Tensor:
        self._check_q(q)
        x = (q - self.q_offset) / self.q_scale
        return self.fc2(torch.tanh(self.fc1(x))) * self.out_scale


class LearnedEffect(Effect):
    """The ``learned`` effect: a :class:`CorrectionNet` adding a correction in the base frame."""

    kind = "learned"
    acts_on = "cartesian"
    fades_beyond_region = True

    def __init__(self, net: CorrectionNet):
        super().__init__(joint=None)
        self.net = net

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
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
