"""Effects that act on one joint angle: compliance, backlash, cyclic transmission errors."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from torchcal import _dual
from torchcal.effects.base import Context, Effect

Tensor = torch.Tensor


class Compliance(Effect):
    """Joint compliance under gravity.

    A harmonic drive and its bearings twist elastically under load: the gravity torque
    of the links beyond joint j (from the masses and centres of mass of the robot
    description, plus an optional payload at the probe) deflects the joint by
    ``dq_j = k * tau_j(q)``, with ``k`` the joint's compliance [rad / (N m)]. The encoder
    sits on the motor side, so the reading misses this twist and the arm sags.

    Args:
        joint: 1-based joint.
        k: compliance [rad/(N m)].
        payload: mass at the probe [kg].
    """

    kind = "compliance"

    def __init__(self, joint: int, k: float = 0.0, payload: float = 0.0):
        super().__init__(joint)
        self.k = nn.Parameter(torch.tensor(float(k), dtype=torch.float64))
        self.payload = float(payload)

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The gravity torque at this joint ``(N,)`` [N m]: the term multiplied by ``k`` (held constant in
        derivatives: :meth:`~torchcal.robot.model.RobotModel.static_torques`)."""
        return robot.static_torques(ctx.q, payload=self.payload)[:, self.j]

    def forward(self, robot, ctx: Context) -> Tensor:
        # the torque is a constant of the estimators' forward-mode Jacobians: torchcal._dual keeps the product in C++
        return self._joint_delta(ctx, _dual.mul(self.k, self.regressor(robot, ctx)))

    def config(self) -> dict:
        return {"joint": self.joint, "payload": self.payload}

    def describe(self) -> dict:
        return {"k_rad_per_Nm": float(self.k.detach()), "payload_kg": self.payload}


class Backlash(Effect):
    """Gear backlash: a dead zone of width ``b`` between the gear flanks.

    The joint rests on one flank or the other, so its angle is offset by ``+b/2`` or
    ``-b/2`` depending on which way the load pushes it: the sign of the gravity torque
    for static poses, the direction of motion along a trajectory (``source="motion"``),
    or the motion where it is known and the torque otherwise (``source="auto"``).

    Args:
        joint: 1-based joint.
        b: backlash width [rad].
        source: "torque", "motion" or "auto".
    """

    kind = "backlash"
    SOURCES = ("torque", "motion", "auto")

    def __init__(self, joint: int, b: float = 0.0, source: str = "auto"):
        super().__init__(joint)
        if source not in self.SOURCES:
            from torchcal.errors import OptionError

            raise OptionError(f"backlash source '{source}' is not one of {self.SOURCES}")
        self.b = nn.Parameter(torch.tensor(float(b), dtype=torch.float64))
        self.source = source

    def regressor(self, robot, ctx: Context) -> Tensor:
        """The flank sign ``(N,)`` in {-1, +1} (the term multiplied by ``b / 2``)."""
        if self.source != "torque" and ctx.direction is not None:
            s = ctx.direction[:, self.j]
        elif self.source == "motion":
            from torchcal.errors import EstimationError

            raise EstimationError("backlash with source='motion' needs a trajectory (a 't' column)")
        else:
            s = torch.sign(robot.static_torques(ctx.q)[:, self.j])
        return torch.where(s == 0, torch.ones_like(s), s)

    def forward(self, robot, ctx: Context) -> Tensor:
        # constants of the estimators' forward-mode Jacobians meet b through torchcal._dual (same values)
        half_b = _dual.mul_scalar(self.b, 0.5)
        return self._joint_delta(ctx, _dual.mul(half_b, self.regressor(robot, ctx)))

    def config(self) -> dict:
        return {"joint": self.joint, "source": self.source}

    def describe(self) -> dict:
        return {"b_rad": float(self.b.detach()), "source": self.source}


class Cyclic(Effect):
    """Cyclic transmission errors: ``dq_j = sum_k a_k sin(k q_j) + b_k cos(k q_j)``.

    Eccentric gears, encoders mounted off-centre and the flexspline's two-lobe wave
    make the true joint angle run ahead and behind the reading periodically, once or
    twice per revolution of the output; gear tooth and bearing patterns add higher orders
    (3rd to about 10th) at the output, and the gear ratio's multiples on the motor side
    are too fast to see at the flange. Any set of orders is allowed; the default (1, 2)
    is the classic pair, and order selection (:mod:`torchcal.diagnose.forms`) picks others.

    Args:
        joint: 1-based joint.
        harmonics: the orders k, distinct positive integers (default 1 and 2).
        a, b: sine and cosine amplitudes [rad], one per harmonic.
    """

    kind = "cyclic"

    def __init__(self, joint: int, harmonics: Sequence[int] = (1, 2), a=None, b=None):
        super().__init__(joint)
        orders = [int(k) for k in harmonics]
        if not orders or min(orders) < 1 or len(set(orders)) != len(orders):
            from torchcal.errors import OptionError

            raise OptionError(f"cyclic harmonics must be distinct positive integers, got {list(harmonics)}")
        h = torch.tensor(orders, dtype=torch.float64)
        self.register_buffer("harmonics", h)
        n = len(harmonics)

        def init(v):
            return torch.zeros(n, dtype=torch.float64) if v is None else torch.as_tensor(v, dtype=torch.float64)

        self.a = nn.Parameter(init(a).clone())
        self.b = nn.Parameter(init(b).clone())

    def regressor(self, robot, ctx: Context) -> Tensor:
        """``[sin(k q_j), cos(k q_j)]`` per harmonic ``(N, 2 * n_harmonics)``."""
        arg = ctx.q[:, self.j : self.j + 1] * self.harmonics
        return torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1)

    def forward(self, robot, ctx: Context) -> Tensor:
        coef = torch.cat([self.a, self.b])
        return self._joint_delta(ctx, self.regressor(robot, ctx) @ coef)

    def config(self) -> dict:
        return {"joint": self.joint, "harmonics": [int(k) for k in self.harmonics]}

    def describe(self) -> dict:
        return {
            "harmonics": [int(k) for k in self.harmonics],
            "a_rad": self.a.detach().tolist(),
            "b_rad": self.b.detach().tolist(),
        }


class Transmission(Effect):
    """A joint-angle error polynomial in the joint's reading: ``dq_j = sum_{d=1..D} c_d q_j^d``.

    A transmission ratio that differs from the controller's value scales the angle
    (degree 1: ``dq_j = c_1 q_j``, ``c_1`` the relative ratio error); a slightly
    non-linear encoder or a cam-like drive adds degrees 2 and 3. The constant term is
    the joint offset, which the geometry already carries, so degrees start at 1.

    Args:
        joint: 1-based joint.
        degree: highest degree D (>= 1).
        c: coefficients ``(D,)`` [rad / rad^d].
    """

    kind = "transmission"

    def __init__(self, joint: int, degree: int = 1, c=None):
        super().__init__(joint)
        if int(degree) < 1:
            from torchcal.errors import OptionError

            raise OptionError(f"transmission degree must be >= 1, got {degree}")
        self.degree = int(degree)
        c0 = torch.zeros(self.degree, dtype=torch.float64) if c is None else torch.as_tensor(c, dtype=torch.float64)
        self.c = nn.Parameter(c0.reshape(self.degree).clone())

    def regressor(self, robot, ctx: Context) -> Tensor:
        """``[q_j, q_j^2, ..., q_j^D]`` ``(N, D)``."""
        qj = ctx.q[:, self.j : self.j + 1]
        return qj ** torch.arange(1, self.degree + 1, dtype=qj.dtype, device=qj.device)

    def forward(self, robot, ctx: Context) -> Tensor:
        return self._joint_delta(ctx, self.regressor(robot, ctx) @ self.c)

    def config(self) -> dict:
        return {"joint": self.joint, "degree": self.degree}

    def describe(self) -> dict:
        return {"degree": self.degree, "c": self.c.detach().tolist()}


# A joint-angle function fitted on poses whose joint covers a narrow range can be a sum of large terms that cancel
# there (harmonics of 10-250 rad summing to 1e-4 rad): it fits the poses and explodes just beyond them. The bound is
# loose for a well-determined function: its terms add up (ratio near 1; a few where two harmonics partly cancel).
# A smooth function that is small on the poses and large just beyond them has such cancelling terms, so the ratio
# is the test (a search over random cubics and harmonic pairs found none that grew threefold within a tenth of the
# range beyond the poses without a ratio above this bound).
CANCELLATION_RATIO = 20.0  # largest allowed sum of |term| over |sum of terms|, both at their peak on the poses


def joint_function_check(effect: Effect, q: Tensor) -> str | None:
    """Whether a fitted joint-angle function (:class:`Cyclic`, :class:`Transmission`) is determined by the poses.

    Args:
        effect: the fitted effect; other kinds pass (``None``).
        q: the joints of the poses it was fitted on ``(N, dof)`` [rad].

    Returns:
        ``None`` when the function is well determined, else the reason: its terms cancel on the poses (the sum
        of the terms' peaks exceeds ``CANCELLATION_RATIO`` times the function's peak), so that the poses do not
        determine them and the function explodes beyond them.
    """
    if not isinstance(effect, (Cyclic, Transmission)):
        return None
    with torch.no_grad():
        coef = torch.cat([effect.a, effect.b]) if isinstance(effect, Cyclic) else effect.c
        terms = effect.regressor(None, Context(q=q)) * coef
        peak = float(terms.sum(-1).abs().max())
        peak_terms = float(terms.abs().max(0).values.sum())
    if peak_terms <= CANCELLATION_RATIO * max(peak, 1e-15):
        return None
    qj = q[:, effect.j]
    return (
        f"its terms cancel on the fitting poses (sum of |terms| {peak_terms:.3g} rad against a function of "
        f"{peak:.3g} rad): the range of joint {effect.joint} seen ({float(qj.min()):.3f} to {float(qj.max()):.3f} "
        "rad) does not determine them, and beyond it the function would explode"
    )
