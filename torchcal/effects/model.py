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
        p = self.robot.probe_in_base(q) if fk is None else fk(self.robot, q)
        if with_cartesian:
            for e in self.effects:
                if e.acts_on == Acts.CARTESIAN:
                    p = _dual.add(p, e(self.robot, ctx, p_base=p))
        return p

    def forward(self, ctx: Context, fk=None) -> Tensor:
        """Probe position in the tracker frame ``(N, 3)`` [m] (``fk``: see :meth:`probe_in_base`)."""
        p = self.probe_in_base(ctx, fk=fk)
        T = self.robot.T_tracker_base()
        inst = [e for e in self.effects if e.acts_on == Acts.INSTRUMENT]
        if not inst:
            return tf.transform_points(T, p)
        xi = _dual.add_scalar(inst[0](self.robot, ctx), 0)  # = sum(...), which starts from 0
        for e in inst[1:]:
            xi = _dual.add(xi, e(self.robot, ctx))
        return tf.transform_points(T @ tf.se3_from_vector(xi), p)

    def predict(self, q: Tensor, **kw) -> Tensor:
        """Convenience: ``forward(Context(q, **kw))`` without gradients."""
        with torch.no_grad():
            return self(Context(q=q, **kw))
