"""Campaigns with effects written as plain formulas, outside the effect library's families.

:mod:`torchcal.sim.campaign` injects the effect modules the calibration fits, so a test built on it
can only find what the library already knows. This generator writes its effects as formulas on
tensors, not as :mod:`torchcal.effects` modules, in forms the library need not have:

* ``harmonic``: ``dq_j = A sin(k q_j + phi)`` of any order ``k`` (3 to 8 and beyond) on any joint;
* ``polynomial``: ``dq_j = sum_d c_d q_j^d`` (degree 1: a transmission-ratio error);
* ``joint_time``: a joint error that changes over the campaign, ``dq_j = A s(t) sin(k q_j + phi)`` with
  ``s = (t - t_0) / duration`` growing from 0 to 1 (order ``k = 0``: ``sin`` replaced by 1, a joint offset
  that drifts linearly); a product of a joint angle and time that neither shows alone;
* ``warmup``: the tracker-frame position moves by ``A u (1 - exp(-(t - t_0) / tau))`` along a unit
  vector ``u`` (an axis index, ``"horizontal"`` for a random horizontal direction, or a vector), with
  the time constant ``tau`` [s];

and any combination of them. Each effect is scaled so that the RMS probe displacement it causes alone
over all poses equals its ``size`` [m]. Geometry bias, tracker placement, lever arm, poses and noise
are those of :func:`torchcal.sim.campaign.simulate` (same :class:`SimConfig`); static test poses are
interleaved in time with the training poses (a seeded random draw), trajectories are split as there.
The result is a :class:`~torchcal.sim.campaign.Campaign` whose ``model`` holds the true geometry
without the effects (their formulas are in ``truth["effects"]``).

:func:`simulate_outside_trajectory` writes a trajectory campaign that shares neither the path nor the field of
:mod:`torchcal.sim.campaign`, to judge the integrated method on paths it was not tuned on
(:class:`OutsideTrajectory`): every joint follows its own sum of 3 to 5 sines of incommensurate periods (a
fraction of the campaign up to longer than it, so the continuation reaches postures the training part did not),
random phases and amplitudes that together reach most of the joint range, without the line-of-sight rule; the
field is a formula on tensors of the commanded joints (:data:`FIELD_KINDS`): a random tanh network of any width,
a sum of random Fourier features, products of per-joint sines, or a per-joint (additive) sum. Only the biased
geometry, tracker placement and lever arm come from :mod:`torchcal.sim.campaign`; the first
``train_fraction`` of the samples train, their continuation is the test.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import torch

from torchcal.data import Measurements
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.robot import transforms as tf
from torchcal.sim.campaign import Campaign, SimConfig, _config_dict, _measured, _true_robot
from torchcal.sim.poses import Scene, random_poses, trajectory

Tensor = torch.Tensor
F64 = torch.float64

FORMS = ("harmonic", "polynomial", "warmup", "joint_time")
#: fields of :func:`simulate_outside_trajectory` (:class:`OutsideTrajectory`)
FIELD_KINDS = ("tanh", "fourier", "product", "additive")


@dataclass
class OutsideEffect:
    """One effect as a formula (module docstring).

    Attributes:
        form: ``harmonic``, ``polynomial``, ``warmup`` or ``joint_time``.
        joint: 1-based joint (harmonic, polynomial, joint_time).
        order: harmonic order k (joint_time: 0 for an offset drifting in time; default 0).
        coeffs: polynomial shape ``c_1..c_D`` (rescaled to ``size``); default ``(1.0,)``.
        axis: warmup direction: 0, 1, 2 (tracker x, y, z), ``"horizontal"`` or a 3-vector.
        tau: warmup time constant [s]; None draws one uniformly in 5-60 min.
        size: RMS probe displacement [m].
        phase: harmonic phase [rad]; None draws one.
    """

    form: str
    joint: int | None = None
    order: int | None = None
    coeffs: tuple[float, ...] | None = None
    axis: int | str | tuple[float, float, float] | None = None
    tau: float | None = None
    size: float = 4e-5
    phase: float | None = None

    def __post_init__(self):
        if self.form not in FORMS:
            raise OptionError(f"outside effect form '{self.form}' is not one of {FORMS}")
        if self.form in ("harmonic", "polynomial", "joint_time") and self.joint is None:
            raise OptionError(f"a {self.form} effect needs a joint")
        if self.form == "harmonic" and not (self.order and self.order >= 1):
            raise OptionError(f"a harmonic effect needs an order >= 1, got {self.order}")
        if self.form == "joint_time" and not (self.order or 0) >= 0:
            raise OptionError(f"a joint_time effect needs an order >= 0, got {self.order}")
        if self.form == "warmup" and self.axis is None:
            raise OptionError("a warmup effect needs an axis (0, 1, 2, 'horizontal' or a vector)")
        if not self.size > 0:
            raise OptionError(f"effect size must be positive, got {self.size}")


def _joint_term(e: OutsideEffect, q: Tensor, amp: float, phase: float, coeffs: Tensor, s: Tensor) -> Tensor:
    qj = q[:, e.joint - 1]
    if e.form == "harmonic":
        return amp * torch.sin(e.order * qj + phase)
    if e.form == "joint_time":
        return amp * s * (torch.sin(e.order * qj + phase) if e.order else torch.ones_like(qj))
    return amp * (qj[:, None] ** torch.arange(1, len(coeffs) + 1, dtype=F64) @ coeffs)


def simulate_outside(effects: list[OutsideEffect], cfg: SimConfig | None = None) -> Campaign:
    """Simulate a campaign with ``effects`` (module docstring); ``cfg`` gives everything else.

    ``cfg.effects`` is ignored (the effects here are formulas). For static poses ``cfg.test_poses``
    test poses are drawn among all ``cfg.poses + cfg.test_poses`` in time order.
    """
    cfg = replace(cfg or SimConfig(), effects=[])
    g = torch.Generator().manual_seed(int(cfg.seed))
    nominal, robot, T, tracker_in_base, lever_nominal = _true_robot(cfg, g, [(e.form, e.joint) for e in effects])
    scene = Scene(nominal, tracker_in_base, lever_nominal, cfg.sight)
    q, t, train_idx, test_idx = _outside_poses(cfg, scene, g)
    duration = float(t[-1] - t[0]) if len(t) > 1 else 1.0
    temperature = 20.0 + torch.randn(len(t), generator=g, dtype=F64) * 0.02

    with torch.no_grad():
        p0 = tf.transform_points(T, robot.probe_in_base(q))
    dq = torch.zeros_like(q)
    dp = torch.zeros_like(p0)
    truth_effects = []
    for e in effects:
        if e.form in ("harmonic", "polynomial", "joint_time"):
            term, rec = _joint_effect(
                e, q, (t - t[0]) / duration, lambda dq1: tf.transform_points(T, robot.probe_in_base(q + dq1)) - p0, g
            )
            dq[:, e.joint - 1] += term
        else:
            shift, rec = _warmup_effect(e, t, g)
            dp += shift
        truth_effects.append(rec)

    with torch.no_grad():
        p_true = tf.transform_points(T, robot.probe_in_base(q + dq)) + dp
    for rec, e in zip(truth_effects, effects):
        rec["rms_m"] = e.size  # by construction (joint effects: to first order in the amplitude)
    total = (p_true - p0).norm(dim=-1)
    part = _measured(cfg, g, q, p_true, t, temperature, "torchcal.sim.outside", nominal.limits)

    truth = {
        "generator": "torchcal.sim.outside",
        "config": _config_dict(cfg),
        **_set_up_truth(robot, cfg.robot, T, tracker_in_base),
        "noise": {"tracker_sigma_m": cfg.sigma_tracker, "joint_sigma_rad": math.radians(cfg.sigma_joint_deg)},
        "effects": truth_effects,
        "effects_total_rms_m": float(total.square().mean().sqrt()),
        "duration_s": duration,
        "outside_effects": [asdict(e) for e in effects],
        "files": {"train": {"n": len(train_idx)}, "test": {"n": len(test_idx)}},
    }
    model = MeasurementModel(robot, [])
    return Campaign(train=part(train_idx, "train"), test=part(test_idx, "test"), truth=truth, model=model, q_true=q)


def _outside_poses(cfg: SimConfig, scene: Scene, g: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The campaign's joints ``(N, dof)``, times ``(N,)`` [s] and training / test indices: a trajectory split in
    time, or random poses with ``cfg.test_poses`` drawn among them."""
    if cfg.trajectory:
        q = trajectory(scene, cfg.samples, g)
        t = torch.arange(len(q), dtype=F64) * cfg.sample_interval_s
        return q, t, torch.arange(cfg.train_samples), torch.arange(cfg.train_samples, len(q))
    n = cfg.poses + cfg.test_poses
    q = random_poses(scene, n, g)
    t = (
        torch.arange(n, dtype=F64) * cfg.pose_interval_s
        + torch.rand(n, generator=g, dtype=F64) * 0.5 * cfg.pose_interval_s
    )
    perm = torch.randperm(n, generator=g)
    return q, t, torch.sort(perm[cfg.test_poses :]).values, torch.sort(perm[: cfg.test_poses]).values


def _joint_effect(e: OutsideEffect, q: Tensor, s: Tensor, displacement, g: torch.Generator) -> tuple[Tensor, dict]:
    """A joint effect's term added to joint ``e.joint`` ``(N,)`` [rad], scaled so that the probe's displacement has
    RMS ``e.size`` (``displacement``: a joint change ``(N, dof)`` -> the probe's displacement ``(N, 3)``; ``s`` the
    time from 0 to 1), and its truth record."""
    rec = {"form": e.form, "size_m": e.size}
    phase = float(torch.rand(1, generator=g, dtype=F64)) * 2 * math.pi if e.phase is None else float(e.phase)
    coeffs = torch.as_tensor(e.coeffs if e.coeffs is not None else (1.0,), dtype=F64)
    shape = _joint_term(e, q, 1.0, phase, coeffs, s)
    with torch.no_grad():
        dq1 = torch.zeros_like(q)
        dq1[:, e.joint - 1] = shape
        disp = displacement(dq1)
    amp = e.size / float(disp.norm(dim=-1).square().mean().sqrt())
    rec.update(joint=e.joint, variable=f"q{e.joint}" if e.form != "joint_time" else f"q{e.joint}_t")
    if e.form == "joint_time":
        rec.update(order=e.order or 0, amplitude_rad_at_end=amp, phase=phase, variables=[f"q{e.joint}", "t"])
    elif e.form == "harmonic":
        rec.update(
            order=e.order, amplitude_rad=amp, phase=phase, a_sin=amp * math.cos(phase), b_cos=amp * math.sin(phase)
        )
    else:
        rec.update(degree=len(coeffs), coeffs=(amp * coeffs).tolist())
    return amp * shape, rec


def _warmup_effect(e: OutsideEffect, t: Tensor, g: torch.Generator) -> tuple[Tensor, dict]:
    """A warm-up drift of the measured points ``(N, 3)`` [m] along an axis of the tracker, RMS ``e.size``, and its
    truth record."""
    if isinstance(e.axis, str):
        if e.axis != "horizontal":
            raise OptionError(f"warmup axis '{e.axis}' is not 'horizontal', an index or a vector")
        ang = float(torch.rand(1, generator=g, dtype=F64)) * 2 * math.pi
        u = torch.tensor([math.cos(ang), math.sin(ang), 0.0], dtype=F64)
    elif isinstance(e.axis, int):
        u = torch.zeros(3, dtype=F64)
        u[e.axis] = 1.0
    else:
        u = torch.as_tensor(e.axis, dtype=F64)
        u = u / u.norm()
    tau = float(e.tau) if e.tau is not None else 60.0 * (5 + 55 * float(torch.rand(1, generator=g, dtype=F64)))
    shape = -torch.expm1(-(t - t[0]) / tau)
    amp = e.size / float(shape.square().mean().sqrt())
    rec = {"form": e.form, "size_m": e.size}
    rec.update(variable="t", axis_tracker=u.tolist(), amplitude_m=amp, tau_s=tau, t0_s=float(t[0]))
    return amp * shape[:, None] * u, rec


@dataclass
class OutsideTrajectory:
    """A trajectory campaign of :func:`simulate_outside_trajectory` (module docstring).

    Attributes:
        robot: robot spec (a name of ``robots/`` or a file).
        samples: samples of the whole path (training and continuation).
        train_fraction: share of the samples, from the start, that train; the rest is the continuation.
        seed: seeds everything (geometry, tracker, path, field, noise).
        field: one of :data:`FIELD_KINDS`, or ``"none"``.
        width: tanh hidden units, Fourier features, product pairs (``additive``: sines per joint).
        size: RMS over all samples of the field's displacement at the probe [m].
        length_scale: joint-space length scale of the ``fourier`` features [rad].
        sines: least and most sines per joint.
        span: share of the room around the centre (to the nearer limit) the amplitudes of a joint sum to.
        periods: shortest and longest period [samples] of the sines; None: ``samples / 8`` to ``1.5 samples``.
        dt: sampling interval [s].
        sigma_tracker: tracker noise per axis [m].
        sigma_joint: joint reading noise [rad].
    """

    robot: str = "ur5"
    samples: int = 7342
    train_fraction: float = 0.8
    seed: int = 0
    field: str = "tanh"
    width: int = 29
    size: float = 1e-4
    length_scale: float = 1.5
    sines: tuple[int, int] = (3, 5)
    span: float = 0.85
    periods: tuple[float, float] | None = None
    dt: float = 4.0
    sigma_tracker: float = 15e-6
    sigma_joint: float = 9e-6

    def __post_init__(self):
        if self.field not in (*FIELD_KINDS, "none"):
            raise OptionError(f"outside trajectory field '{self.field}' is not one of {(*FIELD_KINDS, 'none')}")
        if self.samples < 10 or not 0.0 < self.train_fraction < 1.0:
            raise OptionError(
                f"need samples >= 10 and train_fraction in (0, 1), got {self.samples} and {self.train_fraction}"
            )
        if not (1 <= self.sines[0] <= self.sines[1]):
            raise OptionError(f"sines must be (least, most) with 1 <= least <= most, got {self.sines}")
        if self.periods is not None and not 0 < self.periods[0] <= self.periods[1]:
            raise OptionError(f"periods must be (shortest, longest) with 0 < shortest <= longest, got {self.periods}")
        if not 0.0 < self.span <= 1.0 or self.width < 1 or not self.size > 0 or not self.dt > 0:
            raise OptionError(
                f"need span in (0, 1], width >= 1, size > 0 and dt > 0, got {self.span}, {self.width}, "
                f"{self.size}, {self.dt}"
            )

    @property
    def train_samples(self) -> int:
        """Samples of the training part (the first ones), at least 1 and leaving at least 1 to the continuation."""
        return min(max(1, round(self.train_fraction * self.samples)), self.samples - 1)


def multisine_joints(
    lo: Tensor,
    hi: Tensor,
    n: int,
    sines: tuple[int, int],
    span: float,
    g: torch.Generator,
    periods: tuple[float, float] | None = None,
) -> tuple[Tensor, dict]:
    """A multi-sine path ``(n, dof)`` [rad] inside the box ``lo, hi`` ``(dof,)`` [rad], and what defines it.

    Each joint: a centre drawn in the middle half of its box, plus 3-5 (``sines``) sines with periods drawn
    log-uniformly in ``periods`` [samples] (default ``n / 8`` to ``1.5 n``; incommensurate almost surely), random
    phases and Dirichlet amplitude shares that sum to ``span`` of the room from the centre to the nearer limit, so
    the path stays inside the box and reaches most of it.

    Returns:
        ``q (n, dof)`` and a dict of the centres, periods [samples], phases and amplitudes [rad] (lists).
    """
    dof = len(lo)
    mid, half = 0.5 * (hi + lo), 0.5 * (hi - lo)
    centre = mid + half * 0.5 * (2 * torch.rand(dof, generator=g, dtype=F64) - 1)
    room = torch.minimum(hi - centre, centre - lo)
    p_lo, p_hi = periods if periods is not None else (n / 8, 1.5 * n)
    k = torch.arange(n, dtype=F64)
    q = centre.expand(n, dof).clone()
    record = {"centre": centre.tolist(), "periods_samples": [], "phases": [], "amplitudes_rad": []}
    for j in range(dof):
        m = int(torch.randint(sines[0], sines[1] + 1, (1,), generator=g))
        per = torch.exp(math.log(p_lo) + math.log(p_hi / p_lo) * torch.rand(m, generator=g, dtype=F64))
        phases = 2 * math.pi * torch.rand(m, generator=g, dtype=F64)
        share = -torch.log(torch.rand(m, generator=g, dtype=F64))  # Dirichlet(1, ..., 1) after normalising
        amps = span * room[j] * share / share.sum()
        q[:, j] += (amps * torch.sin(2 * math.pi * k[:, None] / per + phases)).sum(-1)
        for key, v in zip(("periods_samples", "phases", "amplitudes_rad"), (per, phases, amps)):
            record[key].append(v.tolist())
    return q, record


def joint_field(kind: str, q: Tensor, width: int, length_scale: float, g: torch.Generator) -> tuple[Tensor, dict]:
    """A smooth displacement field ``(N, 3)`` of the joints ``q (N, dof)`` [rad], of unit RMS, and its formula.

    Kinds (:data:`FIELD_KINDS`): ``tanh`` ``W2 tanh(W1 q + b1)`` with ``width`` hidden units (``W1`` of standard
    deviation ``1.5 / sqrt(dof)``, ``b1`` of 0.5); ``fourier`` ``A cos(Omega q + phi)`` with ``width`` features of
    frequencies ``N(0, 1 / length_scale^2)``; ``product`` ``sum_p a_p sin(k q_i + phi) sin(l q_j + psi)`` over
    ``width`` random pairs ``i < j``, orders 1-2; ``additive`` ``sum_j sum_m a_jm sin(k_jm q_j + phi_jm)`` with
    ``width`` terms per joint, orders 1-3. The amplitudes are Gaussian 3-vectors; the field is scaled to unit
    RMS of its norm over ``q``.

    Returns:
        ``d (N, 3)`` and a dict of the drawn parameters (lists), with ``scale`` the factor applied.
    """
    n, dof = q.shape
    rnd = lambda *shape: torch.randn(*shape, generator=g, dtype=F64)  # noqa: E731
    uni = lambda *shape: torch.rand(*shape, generator=g, dtype=F64)  # noqa: E731
    if kind == "tanh":
        w1, b1, w2 = rnd(width, dof) * 1.5 / math.sqrt(dof), rnd(width) * 0.5, rnd(3, width)
        d = torch.tanh(q @ w1.T + b1) @ w2.T
        params = {"w1": w1, "b1": b1, "w2": w2}
    elif kind == "fourier":
        om, ph, a = rnd(width, dof) / length_scale, 2 * math.pi * uni(width), rnd(width, 3)
        d = torch.cos(q @ om.T + ph) @ a
        params = {"omega": om, "phase": ph, "a": a}
    elif kind == "product":
        pairs = torch.stack([torch.randperm(dof, generator=g)[:2].sort().values for _ in range(width)])
        orders = torch.randint(1, 3, (width, 2), generator=g).to(F64)
        ph, a = 2 * math.pi * uni(width, 2), rnd(width, 3)
        s = torch.sin(orders * q[:, pairs] + ph)  # (N, width, 2)
        d = (s[..., 0] * s[..., 1]) @ a
        params = {"pairs": pairs, "orders": orders, "phase": ph, "a": a}
    elif kind == "additive":
        orders = torch.randint(1, 4, (dof, width), generator=g).to(F64)
        ph, a = 2 * math.pi * uni(dof, width), rnd(dof, width, 3)
        d = torch.einsum("njm,jmc->nc", torch.sin(orders * q[:, :, None] + ph), a)
        params = {"orders": orders, "phase": ph, "a": a}
    else:
        raise OptionError(f"field kind '{kind}' is not one of {FIELD_KINDS}")
    scale = 1.0 / float(d.norm(dim=-1).square().mean().sqrt())
    return d * scale, {"kind": kind, "scale": scale, **{k: v.tolist() for k, v in params.items()}}


def simulate_outside_trajectory(spec: OutsideTrajectory | None = None) -> Campaign:
    """Simulate a trajectory campaign of ``spec`` (module docstring, :class:`OutsideTrajectory`).

    The field moves the probe in the robot's base frame, as a function of the commanded (true) joints; the
    readings carry joint noise, the tracker positions tracker noise, and the files no ``sx, sy, sz`` (as the
    outside campaigns).

    Returns:
        A :class:`~torchcal.sim.campaign.Campaign`: ``train`` the first ``spec.train_samples`` samples, ``test``
        their continuation, ``truth`` the geometry, path and field formula, ``model`` the true geometry without
        the field.
    """
    spec = spec or OutsideTrajectory()
    g = torch.Generator().manual_seed(int(spec.seed))
    cfg = SimConfig(robot=spec.robot, seed=spec.seed)
    _, robot, T, tracker_in_base, _ = _true_robot(cfg, g, [])
    lo = robot.limits[:, 0].clamp(min=-math.pi)
    hi = robot.limits[:, 1].clamp(max=math.pi)
    q, path_record = multisine_joints(lo, hi, spec.samples, spec.sines, spec.span, g, spec.periods)
    t = torch.arange(spec.samples, dtype=F64) * spec.dt
    with torch.no_grad():
        p_base = robot.probe_in_base(q)
    field_record: dict = {"kind": "none"}
    if spec.field != "none":
        d, field_record = joint_field(spec.field, q, spec.width, spec.length_scale, g)
        p_base = p_base + spec.size * d
        field_record.update(rms_m=spec.size, width=spec.width)
    p_true = tf.transform_points(T, p_base)
    p_meas = p_true + torch.randn(p_true.shape, generator=g, dtype=F64) * spec.sigma_tracker
    q_read = q + torch.randn(q.shape, generator=g, dtype=F64) * spec.sigma_joint
    q_read = torch.minimum(torch.maximum(q_read, robot.limits[:, 0]), robot.limits[:, 1])  # as campaign._measured
    n_train = spec.train_samples
    meta = {"simulated": "torchcal.sim.outside trajectory", "robot": str(spec.robot), "seed": str(spec.seed)}

    def part(rows: slice, name: str) -> Measurements:
        return Measurements(
            q=q_read[rows].clone(), p=p_meas[rows].clone(), t=t[rows].clone(), meta={**meta, "part": name}
        )

    truth = {
        "generator": "torchcal.sim.outside trajectory",
        "spec": asdict(spec),
        **_set_up_truth(robot, spec.robot, T, tracker_in_base),
        "noise": {"tracker_sigma_m": spec.sigma_tracker, "joint_sigma_rad": spec.sigma_joint},
        "path": path_record,
        "field": field_record,
        "files": {
            "train": {"n": n_train},
            "test": {"n": spec.samples - n_train},
            "split": "time-ordered: the first train_samples train, their continuation is the test",
        },
    }
    return Campaign(
        train=part(slice(0, n_train), "train"),
        test=part(slice(n_train, None), "test"),
        truth=truth,
        model=MeasurementModel(robot, []),
        q_true=q,
    )


__all__ = [
    "FIELD_KINDS",
    "FORMS",
    "OutsideEffect",
    "OutsideTrajectory",
    "joint_field",
    "multisine_joints",
    "simulate_outside",
    "simulate_outside_trajectory",
]


def _set_up_truth(robot, spec, T: Tensor, tracker_in_base: Tensor) -> dict:
    """The parts of ``truth.json`` that describe the set-up: the robot, its true geometry, the tracker's pose and
    the lever arm."""
    geo = robot.geometry
    return {
        "robot": {"spec": str(spec), "name": robot.name, "dof": robot.dof},
        "geometry": {
            "parametrisation": type(geo).__name__,
            "columns": list(geo.COLUMNS),
            "names": list(geo.names),
            "delta": geo.delta.detach().flatten().tolist(),
        },
        "instrument": {"T_tracker_base": T.tolist(), "tracker_in_base_m": tracker_in_base.tolist()},
        "tool": {"t_flange_probe": robot.tool.nominal.tolist()},
    }
