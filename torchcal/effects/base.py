"""What every non-geometric effect shares, and the context it reads.

An effect is an ``nn.Module`` with its own parameters that acts where it physically
does: on the joint angles (``joint``: returns ``dq (N, dof)`` added to the readings), on
the probe position in the robot base frame (``cartesian``: returns ``dp (N, 3)``), or on
the instrument pose (``instrument``: returns a per-sample correction ``(N, 6)``
``[t, r]`` applied as ``T_tracker_base @ [exp(r) | t]``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import torch
from torch import nn

Tensor = torch.Tensor


@dataclass
class Context:
    """Per-sample inputs an effect may read.

    Attributes:
        q: joint readings ``(N, dof)`` [rad].
        t: acquisition time ``(N,)`` [s] or None.
        temperature: ``(N,)`` [degC] or None.
        direction: sign of each joint's motion ``(N, dof)`` in {-1, 0, +1} (trajectories), or None.
        station: which instrument placement measured each row ``(N,)`` int64, or None (station 0 everywhere).
        probe: which probe each row measured ``(N,)`` int64, or None (probe 0 everywhere).
        payload: the mass at the flange ``(N,)`` [kg], or None (no load column: 0 kg).
        payload_com: the payload's centre of mass in the flange frame ``(N, 3)`` [m], or None (at the probe).
        tau: the measured joint torques ``(N, dof)`` [N m, N for a prismatic joint], or None.
    """

    q: Tensor
    t: Tensor | None = None
    temperature: Tensor | None = None
    direction: Tensor | None = None
    station: Tensor | None = None
    probe: Tensor | None = None
    payload: Tensor | None = None
    payload_com: Tensor | None = None
    tau: Tensor | None = None

    @classmethod
    def from_measurements(cls, m, *, trajectory: bool | None = None) -> Context:
        """Context of a :class:`~torchcal.data.Measurements`; motion direction when it is a trajectory."""
        traj = (m.t is not None) if trajectory is None else trajectory
        return cls(
            q=m.q,
            t=m.t,
            temperature=m.temperature,
            direction=motion_direction(m.q) if traj else None,
            station=getattr(m, "station", None),
            probe=getattr(m, "probe", None),
            payload=getattr(m, "payload", None),
            payload_com=getattr(m, "payload_com", None),
            tau=getattr(m, "tau", None),
        )

    def subset(self, idx) -> Context:
        def pick(x):
            return None if x is None else x[idx]

        return Context(
            q=self.q[idx],
            t=pick(self.t),
            temperature=pick(self.temperature),
            direction=pick(self.direction),
            station=pick(self.station),
            probe=pick(self.probe),
            payload=pick(self.payload),
            payload_com=pick(self.payload_com),
            tau=pick(self.tau),
        )


def motion_direction(q: Tensor, deadband: float = 0.0) -> Tensor:
    """Sign of each joint's motion along a sampled trajectory ``(N, dof)``.

    Where a joint stands still (|dq| <= deadband) the previous sign is held, because a
    gear stays on the flank it last loaded; the first sample takes the first motion's sign.
    """
    if len(q) == 0:  # no samples, no motion (the reductions below need one)
        return torch.zeros_like(q)
    dq = torch.diff(q, dim=0, prepend=q[:1])
    s = torch.where(dq.abs() > deadband, torch.sign(dq), torch.zeros_like(dq))
    out = s.clone()
    # forward fill of zeros (hold last non-zero sign), then back fill the leading zeros
    idx = torch.arange(len(q), device=q.device).unsqueeze(1).expand_as(s)
    last = torch.where(s != 0, idx, torch.zeros_like(idx))
    last = torch.cummax(last, dim=0).values
    out = torch.gather(s, 0, last)
    first_nonzero = torch.where(s != 0, idx, torch.full_like(idx, len(q))).min(dim=0).values
    lead = idx < first_nonzero.unsqueeze(0)
    first_sign = torch.gather(s, 0, first_nonzero.clamp(max=len(q) - 1).unsqueeze(0)).expand_as(s)
    return torch.where(lead, first_sign, out)


class Acts(str, Enum):
    """Where an effect acts in :class:`~torchcal.effects.model.MeasurementModel` (str-valued: ``"joint"`` etc.)."""

    JOINT = "joint"  #: adds a joint offset ``dq (N, dof)`` [rad] before the kinematics
    CARTESIAN = "cartesian"  #: adds a probe offset ``dp (N, 3)`` [m] in the base frame
    INSTRUMENT = "instrument"  #: perturbs the tracker pose by ``xi (N, 6)`` (se(3) vector)
    TRACKER = "tracker"  #: adds ``dp (N, 3)`` [m] to the point in the tracker frame: the instrument's own errors

    def __str__(self) -> str:  # f-strings and str() give the value on every Python version
        return self.value


def register_range(module: nn.Module, name: str, region, what: str) -> None:
    """Register the buffer ``name``: ``(lo, hi)`` from ``region`` (float64), or None when ``region`` is None (a None
    buffer is not in the state dict, so runs written before the range was kept load as they were).

    Raises:
        OptionError: ``lo > hi`` (``what`` names the range in the message).
    """
    if region is None:
        module.register_buffer(name, None)
        return
    lo, hi = (float(v) for v in region)
    if not lo <= hi:
        from torchcal.errors import OptionError

        raise OptionError(f"{what} must be (lo, hi) with lo <= hi, got {list(region)}")
    module.register_buffer(name, torch.tensor([lo, hi], dtype=torch.float64))


def read_renamed(mapping: dict, renamed: dict[str, str], prefix: str = "") -> dict:
    """Read the keys ``mapping`` saved under an older name by their new one, in place, and return it.

    ``renamed`` maps old names to new (:attr:`Effect.renamed`); ``prefix`` is a state dict's module prefix. A run
    written before "region" became the one word for where a correction was fitted saved ``support`` or ``span``:
    its ``model.json`` configs and ``model.pt`` state dicts load as if written now.

    Raises:
        ValueError: both the old and the new name (the file cannot say which holds).
    """
    for old, new in renamed.items():
        if prefix + old not in mapping:
            continue
        if prefix + new in mapping:
            raise ValueError(f"both {prefix + old!r} and its newer name {prefix + new!r} are given")
        mapping[prefix + new] = mapping.pop(prefix + old)
    return mapping


class Effect(nn.Module):
    """Base class. Subclasses set ``kind`` and ``acts_on`` and implement the one signature
    ``forward(robot, ctx, p_base=None)``.

    ``p_base`` ``(N, 3)`` [m] is the probe position in the base frame with the joint effects applied; the
    measurement model passes it to every Cartesian effect (a scale drift is proportional to it), the
    others ignore it.

    Args:
        joint: 1-based joint the effect belongs to, or None.
    """

    kind: str = "effect"
    acts_on: Acts = Acts.JOINT  # a plain string compares equal to its Acts member
    #: whether the output reads the robot's instrument pose (``T_tracker_base``): the estimators then differentiate
    #: the pose through the whole model instead of in closed form (:func:`torchcal.estimate.problem.residual_function`)
    reads_instrument: bool = False
    #: whether a :class:`~torchcal.effects.model.MeasurementModel` whose region fades fades this effect beyond its
    #: calibrated region (a learned correction with no law of its own beyond the data)
    fades_beyond_region: bool = False
    #: keys of the config and the state dict under an older name, old -> new (:func:`read_renamed`)
    renamed: dict[str, str] = {}

    def __init__(self, joint: int | None = None):
        super().__init__()
        self.joint = joint

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a model.pt written before a buffer's rename holds it under the old name
        read_renamed(state_dict, self.renamed, prefix)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def j(self) -> int:
        """0-based joint index."""
        return int(self.joint) - 1

    def forward(self, robot, ctx: Context, p_base: Tensor | None = None) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def scale_(self, factor: float) -> None:
        """Multiply the effect's magnitude by ``factor`` (the simulator sizes effects this way)."""
        with torch.no_grad():
            for p in self.parameters():
                p.mul_(factor)

    def describe(self) -> dict:
        """The effect's parameters as plain numbers, for truth.json and reports."""
        return {name: p.detach().cpu().tolist() for name, p in self.named_parameters()}

    def param_units(self, robot) -> dict[str, str | list[str]]:
        """The unit of each fitted parameter (by attribute name; a list gives one per element), for the reports:
        SI, ``rad`` for an angle, and a joint's own unit (``rad``, or ``m`` for a prismatic joint of ``robot``)
        where the parameter is a joint error. Empty for effects with no physical parameters (learned ones)."""
        return {}

    def joint_unit(self, robot) -> str:
        """``rad``, or ``m`` where this effect's joint of ``robot`` is prismatic."""
        return "m" if robot.joint_types[self.j] == "prismatic" else "rad"

    def config(self) -> dict:
        """Constructor arguments (besides parameter values) to rebuild the module (see
        :func:`~torchcal.effects.registry.effect_from_config`)."""
        return {"joint": self.joint}

    def label(self) -> str:
        return self.kind if self.joint is None else f"{self.kind}(joint {self.joint})"

    def _joint_delta(self, ctx: Context, value: Tensor) -> Tensor:
        # built out of place: the least squares evaluate their trial points in one torch.func.vmap call, where a
        # batched value cannot be written into an unbatched tensor
        q, j = ctx.q, self.j
        return torch.cat(
            [q.new_zeros(len(q), j), value.expand(len(q)).unsqueeze(-1), q.new_zeros(len(q), q.shape[1] - j - 1)], -1
        )
