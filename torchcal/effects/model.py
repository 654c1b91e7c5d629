"""The full observation model: geometry + effects -> probe position in the tracker frame."""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import nn

from torchcal import _dual
from torchcal.effects.base import Acts, Context, Effect
from torchcal.robot import transforms as tf
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor


class MeasurementModel(nn.Module):
    """``p_tracker = T_tracker_base(ctx) @ (T_base_flange(q + dq) @ t_flange_probe + dp)``.

    ``dq`` sums the joint effects, ``dp`` the Cartesian ones (base frame), and instrument
    effects perturb ``T_tracker_base`` per sample (each effect's :class:`~torchcal.effects.base.Acts`).
    Every Cartesian effect is called with the probe position reached so far, ``p_base``.

    Args:
        robot: the :class:`RobotModel` (geometry, instrument pose, lever arm).
        effects: non-geometric effects.
    """

    def __init__(self, robot: RobotModel, effects: Iterable[Effect] = ()):
        super().__init__()
        self.robot = robot
        self.effects = nn.ModuleList([e.to(robot.device) for e in effects])  # effects are built on CPU
        # the calibrated region (set_region): not in the state dict, a run directory's model.json carries it
        self.register_buffer("region", None, persistent=False)
        self.region_fade = False

    def set_region(self, q: Tensor | None, *, fade: bool = False) -> None:
        """Record the calibrated region: the range of every joint in ``q`` ``(N, dof)`` (None: no region).

        With ``fade``, the learned Cartesian corrections (the effects whose ``fades_beyond_region`` is set: a
        network, a kernel regression, a Gaussian process; not a :class:`~torchcal.effects.region.RegionGate`,
        which has its own region) fade to zero beyond the region, by ``exp(-d^2 / (2 FADE_LENGTH^2))`` with ``d``
        the :meth:`extrapolation`: nothing in their fit says how they continue there.
        """
        if q is None:
            self.region, self.region_fade = None, False
            return
        self.region = torch.stack([q.min(0).values, q.max(0).values]).detach().to(self.robot.dtype)
        self.region_fade = bool(fade)

    def extrapolation(self, q: Tensor) -> Tensor:
        """How far each pose lies outside the calibrated region ``(N,)``: the largest distance of a joint beyond the
        range it covered in the calibration, in the joint's unit (rad for a revolute joint, m for a prismatic one); 0
        inside the region, and everywhere when no region is recorded."""
        if self.region is None:
            return torch.zeros(len(q), dtype=q.dtype, device=q.device)
        lo, hi = self.region[0], self.region[1]
        return torch.maximum(lo - q, q - hi).clamp(min=0).amax(dim=1) if q.shape[1] else q.new_zeros(len(q))

    @property
    def has_learned(self) -> bool:
        """Whether the model holds a learned correction (an effect of kind ``learned``)."""
        return any(e.kind == "learned" for e in self.effects)

    def region_weight(self, q: Tensor) -> Tensor | None:
        """The fade of the learned corrections at ``q`` ``(N, 1)``, or None where they do not fade (see
        :meth:`set_region`)."""
        if not self.region_fade or self.region is None:
            return None
        from torchcal.effects.joint import FADE_LENGTH

        d = self.extrapolation(q.detach())
        return torch.exp(-0.5 * (d / FADE_LENGTH) ** 2)[:, None]

    def add(self, effect: Effect) -> None:
        self.effects.append(effect.to(self.robot.device))

    def joint_offsets(self, ctx: Context) -> Tensor:
        # sums of constants (the readings, a fixed effect) and differentiated terms meet through torchcal._dual: the
        # estimators' Jacobians are forward-mode passes over this model (there, torch's Python path otherwise)
        dq = torch.zeros_like(ctx.q)
        for e in self.effects:
            if e.acts_on == Acts.JOINT:
                dq = _dual.add(dq, e(self.robot, ctx))
        return dq

    def probe_in_base(self, ctx: Context, *, with_cartesian: bool = True, fk=None) -> Tensor:
        """Probe position in the base frame ``(N, 3)`` with joint and Cartesian effects applied.

        ``fk(robot, q) -> (N, 3)`` replaces the robot's own kinematics (the estimators pass a linearisation of it
        to differentiate everything else cheaply, :func:`torchcal.estimate.problem.residual_function`).
        """
        q = _dual.add(ctx.q, self.joint_offsets(ctx))
        if fk is not None:
            p = fk(self.robot, q)
        elif self.robot.probes:  # one lever arm per probe: each row's own
            p = self.robot.probe_in_base(q, ctx.probe)
        else:
            p = self.robot.probe_in_base(q)
        if with_cartesian:
            w = self.region_weight(ctx.q)
            for e in self.effects:
                if e.acts_on == Acts.CARTESIAN:
                    dp = e(self.robot, ctx, p_base=p)
                    if w is not None and e.fades_beyond_region:
                        dp = _dual.mul(dp, w)
                    p = _dual.add(p, dp)
        return p

    def _instrument(self, ctx: Context) -> Tensor:
        """``T_tracker_base`` ``(4, 4)``, or each row's ``(N, 4, 4)`` with one instrument pose per station (the
        context's ``station``); drift effects perturb every station's pose alike (:meth:`_instrument_offset`)."""
        return self.robot.instrument.rows(ctx.station) if self.robot.stations else self.robot.T_tracker_base()

    def _instrument_offset(self, ctx: Context) -> Tensor | None:
        """The instrument effects' per-sample perturbation ``xi (N, 6)`` of ``T_tracker_base``, or None."""
        inst = [e for e in self.effects if e.acts_on == Acts.INSTRUMENT]
        if not inst:
            return None
        xi = _dual.add_scalar(inst[0](self.robot, ctx), 0)  # = sum(...), which starts from 0
        for e in inst[1:]:
            xi = _dual.add(xi, e(self.robot, ctx))
        return xi

    def forward(self, ctx: Context, fk=None, *, orientation: bool = False, rot=None) -> Tensor:
        """Probe position in the tracker frame ``(N, 3)`` [m] (``fk``: see :meth:`probe_in_base`); with
        ``orientation`` the probe frame's orientation there instead (:meth:`orientation`, ``rot``: see there)."""
        if orientation:
            return self.orientation(ctx, rot=rot)
        p = self.probe_in_base(ctx, fk=fk)
        T = self._instrument(ctx)
        xi = self._instrument_offset(ctx)
        p = tf.transform_points(T if xi is None else T @ tf.se3_from_vector(xi), p)
        for e in self.effects:  # the instrument's own errors, on the point it measures (effects.instrument)
            if e.acts_on == Acts.TRACKER:
                p = _dual.add(p, e(self.robot, ctx, p_tracker=p))
        return p

    def orientation(self, ctx: Context, *, rot=None) -> Tensor:
        """The probe frame's orientation in the tracker frame ``(N, 3, 3)``:
        ``R_tracker_base(ctx) R_base_flange(q + dq) R_flange_probe``.

        Joint effects (``dq``) and instrument effects turn it; Cartesian effects (a position correction, a learned
        residual model) do not: they say nothing about orientation. Needs a robot with a probe orientation
        (:meth:`~torchcal.robot.model.RobotModel.enable_orientation`). ``rot(robot, q) -> (N, 3, 3)`` replaces the
        robot's ``R_base_flange`` (the estimators pass a linearisation of it,
        :func:`torchcal.estimate.problem.orientation_function`).
        """
        q = _dual.add(ctx.q, self.joint_offsets(ctx))
        if rot is not None:
            R = rot(self.robot, q) @ self.robot.tool_rotation.matrix()
        else:
            R = self.robot.probe_rotation(q)
        T = self._instrument(ctx)
        xi = self._instrument_offset(ctx)
        if xi is not None:
            T = T @ tf.se3_from_vector(xi)
        return T[..., :3, :3] @ R

    def predict(self, q: Tensor, **kw) -> Tensor:
        """Predicted probe positions in the tracker frame ``(N, 3)`` [m], in memory and without gradients: a run's
        ``run.model.predict(q)`` is what ``torchcal predict`` computes from its run directory (tests/use/
        test_predict_in_memory.py).

        Args:
            q: joint readings ``(N, dof)`` [rad, or m for a prismatic joint].
            **kw: the other fields of :class:`~torchcal.effects.base.Context`: ``t`` ``(N,)`` [s] for a drift in time,
                ``temperature`` ``(N,)`` [degC], ``station`` and ``probe`` ``(N,)`` int64 indices for a run of several.
        """
        with torch.no_grad():
            return self(Context(q=q, **kw))
