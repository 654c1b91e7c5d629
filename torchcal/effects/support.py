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

With a ``fallback`` robot (the kinematic calibration's geometry) the whole prediction fades to that geometry, not
only the learned correction: a filter that estimated its own geometry together with the network (the adaptive
engine) has a geometry that is only right together with its network, so away from the training joints

    ``y(q) = g * y_model(q) + (1 - g) * y_fallback(q)``

(tracker frame), which the gate writes as a position correction in the model's base frame. The model must then have
no other effects (the integrated method's models have none).
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

    def __init__(
        self, inner: Effect, support: Tensor, length: float = math.inf, *, max_support: int = 3000, fallback=None
    ):
        super().__init__(joint=None)
        if inner.acts_on != "cartesian":
            raise ValueError(f"SupportGate wraps a position correction; {type(inner).__name__} acts on {inner.acts_on}")
        if support.ndim != 2 or len(support) == 0:
            raise ValueError(f"support must have shape (M, dof) with M > 0, got {tuple(support.shape)}")
        self.inner = inner
        stride = max(1, math.ceil(len(support) / max_support))
        kept = support[::stride].detach().clone()
        self.register_buffer("support", kept)
        spread = kept.std(dim=0) if len(kept) > 1 else torch.ones(kept.shape[1], dtype=kept.dtype, device=kept.device)
        self.register_buffer("spread", spread.clamp(min=1e-3))
        self.length = float(length)
        self.fallback = fallback
        if fallback is not None:
            for p in fallback.parameters():
                p.requires_grad_(False)

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

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
        g = self.gate(ctx.q)[:, None]
        out = self.inner(robot, ctx, p_base=p_base) * g
        if self.fallback is None or math.isinf(self.length):
            return out
        p_own = robot.probe_in_base(ctx.q) if p_base is None else p_base
        y_fb = (
            self.fallback.T_tracker_base()
            @ torch.cat([self.fallback.probe_in_base(ctx.q), torch.ones_like(ctx.q[:, :1])], dim=-1).T
        )
        T_inv = torch.linalg.inv(robot.T_tracker_base())
        p_fb = (T_inv @ y_fb).T[:, :3]  # the fallback's probe in this model's base frame
        return out + (1.0 - g) * (p_fb - p_own)

    def config(self) -> dict:
        return {
            "inner": {"class": type(self.inner).__name__, **self.inner.config()},
            "length": self.length,
            "n_support": int(len(self.support)),
            "dof": int(self.support.shape[1]),
            "fallback": self.fallback is not None,
        }

    def describe(self) -> dict:
        return {
            "gate_length": self.length,
            "support_points": int(len(self.support)),
            "falls_back_to": "the kinematic calibration" if self.fallback is not None else "the model's geometry",
            "inner": self.inner.describe(),
        }

    def label(self) -> str:
        return self.inner.label()


def choose_gate_length(
    make_gate: Callable[[float], SupportGate],
    score: Callable[[SupportGate], float],
    lengths: Sequence[float] = GATE_LENGTHS,
) -> tuple[float, list[dict]]:
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
