"""A learned correction per measurement group: each row takes the correction of its station and probe.

Where the data carry several instrument stations or probes (measurement days, tools), the residual field that
geometry and named effects leave differs between them; one correction, a function of the joints alone, fits their
average. :class:`GroupedCorrection` holds one learned correction per ``(station, probe)`` group present in the
training data and dispatches each row to its group's one by the context's ``station`` and ``probe``; a group
without a correction (too few rows, or none earned its place) adds nothing. Each group's correction fades to zero
beyond the range of joints that group was measured over, as the model's learned corrections fade beyond the whole
calibration's (:meth:`~torchcal.effects.model.MeasurementModel.set_region`): a group measured over a small part of the
region (one day's cube of poses) says nothing about the rest of it.
"""

from __future__ import annotations

import torch
from torch import nn

from torchcal._torch import same_version, version_key
from torchcal.effects.base import Context, Effect

Tensor = torch.Tensor


def row_groups(ctx: Context) -> tuple[Tensor, Tensor]:
    """Each row's station and probe index ``(N,)`` int64 (0 where the context carries none)."""
    n = ctx.q.shape[0]
    zero = torch.zeros(n, dtype=torch.long, device=ctx.q.device)
    st = zero if ctx.station is None else ctx.station.to(torch.long)
    pr = zero if ctx.probe is None else ctx.probe.to(torch.long)
    return st, pr


class GroupedCorrection(Effect):
    """The ``learned`` effect, one Cartesian correction per ``(station, probe)`` group.

    Args:
        groups: the ``(station, probe)`` index of each inner correction.
        inner: the corrections (Cartesian effects of kind ``learned``), in the order of ``groups``.
        regions: each group's joint range ``(2, dof)`` (lower, upper) its correction fades beyond; None: no fade.
    """

    kind = "learned"
    acts_on = "cartesian"
    fades_beyond_region = True

    def __init__(self, groups, inner, regions=None):
        super().__init__(joint=None)
        self.groups = [(int(s), int(p)) for s, p in groups]
        self.inner = nn.ModuleList(list(inner))
        if len(self.groups) != len(self.inner):
            raise ValueError("GroupedCorrection: one inner correction per group")
        if regions is not None and len(regions) != len(self.groups):
            raise ValueError("GroupedCorrection: one region per group")
        self.regions = None if regions is None else [torch.as_tensor(r, dtype=torch.float64) for r in regions]
        self._cache: tuple | None = None

    def _split(self, ctx: Context) -> list[tuple[Tensor, Context]]:
        """Each group's rows and sub-context. The last split is reused while the context's tensors are the same
        objects, unmodified: a least-squares fit evaluates the effect at the same rows dozens of times, and the
        inner corrections keep their last result for the same context tensors (the GP's, the kernel's cache)."""
        key = version_key(ctx.q, ctx.t, ctx.temperature, ctx.direction, ctx.station, ctx.probe)
        if key is not None and self._cache is not None and same_version(self._cache[0], key):
            return self._cache[1]
        st, pr = row_groups(ctx)
        parts = []
        for s, p in self.groups:
            rows = torch.nonzero((st == s) & (pr == p)).flatten()
            parts.append((rows, ctx.subset(rows)))
        if key is not None:
            self._cache = (key, parts)
        return parts

    def fade(self, k: int, q: Tensor) -> Tensor | None:
        """Group ``k``'s fade at ``q`` ``(n, 1)``: 1 within its joint range, ``exp(-d^2 / (2 FADE_LENGTH^2))`` at a
        distance ``d`` beyond it (the model's own rule); None without regions."""
        if self.regions is None:
            return None
        from torchcal.effects.joint import FADE_LENGTH

        lo, hi = (r.to(dtype=q.dtype, device=q.device) for r in self.regions[k])
        d = torch.maximum(lo - q.detach(), q.detach() - hi).clamp(min=0).amax(dim=1)
        return torch.exp(-0.5 * (d / FADE_LENGTH) ** 2)[:, None]

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:
        out = torch.zeros(ctx.q.shape[0], 3, dtype=ctx.q.dtype, device=ctx.q.device)
        for k, ((rows, sub), eff) in enumerate(zip(self._split(ctx), self.inner)):
            if len(rows) == 0:
                continue
            dp = eff(robot, sub, None if p_base is None else p_base[rows])
            w = self.fade(k, sub.q)
            out = out.index_put((rows,), dp if w is None else dp * w)
        return out

    def scale_(self, factor: float) -> None:
        for eff in self.inner:
            eff.scale_(factor)

    def config(self) -> dict:
        out = {
            "groups": [list(g) for g in self.groups],
            "inner": [{"class": type(e).__name__, **e.config()} for e in self.inner],
        }
        if self.regions is not None:
            out["regions"] = [r.tolist() for r in self.regions]
        return out

    def describe(self) -> dict:
        return {
            "groups": [
                {"station": s, "probe": p, "class": type(e).__name__, **e.describe()}
                for (s, p), e in zip(self.groups, self.inner)
            ]
        }
