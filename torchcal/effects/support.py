"""A learned correction that knows where it has seen data.

A network or kernel fitted along a trajectory has seen a thin tube of joint space around that path. Where a later
path leaves the tube, its output is an extrapolation, and a tanh network extrapolates as confidently as it
interpolates. :class:`SupportGate` wraps such an effect and fades its correction towards zero, i.e. back to the
geometric model, with the distance from the training joints:

    ``dp_gated(q) = g(d(q)) * dp(q)``,  ``d(q) = min_i || (q - q_i) / s ||``,  ``g(d) = exp(-d^2 / (2 l^2))``

with ``q_i`` the training joints (thinned to at most ``max_support`` of them), ``s`` the joints' spread on the
training data (so one length fits all joints) and ``l`` the gate's length, chosen on validation data that continue
the training path (:func:`choose_gate_length`). At a training sample ``d = 0`` and the gate is 1, so wrapping an
already fitted effect leaves the training fit unchanged; ``l = inf`` switches the gate off.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

from torchcal.effects.base import Context, Effect

Tensor = torch.Tensor

#: lengths tried by :func:`choose_gate_length`, in units of the joints' training spread (inf: no gate)
GATE_LENGTHS = (math.inf, 0.5, 0.25, 0.12, 0.06)


class SupportGate(Effect):
    """Wrap a Cartesian correction ``inner`` so that it fades to zero away from the training joints.

    Args:
        inner: the fitted effect (``acts_on`` must be ``"cartesian"``: a position correction).
        support: training joints ``(M, dof)`` [rad]; thinned to ``max_support`` evenly spaced rows.
        length: gate length in units of the joints' spread (``inf``: no gate).
        max_support: most support points kept (the distance costs ``N * M * dof``).
    """

    kind = "learned"
    acts_on = "cartesian"

    def __init__(self, inner: Effect, support: Tensor, length: float = math.inf, *, max_support: int = 3000):
        super().__init__(joint=None)
        if inner.acts_on != "cartesian":
            raise ValueError(f"SupportGate wraps a position correction; {type(inner).__name__} acts on {inner.acts_on}")
        if support.ndim != 2 or len(support) == 0:
            raise ValueError(f"support must have shape (M, dof) with M > 0, got {tuple(support.shape)}")
        self.inner = inner
        stride = max(1, math.ceil(len(support) / max_support))
        kept = support[::stride].detach().clone()
        self.register_buffer("support", kept)
        spread = kept.std(dim=0) if len(kept) > 1 else torch.ones(kept.shape[1], dtype=kept.dtype)
        self.register_buffer("spread", spread.clamp(min=1e-3))
        self.length = float(length)

    def distance(self, q: Tensor) -> Tensor:
        """``d(q)``: distance to the nearest support point in units of the spread ``(N,)``."""
        s = self.support / self.spread
        x = q / self.spread
        out = torch.empty(len(q), dtype=q.dtype, device=q.device)
        for i in range(0, len(q), 2048):  # bounded memory: (2048, M) distances at a time
            out[i : i + 2048] = torch.cdist(x[i : i + 2048], s).min(dim=1).values
        return out

    def gate(self, q: Tensor) -> Tensor:
        """``g(d(q))`` in (0, 1] ``(N,)``."""
        if math.isinf(self.length):
            return torch.ones(len(q), dtype=q.dtype, device=q.device)
        d = self.distance(q.detach())
        return torch.exp(-0.5 * (d / self.length) ** 2)

    def forward(self, robot, ctx: Context, **kw) -> Tensor:
        return self.inner(robot, ctx, **kw) * self.gate(ctx.q)[:, None]

    def config(self) -> dict:
        return {"inner": {"class": type(self.inner).__name__, **self.inner.config()}, "length": self.length,
                "n_support": int(len(self.support)), "dof": int(self.support.shape[1])}

    def describe(self) -> dict:
        return {"gate_length": self.length, "support_points": int(len(self.support)), "inner": self.inner.describe()}

    def label(self) -> str:
        return self.inner.label()


def choose_gate_length(make_gate: Callable[[float], SupportGate], score: Callable[[SupportGate], float],
                       lengths: Sequence[float] = GATE_LENGTHS) -> tuple[float, list[dict]]:
    """The gate length with the lowest validation score, and the table of all tried.

    Args:
        make_gate: builds the gated effect for a length.
        score: validation RMSE [m] of the model with that gated effect (lower is better).
        lengths: the lengths to try; ``inf`` (no gate) should be among them, so the gate can only help.

    Ties go to the longer gate (the earlier one in ``lengths``): a gate is kept only where it helps.
    """
    table = []
    best = (math.inf, lengths[0])
    for length in lengths:
        s = float(score(make_gate(length)))
        table.append({"length": length, "validation_rmse_m": s})
        if s < best[0] * (1.0 - 1e-9):
            best = (s, length)
    return best[1], table
