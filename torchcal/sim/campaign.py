"""Simulated laser-tracker campaigns: biased geometry, unknown tracker pose and lever arm,
tracker and joint noise, and non-geometric effects of a chosen size.

The settings follow Horvath & Neuner (2024), Sec. 2.2 and 3.1: DH biases of sigma 0.1 mm
for lengths and 0.01 deg for angles, a tracker noise of 15 um per axis, joint noise of
0.0005 deg (about 1.5e-5 m at the probe), a smooth non-geometric field from a random
6-29-3 tanh network, 7342 trajectory samples of which the first 5874 train. A prismatic joint's reading
gets the joint noise's number in metres (8.7 um at the default, a linear encoder's), and its DH ``d`` bias
is its zero offset.

Effect size: every injected effect is scaled so that the root-mean-square displacement it
causes at the probe, over all simulated poses, equals the requested size (the field's
peak-to-peak variation of |correction| is reported in truth.json too, as the paper quotes it).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from torchcal._bounds import MAX_SIGMA_ANGLE, MAX_SIGMA_JOINT, MAX_SIGMA_LENGTH, MAX_SIGMA_TRACKER, check_range
from torchcal.data import Measurements, write_measurements
from torchcal.effects import (
    Backlash,
    Compliance,
    Context,
    CorrectionNet,
    Coupling,
    Cyclic,
    Drift,
    LearnedEffect,
    LumpedCompliance,
    TrackerError,
)
from torchcal.effects.base import Effect, motion_direction
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.robot import load_robot
from torchcal.robot import transforms as tf
from torchcal.robot.model import RobotModel
from torchcal.sim.load import check_load_config, has_load, load_columns, measured_torques, row_payloads, true_masses
from torchcal.sim.poses import PATHS, Scene, SightRule, fixed_axis_poses, narrow_poses, path, random_poses

Tensor = torch.Tensor
F64 = torch.float64

#: default sizes (RMS probe displacement, m) when an effect spec gives none
DEFAULT_SIZES = {
    "compliance": 5e-5,
    "backlash": 3e-5,
    "cyclic": 3e-5,
    "drift": 5e-5,
    "field": 1.5e-4,
    "coupling": 5e-5,
    # the instrument's own errors (torchcal.effects.instrument): an azimuth or elevation encoder harmonic of order H,
    # a range offset, a range scale, a tilt of the trunnion axis or of the beam, the beam's offset
    "tracker_az": 2e-5,
    "tracker_el": 2e-5,
    "range_offset": 2e-5,
    "range_scale": 2e-5,
    "axis_tilt": 2e-5,
    "beam_tilt": 2e-5,
    "beam_offset": 2e-5,
}
#: the simulated instrument terms, and the term of torchcal.effects.instrument.TrackerError each one is
INSTRUMENT_SPECS = {
    "tracker_az": "azimuth",
    "tracker_el": "elevation",
    "range_offset": "range",
    "range_scale": "range",
    "axis_tilt": "tilt",
    "beam_tilt": "tilt",
    "beam_offset": "beam",
}
#: the unit an instrument term takes its value in (the others take a length: the offset itself, or its RMS size)
_VALUE_OF = {"tracker_az": "urad", "tracker_el": "urad", "range_scale": "ppm", "axis_tilt": "urad", "beam_tilt": "urad"}
EFFECT_NAMES = tuple(DEFAULT_SIZES)
_UNITS = {"m": 1.0, "mm": 1e3, "um": 1e6}  # divisors to metres (exact for decimal input)
_VALUE_UNITS = {"urad": 1e6, "ppm": 1e6}  # divisors of an instrument term's value to rad and m/m
MASS_STREAM = 45_000_001  # offset of the seed of the true masses' generator (torchcal.sim.load.true_masses)


@dataclass
class EffectSpec:
    """One effect to inject: ``kind``, ``joint`` (1-based) or drift ``variable``, ``size`` [m RMS]; a coupling's
    ``source`` joint (1-based)."""

    kind: str
    joint: int | None = None
    variable: str | None = None
    size: float | None = None
    source: int | None = None
    k: float | None = None  # a compliance given as its physical value [rad/(N m)] instead of a size
    ratio: float | None = None  # a coupling given as its ratio c [rad/rad] instead of a size
    order: int | None = None  # an instrument encoder harmonic's order (tracker_az:H, tracker_el:H)
    amount: float | None = None  # an instrument term by its value: a harmonic's amplitude [rad], a range scale [m/m]

    @classmethod
    def _ratio(cls, text: str, kind: str, value: str) -> EffectSpec:
        """A coupling given by its ratio (a number without a unit, or ``rad/rad``)."""
        if kind != "coupling":
            if text.rstrip().endswith("rad/rad"):
                raise OptionError(
                    f"effect '{text}': only a coupling takes a ratio (rad/rad); give {kind} a size, e.g. '=50um'"
                )
            raise OptionError(f"effect '{text}': give the size with a unit, e.g. '=50um', '=0.05mm' or '=5e-5m'")
        try:
            ratio = float(value)
        except ValueError:
            raise OptionError(f"effect '{text}': the ratio '{value}' is not a number") from None
        if not (math.isfinite(ratio) and ratio != 0.0):
            raise OptionError(f"effect '{text}': the coupling's ratio must be a finite number other than 0")
        return cls(kind=kind, ratio=ratio)

    @classmethod
    def _instrument(cls, text: str, kind: str, arg: str | None, size: str | None, unit: str | None) -> EffectSpec:
        """An instrument term: ``tracker_az:H`` / ``tracker_el:H`` (an encoder harmonic of order H, its amplitude in
        urad or its size), ``range_offset`` (a size: the offset itself), ``range_scale`` (in ppm, or a size),
        ``axis_tilt`` / ``beam_tilt`` (the trunnion axis's or the beam's tilt in urad, or a size), ``beam_offset`` (a
        size: the offset itself, in a seeded direction across the beam)."""
        spec = cls(kind=kind, variable=INSTRUMENT_SPECS[kind])
        if kind in ("tracker_az", "tracker_el"):
            if arg is None or not arg.isdigit() or int(arg) < 1:
                raise OptionError(f"effect '{text}': {kind} needs a harmonic order >= 1, e.g. '{kind}:1=40urad'")
            spec.order = int(arg)
        elif arg is not None:
            raise OptionError(f"effect '{text}': {kind} takes no joint or order")
        want = _VALUE_OF.get(kind)
        if size is None:
            return spec
        if unit in _VALUE_UNITS and unit == want:
            spec.amount = float(size) / _VALUE_UNITS[unit]
            if not (math.isfinite(spec.amount) and spec.amount != 0.0):
                raise OptionError(f"effect '{text}': the value must be a finite number other than 0")
        elif unit in _UNITS:
            spec.size = float(size) / _UNITS[unit]
            if not spec.size > 0:
                raise OptionError(f"effect '{text}': size must be positive")
        else:
            units = f"{want} or " if want else ""
            raise OptionError(f"effect '{text}': give {kind} in {units}a length (its RMS displacement, e.g. '=20um')")
        return spec

    @classmethod
    def parse(cls, text: str) -> EffectSpec:
        """Parse ``KIND[:JOINT|:VARIABLE][=SIZE UNIT]``.

        Examples: ``compliance:2=50um``, ``field=0.6mm``, ``drift:temperature``, ``coupling:3<-2=50um`` (joint 3's
        reading error proportional to joint 2's reading), ``coupling:5<-4=1e-3`` (the same by its ratio, ``dq_5 = 1e-3
        q_4``; ``=1e-3rad/rad`` alike), ``compliance:2=1.5e-5rad/Nm`` (a compliance by its value, on a robot whose
        description has link masses).
        """
        m = re.fullmatch(
            r"\s*([a-z_]+)(?::([A-Za-z0-9_]+(?:<-[0-9]+)?))?(?:=\s*([0-9.eE+-]+)\s*(m|mm|um|rad/Nm|rad/rad|urad|ppm)?)?\s*",
            text,
        )
        if not m:
            if re.fullmatch(r".*=\s*[0-9.eE+-]+\s*", text):
                raise OptionError(f"effect '{text}': give the size with a unit, e.g. '=50um', '=0.05mm' or '=5e-5m'")
            raise OptionError(f"effect '{text}' is not KIND[:JOINT][=SIZE UNIT]; kinds: {', '.join(EFFECT_NAMES)}")
        kind, arg, size, unit = m.groups()
        if kind not in EFFECT_NAMES:
            raise OptionError(f"effect kind '{kind}' is not one of {', '.join(EFFECT_NAMES)}")
        if kind in INSTRUMENT_SPECS:
            return cls._instrument(text, kind, arg, size, unit)
        if unit in _VALUE_UNITS:
            raise OptionError(
                f"effect '{text}': only an instrument term takes {unit}; give {kind} a size, e.g. '=50um'"
            )
        if size is not None and unit in (None, "rad/rad"):
            spec = cls._ratio(text, kind, size)
        elif unit == "rad/Nm":
            if kind != "compliance":
                raise OptionError(f"effect '{text}': only a compliance takes rad/Nm; give {kind} a size, e.g. '=50um'")
            spec = cls(kind=kind, k=float(size))
            if not spec.k > 0:
                raise OptionError(f"effect '{text}': the compliance must be positive")
        else:
            spec = cls(kind=kind, size=None if size is None else float(size) / _UNITS[unit])
        if kind in ("compliance", "backlash", "cyclic"):
            if arg is None or not arg.isdigit():
                raise OptionError(f"effect '{text}': {kind} needs a joint number, e.g. '{kind}:2'")
            spec.joint = int(arg)
        elif kind == "coupling":
            pair = re.fullmatch(r"([0-9]+)<-([0-9]+)", arg or "")
            if pair is None or pair[1] == pair[2]:
                raise OptionError(f"effect '{text}': coupling needs two different joints, e.g. 'coupling:3<-2'")
            spec.joint, spec.source = int(pair[1]), int(pair[2])
        elif kind == "drift":
            spec.variable = arg or "t"
            if spec.variable not in Drift.VARIABLES:
                raise OptionError(f"effect '{text}': drift variable must be one of {Drift.VARIABLES}")
        elif arg is not None:
            raise OptionError(f"effect '{text}': {kind} takes no joint")
        if spec.size is not None and not spec.size > 0:
            raise OptionError(f"effect '{text}': size must be positive")
        return spec


@dataclass
class SimConfig:
    """Everything that defines a campaign; with the seed, it reproduces it exactly."""

    robot: str = "ur5"
    poses: int = 800
    test_poses: int = 200
    trajectory: bool = False
    path: str = "p2p"  # trajectory family (torchcal.sim.poses.PATHS)
    samples: int = 7342
    train_samples: int = 5874
    seed: int = 0
    sigma_tracker: float = 15e-6  # m per axis
    sigma_joint_deg: float = 0.0005
    sigma_length: float = 1e-4  # m, geometric bias
    sigma_angle_deg: float = 0.01  # geometric bias
    tracker_distance: tuple[float, float] = (2.0, 3.0)  # m from the robot base
    tracker_height: tuple[float, float] = (-0.3, 0.5)  # m relative to the base plane
    tracker_tilt_deg: float = 0.02  # levelled tracker
    lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.1)  # nominal probe offset on the flange, m
    lever_arm_sigma: float = 0.005  # m, how far the true mount is from nominal
    effects: list[EffectSpec] = field(default_factory=list)
    write_sigma: bool = True
    pose_interval_s: float = 6.0  # static poses: time per pose
    sample_interval_s: float = 0.1  # trajectories: tracker sampling interval
    sight: SightRule = field(default_factory=SightRule)
    base_link: str | None = None
    tip_link: str | None = None
    tool_axis_deg: float | None = None  # static poses whose tool axis turns by at most this [deg] (None: free)
    # errors of the readings map's ratios in the true robot (parameter name -> correction, e.g. {"readings.c3_3": 2e-3}
    # for a 0.2 % error of J3's ratio): what a `readings:` block's calibration recovers
    ratio_errors: dict[str, float] = field(default_factory=dict)
    turned_min_deg: float = 30.0  # with tool_axis_deg: the turned poses' tool axis is at least this far off [deg]
    # a 6-D probe (a T-Mac): its orientation noise per axis [deg]; the files then carry rx, ry, rz (and srx, sry, srz
    # with write_sigma) from the true model, whose probe frame is turned by a random rotation in the flange frame.
    # None: a reflector, positions only. Drawn after everything else: the positions are those of the same campaign
    # without orientation
    orientation_sigma_deg: float | None = None
    stations: int = 1  # instrument placements, each measuring an equal share of the (static) poses
    probes: int = 1  # reflectors on a nest at the flange; every pose is measured by each of them (one row each)
    nest_radius: float = 0.05  # m: the probes sit on a circle of this radius about the nominal lever arm
    # loads (torchcal.sim.load): the training rows' payload at the probe [kg], the test rows' (None: the same), or
    # levels both cycle over; measured joint torques (tau1..tauN) from the true static model plus noise [N m]
    payload: float = 0.0
    test_payload: float | None = None
    payload_levels: tuple[float, ...] | None = None
    torques: bool = False
    sigma_torque: float = 0.5
    # a narrow campaign: these joints (1-based, revolute) of the training poses stay within a band of
    # narrow_width_deg about one pose's while the others range; the test poses range over the whole workspace
    narrow: tuple[int, ...] = ()
    narrow_width_deg: float = 1.0

    def __post_init__(self):
        if self.poses < 1 or self.test_poses < 0:
            raise OptionError(f"poses must be >= 1 and test_poses >= 0, got {self.poses} and {self.test_poses}")
        if self.path not in PATHS:
            raise OptionError(f"trajectory path '{self.path}' is not one of {', '.join(PATHS)}")
        if self.trajectory and not 0 < self.train_samples < self.samples:
            raise OptionError(f"train_samples must lie in (0, samples={self.samples}), got {self.train_samples}")
        check_range("sigma_tracker", self.sigma_tracker, 0.0, MAX_SIGMA_TRACKER, scale=1e6, unit="um")
        check_range("sigma_joint_deg", self.sigma_joint_deg, 0.0, math.degrees(MAX_SIGMA_JOINT), unit="deg")
        check_range("sigma_length", self.sigma_length, 0.0, MAX_SIGMA_LENGTH, scale=1e3, unit="mm")
        check_range("sigma_angle_deg", self.sigma_angle_deg, 0.0, math.degrees(MAX_SIGMA_ANGLE), unit="deg")
        if self.stations < 1 or self.probes < 1:
            raise OptionError(f"stations and probes must be >= 1, got {self.stations} and {self.probes}")
        if (self.stations > 1 or self.probes > 1) and self.trajectory:
            raise OptionError("several stations or probes need static poses (no trajectory)")
        if self.probes > 1 and self.tool_axis_deg is not None:
            raise OptionError("a fixed tool axis takes one probe (several stations are fine)")
        if self.stations > 1 and self.poses < 3 * self.stations:
            raise OptionError(f"{self.stations} stations need at least {3 * self.stations} poses, got {self.poses}")
        if self.tool_axis_deg is not None and (self.trajectory or not self.tool_axis_deg > 0):
            raise OptionError(f"tool_axis_deg needs static poses and a positive angle, got {self.tool_axis_deg}")
        if self.orientation_sigma_deg is not None:
            check_range("orientation_sigma_deg", self.orientation_sigma_deg, 0.0, 5.0, unit="deg")
        check_load_config(self)
        if self.narrow:
            self._check_narrow()

    def _check_narrow(self) -> None:
        self.narrow = tuple(int(j) for j in self.narrow)
        if len(set(self.narrow)) != len(self.narrow) or min(self.narrow) < 1:
            raise OptionError(f"narrow joints must be distinct 1-based joint numbers, got {list(self.narrow)}")
        if not 0 < self.narrow_width_deg <= 360:
            raise OptionError(f"narrow_width_deg must lie in (0, 360], got {self.narrow_width_deg}")
        if self.trajectory or self.stations > 1 or self.probes > 1 or self.tool_axis_deg is not None:
            raise OptionError("a narrow campaign takes static poses of one station and probe, no fixed tool axis")


@dataclass
class Campaign:
    train: Measurements
    test: Measurements
    truth: dict
    model: MeasurementModel  # the true measurement model (true geometry, instrument, lever arm, effects)
    q_true: Tensor  # (N, dof) true joint angles of train + test (+ turned)
    turned: Measurements | None = None  # with SimConfig.tool_axis_deg: poses with the tool turned away from its axis


def _bias_geometry(robot: RobotModel, cfg: SimConfig, g: torch.Generator) -> None:
    geo = robot.geometry
    cols = geo.COLUMNS
    angular = torch.tensor([c in ("alpha", "theta", "beta", "rx", "ry", "rz") for c in cols])
    sigma = torch.where(
        angular, torch.tensor(math.radians(cfg.sigma_angle_deg), dtype=F64), torch.tensor(cfg.sigma_length, dtype=F64)
    )
    with torch.no_grad():
        geo.delta.copy_(torch.randn(geo.delta.shape, generator=g, dtype=F64) * sigma * geo.mask)


def _place_tracker(cfg: SimConfig, g: torch.Generator) -> Tensor:
    """``T_tracker_base``: tracker at a random azimuth, distance and height, levelled, random heading."""
    u = torch.rand(5, generator=g, dtype=F64)
    az = 2 * math.pi * u[0]
    r = cfg.tracker_distance[0] + (cfg.tracker_distance[1] - cfg.tracker_distance[0]) * u[1]
    h = cfg.tracker_height[0] + (cfg.tracker_height[1] - cfg.tracker_height[0]) * u[2]
    pos = torch.stack([r * torch.cos(az), r * torch.sin(az), h])
    tilt = torch.randn(2, generator=g, dtype=F64) * math.radians(cfg.tracker_tilt_deg)
    heading = 2 * math.pi * u[3]
    R = tf.rot_z(heading) @ tf.rot_y(tilt[1]) @ tf.rot_x(tilt[0])
    T_base_tracker = tf.homogeneous(R, pos)
    return tf.invert(T_base_tracker)


def _make_effect(spec: EffectSpec, robot: RobotModel, g: torch.Generator, load: bool = False) -> Effect:
    if spec.kind == "compliance":
        if not robot.has_masses:
            return _lumped_truth(spec.joint, robot, g, load)
        return Compliance(spec.joint, k=1e-6)
    if spec.kind == "backlash":
        return Backlash(spec.joint, b=1e-4, source="auto")
    if spec.kind == "cyclic":
        ab = torch.randn(4, generator=g, dtype=F64) * 1e-4
        return Cyclic(spec.joint, harmonics=(1, 2), a=ab[:2], b=ab[2:])
    if spec.kind == "coupling":
        return Coupling(spec.joint, spec.source, c=1e-3)
    if spec.kind in INSTRUMENT_SPECS:
        return _instrument_truth(spec, g)
    if spec.kind == "drift":
        if spec.variable == "t":
            return Drift("t", "instrument", rates=torch.randn(6, generator=g, dtype=F64) * 1e-8)
        return Drift("temperature", "scale", rates=[2.3e-5])
    net = CorrectionNet(robot.dof, 29)
    net.reset_parameters(g, gain=2.0)
    return LearnedEffect(net)


def _instrument_truth(spec: EffectSpec, g: torch.Generator) -> TrackerError:
    """An instrument term (:data:`INSTRUMENT_SPECS`) at its value, or at 1e-5 to be scaled to its size; a harmonic's
    phase is drawn from ``g``."""
    if spec.kind == "range_offset":
        return TrackerError("range", c=[1e-5, 0.0])
    if spec.kind == "range_scale":
        return TrackerError("range", c=[0.0, spec.amount if spec.amount is not None else 1e-5])
    if spec.kind in ("axis_tilt", "beam_tilt"):
        amp = spec.amount if spec.amount is not None else 1e-5
        return TrackerError("tilt", t=[amp, 0.0] if spec.kind == "axis_tilt" else [0.0, amp])
    if spec.kind == "beam_offset":  # the offset itself (scaled to the size), across the beam in a seeded direction
        phase = 2 * math.pi * float(torch.rand(1, generator=g, dtype=F64))
        return TrackerError("beam", e=[1e-5 * math.cos(phase), 1e-5 * math.sin(phase)])
    amp = spec.amount if spec.amount is not None else 1e-5
    phase = 2 * math.pi * float(torch.rand(1, generator=g, dtype=F64))
    return TrackerError(spec.variable, (spec.order,), a=[amp * math.cos(phase)], b=[amp * math.sin(phase)])


def _lumped_truth(joint: int, robot: RobotModel, g: torch.Generator, load: bool = False) -> LumpedCompliance:
    """A compliance of a robot without masses: seeded link masses (1 to 5 kg) and centres of mass (0.1 m per axis
    in each link's frame) over a stiffness of 1e6 N m/rad, as the lumped form's full set of moments (identity
    basis; the simulation scales it to the requested size); with ``load`` the rows' payload twists the joint through
    the same stiffness (scaled with the moments)."""
    m = 1.0 + 4.0 * torch.rand(robot.dof, generator=g, dtype=F64)
    c = torch.randn(robot.dof, 3, generator=g, dtype=F64) * 0.1
    moments = torch.cat([m[:, None], m[:, None] * c], dim=1).reshape(-1)
    basis = torch.eye(4 * robot.dof, dtype=F64)
    return LumpedCompliance(joint, basis, mode=moments * 1e-6, load=load, k=1e-6 if load else 0.0)


def _rms_displacement(model: MeasurementModel, effect: Effect, ctx: Context) -> Tensor:
    """Per-pose displacement of the probe (tracker frame) that ``effect`` alone causes ``(N, 3)``."""
    with torch.no_grad():
        alone = MeasurementModel(model.robot, [effect])
        return alone(ctx) - MeasurementModel(model.robot, [])(ctx)


def _true_robot(
    cfg: SimConfig, g: torch.Generator, effects: list[tuple[str, int | None]]
) -> tuple[RobotModel, RobotModel, Tensor, Tensor, Tensor]:
    """The nominal robot and the true one (biased geometry, a placed tracker, a drawn lever arm), from ``g``.

    ``effects`` are (name, joint or None) of the effects to simulate; a joint outside the robot is an error.

    Returns:
        nominal, truth, ``T_tracker_base`` (4, 4), the tracker's position in the base frame (3,) [m] and the
        nominal lever arm (3,) [m].
    """
    nominal = load_robot(cfg.robot, base_link=cfg.base_link, tip_link=cfg.tip_link)
    truth = load_robot(cfg.robot, base_link=cfg.base_link, tip_link=cfg.tip_link)
    for name, joint in effects:
        if joint is not None and not 1 <= joint <= nominal.dof:
            raise OptionError(f"effect {name}: joint {joint} is outside 1..{nominal.dof} of '{nominal.name}'")
        if name == "cyclic" and nominal.joint_types[joint - 1] == "prismatic":
            raise OptionError(
                f"effect cyclic: joint {joint} of '{nominal.name}' is prismatic; its reading [m] has no turn for "
                "harmonics of the angle to repeat over"
            )
    _bias_geometry(truth, cfg, g)
    T_tracker_base = _place_tracker(cfg, g)
    lever = torch.tensor(cfg.lever_arm, dtype=F64) + torch.randn(3, generator=g, dtype=F64) * cfg.lever_arm_sigma
    with torch.no_grad():
        truth.instrument.set_matrix(T_tracker_base)
        truth.tool.nominal.copy_(lever)
    free = {i.name: i.index for i in truth.parameter_info() if i.group == "readings"}
    for name, value in cfg.ratio_errors.items():
        if name not in free:
            raise OptionError(
                f"ratio error '{name}': not a calibratable ratio of '{truth.name}'s readings map; "
                f"ratios: {', '.join(free) or 'none (the robot declares no readings: block)'}"
            )
        with torch.no_grad():
            truth.readings.delta[free[name]] = float(value)
    return nominal, truth, T_tracker_base, tf.invert(T_tracker_base)[:3, 3], torch.tensor(cfg.lever_arm, dtype=F64)


def _measured(
    cfg: SimConfig,
    g: torch.Generator,
    q_true: Tensor,
    p_true: Tensor,
    t: Tensor,
    temperature: Tensor,
    generator: str,
    limits: Tensor,
) -> Callable[[Tensor | slice, str], Measurements]:
    """Tracker noise on ``p_true`` (N, 3) [m], then joint noise on ``q_true`` (N, dof) [rad], drawn from ``g`` in
    this order; returns ``part(rows, name)``, the measurements of those rows (``meta`` names ``generator``).

    The readings stay within ``limits`` (dof, 2): a controller reports no angle past its limits, and a pose planned
    at a limit would otherwise read a few micro-radians past it, which calibrate rightly refuses."""
    noise_p = torch.randn(p_true.shape, generator=g, dtype=F64) * cfg.sigma_tracker
    q_read = q_true + torch.randn(q_true.shape, generator=g, dtype=F64) * math.radians(cfg.sigma_joint_deg)
    q_read = torch.minimum(torch.maximum(q_read, limits[:, 0].to(F64)), limits[:, 1].to(F64))
    p_meas = p_true + noise_p
    sigma = torch.full_like(p_meas, cfg.sigma_tracker) if cfg.write_sigma and cfg.sigma_tracker > 0 else None

    def part(rows: Tensor | slice, name: str) -> Measurements:
        return Measurements(
            q=q_read[rows].clone(),
            p=p_meas[rows].clone(),
            t=t[rows].clone(),
            temperature=temperature[rows].clone(),
            sigma=None if sigma is None else sigma[rows].clone(),
            meta={"simulated": generator, "robot": str(cfg.robot), "seed": str(cfg.seed), "part": name},
        )

    return part


def _poses_and_times(
    cfg: SimConfig,
    nominal: RobotModel,
    tracker_in_base: Tensor,
    lever_nominal: Tensor,
    g: torch.Generator,
    truth: RobotModel | None = None,
) -> tuple[Context, int]:
    """The true joints, times [s] and temperatures [degC] of every pose (training first), and the training count.

    The poses are planned with the nominal model, as a robot program would be; a fixed tool axis
    (``cfg.tool_axis_deg``) is that of the true robot ``truth``.
    """
    scene = Scene(nominal, tracker_in_base, lever_nominal, cfg.sight)
    if cfg.trajectory:
        q_true = path(cfg.path, scene, cfg.samples, g)
        n_train = cfg.train_samples
        t = torch.arange(len(q_true), dtype=F64) * cfg.sample_interval_s
    else:
        if cfg.tool_axis_deg is not None:
            axis = tool_axis(tracker_in_base)
            # the axis is the true robot's: a lifting column or a levelled tool mount holds it, not the program
            true_scene = Scene(truth, tracker_in_base, lever_nominal, cfg.sight)
            fixed = fixed_axis_poses(true_scene, cfg.poses + cfg.test_poses, g, axis, cfg.tool_axis_deg)
            q_true = torch.cat([fixed, turned_poses(scene, cfg, tracker_in_base, g)])
        elif cfg.narrow:
            q_true = _narrow(cfg, scene, nominal, g)
        else:
            q_true = random_poses(scene, cfg.poses + cfg.test_poses, g)
        n_train = cfg.poses
        jitter = torch.rand(len(q_true), generator=g, dtype=F64) * 0.5 * cfg.pose_interval_s
        t = torch.arange(len(q_true), dtype=F64) * cfg.pose_interval_s + jitter
    duration = float(t[-1]) if len(t) > 1 else 1.0
    temperature = (
        20.0 + 1.0 * (1.0 - torch.exp(-t / (0.5 * duration))) + torch.randn(len(t), generator=g, dtype=F64) * 0.02
    )
    direction = motion_direction(q_true) if cfg.trajectory else None
    return Context(q=q_true, t=t, temperature=temperature, direction=direction), n_train


def _narrow(cfg: SimConfig, scene: Scene, nominal: RobotModel, g: torch.Generator) -> Tensor:
    """A narrow campaign's poses: ``cfg.poses`` training poses with ``cfg.narrow`` in their band, then
    ``cfg.test_poses`` over the whole workspace."""
    for j in cfg.narrow:
        if j > nominal.dof:
            raise OptionError(f"narrow joint {j} is outside 1..{nominal.dof} of '{nominal.name}'")
        if nominal.joint_types[j - 1] == "prismatic":
            raise OptionError(f"narrow joint {j} of '{nominal.name}' is prismatic; a band in degrees needs a turn")
    joints = tuple(j - 1 for j in cfg.narrow)
    train = narrow_poses(scene, cfg.poses, g, joints, math.radians(cfg.narrow_width_deg))
    return torch.cat([train, random_poses(scene, cfg.test_poses, g)]) if cfg.test_poses else train


def _narrow_truth(cfg: SimConfig, q_true: Tensor, n_train: int) -> dict:
    """truth.json's ``narrow``: the held joints, the band's width and each joint's training range [deg]."""
    q = torch.rad2deg(q_true[:n_train])
    return {
        "joints": list(cfg.narrow),
        "width_deg": cfg.narrow_width_deg,
        "train_range_deg": [[float(a), float(b)] for a, b in zip(q.min(0).values, q.max(0).values)],
    }


def tool_axis(tracker_in_base: Tensor) -> Tensor:
    """The tool axis of a fixed-axis campaign ``(3,)``: horizontal, from the robot's base towards the tracker (the
    probe faces the instrument, as a prism on a lifting-column robot faces its total station)."""
    a = tracker_in_base.clone()
    a[2] = 0.0
    return a / a.norm()


def turned_poses(scene: Scene, cfg: SimConfig, tracker_in_base: Tensor, g: torch.Generator) -> Tensor:
    """``cfg.test_poses`` random poses the tracker sees whose tool axis is at least ``cfg.turned_min_deg`` away from
    the fixed-axis campaign's (:func:`tool_axis`): where a lever arm along the tool axis shows."""
    a = tool_axis(tracker_in_base)
    got, count = [], 0
    for _ in range(200):
        q = random_poses(scene, max(cfg.test_poses, 64), g)
        with torch.no_grad():
            cos = scene.robot(q)[:, :3, 2] @ a
        keep = q[cos <= math.cos(math.radians(cfg.turned_min_deg))]
        got.append(keep)
        count += len(keep)
        if count >= cfg.test_poses:
            return torch.cat(got)[: cfg.test_poses]
    raise RuntimeError(f"only {count} of {cfg.test_poses} turned poses satisfy the line-of-sight rule")


def _effects(
    cfg: SimConfig, truth_robot: RobotModel, ctx: Context, g: torch.Generator
) -> tuple[MeasurementModel, list[dict]]:
    """The true measurement model with ``cfg.effects``, each scaled to its size (RMS displacement over all poses),
    and what truth.json says of each."""
    t, temperature = ctx.t, ctx.temperature
    model = MeasurementModel(truth_robot, [])
    effect_truth = []
    for spec in cfg.effects:
        eff = _make_effect(spec, truth_robot, g, has_load(cfg))
        if isinstance(eff, Drift):
            with torch.no_grad():
                eff.reference.fill_(float((t if eff.variable == "t" else temperature)[0]))
        size = spec.size if spec.size is not None else DEFAULT_SIZES[spec.kind]
        disp = _rms_displacement(model, eff, ctx)
        rms = float(disp.norm(dim=-1).square().mean().sqrt())
        if rms == 0.0:
            raise OptionError(f"effect {spec.kind} (joint {spec.joint}) does not move the probe in these poses")
        if spec.ratio is not None:  # the coupling's ratio given: the size is what it moves
            size = rms * spec.ratio / float(eff.c.detach())
        if spec.amount is not None:  # an instrument term made at its value
            size = rms
        if spec.k is not None:  # the physical value given: the size is what it moves
            if not isinstance(eff, Compliance):
                raise OptionError(
                    f"effect compliance:{spec.joint}={spec.k:g}rad/Nm: robot '{truth_robot.name}' has no link masses; "
                    "give the compliance as a size, e.g. '=50um'"
                )
            size = rms * spec.k / float(eff.k.detach())
        eff.scale_(size / rms)  # a negative ratio's size flips the sign
        disp = _rms_displacement(model, eff, ctx)
        mag = disp.norm(dim=-1)
        if spec.k is not None or spec.ratio is not None or spec.amount is not None:  # the size is what it moves
            size = float(mag.square().mean().sqrt())
        model.add(eff)
        effect_truth.append(
            {
                "kind": "learned"
                if spec.kind == "field"
                else "instrument"
                if spec.kind in INSTRUMENT_SPECS
                else spec.kind,
                "spec": spec.kind,
                "joint": spec.joint,
                **({"source": spec.source} if spec.source is not None else {}),
                **({"order": spec.order} if spec.order is not None else {}),  # an encoder harmonic's
                "variable": spec.variable,
                "size_m": size,
                "rms_m": float(mag.square().mean().sqrt()),
                "max_m": float(mag.max()),
                "variation_m": float(mag.max() - mag.min()),
                "params": eff.describe(),
            }
        )
        if isinstance(eff, LearnedEffect):
            effect_truth[-1]["weights"] = {k: v.tolist() for k, v in eff.net.state_dict().items()}

    return model, effect_truth


def simulate(cfg: SimConfig) -> Campaign:
    """Simulate a campaign; see the module docstring for what is modelled."""
    if cfg.stations > 1 or cfg.probes > 1:
        return _simulate_stations(cfg)
    g = torch.Generator().manual_seed(int(cfg.seed))
    joints = [(spec.kind, spec.joint) for spec in cfg.effects] + [
        (spec.kind, spec.source) for spec in cfg.effects if spec.source is not None
    ]
    nominal, truth_robot, T_tracker_base, tracker_in_base, lever_nominal = _true_robot(cfg, g, joints)

    # torques need the truth's masses: drawn from a stream of their own, so that the poses and the noise are those
    # of the same campaign without torques
    masses = (
        true_masses(truth_robot, torch.Generator().manual_seed(int(cfg.seed) + MASS_STREAM)) if cfg.torques else None
    )
    ctx, n_train = _poses_and_times(cfg, nominal, tracker_in_base, lever_nominal, g, truth_robot)
    q_true, t, temperature = ctx.q, ctx.t, ctx.temperature
    # effects are sized on the arm's own weight: their truth (a compliance's k) does not depend on the test load
    model, effect_truth = _effects(cfg, truth_robot, ctx, g)
    payload = row_payloads(cfg, n_train, len(q_true)) if has_load(cfg) else None

    with torch.no_grad():
        p_true = model(dataclasses.replace(ctx, payload=payload))
    sigma_q = math.radians(cfg.sigma_joint_deg)
    part = _measured(cfg, g, q_true, p_true, t, temperature, "torchcal simulate", nominal.limits)
    n_test = n_train + cfg.test_poses if cfg.tool_axis_deg is not None else None
    train, test = part(slice(0, n_train), "train"), part(slice(n_train, n_test), "test")
    turned = part(slice(n_test, None), "turned") if n_test is not None else None
    orientation = None
    if cfg.orientation_sigma_deg is not None:
        r, sigma_r, orientation = _orientations(cfg, g, model, ctx)
        train, test = (
            _with_orientation(train, r, sigma_r, slice(0, n_train)),
            _with_orientation(test, r, sigma_r, slice(n_train, n_test)),
        )
        if turned is not None:
            turned = _with_orientation(turned, r, sigma_r, slice(n_test, None))

    if has_load(cfg):  # the torques' noise is drawn last: the campaign without torques is the same
        tau = measured_torques(truth_robot, q_true, payload, cfg.sigma_torque, g) if cfg.torques else None
        train, test, turned = _with_load(train, test, turned, payload, tau, n_train, n_test)
    truth = _truth(cfg, truth_robot, T_tracker_base, tracker_in_base, sigma_q, effect_truth, train, test)
    if orientation is not None:
        truth["orientation"] = orientation
    if cfg.narrow:
        truth["narrow"] = _narrow_truth(cfg, q_true, n_train)
    if turned is not None:
        truth["files"]["turned"] = {"n": turned.n}
        truth["tool_axis"] = _axis_spread(truth_robot, q_true, n_train, n_test, tracker_in_base)
    if has_load(cfg):
        truth["load"] = _load_truth(cfg, payload, n_train, masses)
    return Campaign(train=train, test=test, truth=truth, model=model, q_true=q_true, turned=turned)


def _truth(cfg: SimConfig, truth_robot, T_tracker_base, tracker_in_base, sigma_q, effect_truth, train, test) -> dict:
    """``truth.json`` of a one-station campaign: the configuration, the true robot, instrument, tool, noise, readings
    map and effects, and what each file holds (the orientation, tool-axis and load blocks are added by the caller)."""
    return {
        "generator": "torchcal simulate",
        "config": _config_dict(cfg),
        "robot": {
            "spec": str(cfg.robot),
            "name": truth_robot.name,
            "kind": truth_robot.kind,
            "dof": truth_robot.dof,
            "source": truth_robot.source,
        },
        "geometry": _geometry_truth(truth_robot.geometry),
        "instrument": {"T_tracker_base": T_tracker_base.tolist(), "tracker_in_base_m": tracker_in_base.tolist()},
        "tool": {"t_flange_probe": truth_robot.tool.nominal.tolist(), "nominal_lever_arm": list(cfg.lever_arm)},
        "noise": {"tracker_sigma_m": cfg.sigma_tracker, "joint_sigma_rad": sigma_q},
        **(
            {
                "readings": {
                    "coupling": truth_robot.readings.matrix().detach().tolist(),
                    "offset": truth_robot.readings.offset.tolist(),
                    "ratio_errors": dict(cfg.ratio_errors),
                }
            }
            if truth_robot.has_readings_map
            else {}
        ),
        "effects": effect_truth,
        "line_of_sight": asdict(cfg.sight),
        "files": {
            "train": {"n": train.n},
            "test": {"n": test.n},
            "split": "trajectory: first train_samples train, the rest test"
            if cfg.trajectory
            else "poses drawn independently; first `poses` train",
        },
    }


def _with_load(train, test, turned, payload, tau, n_train: int, n_test: int | None):
    """The files with their rows' load columns (payload, and the measured torques where simulated)."""

    def put(m: Measurements, rows: slice) -> Measurements:
        return dataclasses.replace(m, meta=dict(m.meta), extra={**m.extra, **load_columns(payload, tau, rows)})

    turned = None if turned is None else put(turned, slice(n_test, None))
    return put(train, slice(0, n_train)), put(test, slice(n_train, n_test)), turned


def _load_truth(cfg: SimConfig, payload: Tensor, n_train: int, masses: dict | None) -> dict:
    """truth.json's ``load``: the payloads of the files [kg], where the payload sits, the torques' noise."""
    return {
        "payload_train_kg": sorted({float(v) for v in payload[:n_train]}),
        "payload_test_kg": sorted({float(v) for v in payload[n_train:]}),
        "payload_at": "the probe (t_flange_probe)",
        "torques": {"sigma_Nm": cfg.sigma_torque, "sign": "drive torque holding the arm: -gravity torque"}
        if cfg.torques
        else None,
        "masses": masses,
    }


def _geometry_truth(geo) -> dict:
    """truth.json's ``geometry``: the parametrisation, its columns, the elements' names, true errors and values."""
    return {
        "parametrisation": type(geo).__name__,
        "columns": list(geo.COLUMNS),
        "names": list(geo.names),
        "delta": geo.delta.detach().flatten().tolist(),
        "values": (geo.values if hasattr(geo, "values") else geo.origins()).detach().tolist(),
    }


def _orientations(cfg: SimConfig, g: torch.Generator, model: MeasurementModel, ctx: Context):
    """A 6-D probe's measured orientations: the true probe frame (a random rotation in the flange frame, drawn from
    ``g``) turned by the true model, then noise ``exp(e) R`` with ``e ~ N(0, sigma^2)`` per tracker axis.

    Returns:
        ``r (N, 3)`` [rad], ``sigma_r (N, 3)`` [rad] or None (``cfg.write_sigma``), and truth.json's entry.
    """
    sigma = math.radians(float(cfg.orientation_sigma_deg))
    rotvec = torch.randn(3, generator=g, dtype=F64)
    rotvec = rotvec / rotvec.norm() * float(torch.rand(1, generator=g, dtype=F64)) * math.pi  # any probe frame
    R_fp = tf.so3_exp(rotvec)
    model.robot.enable_orientation(R_fp)
    with torch.no_grad():
        R_true = model.orientation(ctx)
        noise = torch.randn(len(R_true), 3, generator=g, dtype=F64) * sigma
        r = _rotvec(tf.so3_exp(noise) @ R_true)
    sigma_r = torch.full_like(r, sigma) if cfg.write_sigma and sigma > 0 else None
    truth = {"R_flange_probe": R_fp.tolist(), "rotvec_flange_probe": rotvec.tolist(), "sigma_rad": sigma}
    return r, sigma_r, truth


def _rotvec(R: Tensor) -> Tensor:
    from torchcal.data.ipa import matrix_to_rotvec

    return matrix_to_rotvec(R)


def _with_orientation(m: Measurements, r: Tensor, sigma_r: Tensor | None, rows: slice) -> Measurements:
    return dataclasses.replace(
        m, r=r[rows].clone(), sigma_r=None if sigma_r is None else sigma_r[rows].clone(), meta=dict(m.meta)
    )


def _simulate_stations(cfg: SimConfig) -> Campaign:
    """A campaign of ``cfg.stations`` instrument placements (each measuring an equal share of the training and of the
    test poses, planned for its own line of sight) and ``cfg.probes`` reflectors on a nest (each pose measured by
    every probe: one row per probe, the rows of a pose sharing its joints). One true robot for all; the files carry
    ``station`` (``S1``, ``S2``, ...) and ``probe`` (``P1``, ...) columns; rows run station by station, pose by pose."""
    # the steps draw from g in this order: a seed gives the same campaign
    g = torch.Generator().manual_seed(int(cfg.seed))
    joints = [(spec.kind, spec.joint) for spec in cfg.effects] + [
        (spec.kind, spec.source) for spec in cfg.effects if spec.source is not None
    ]
    nominal, truth_robot, T0, _, lever_nominal = _true_robot(cfg, g, joints)
    K, P = cfg.stations, cfg.probes
    Ts, levers = _place_stations_and_probes(cfg, g, truth_robot, T0)
    plan = _station_poses_all(cfg, g, nominal, truth_robot, Ts, lever_nominal)
    # every pose once per probe: rows (pose, probe) in pose order; a fixed axis' turned poses last
    q_true = plan.q.repeat_interleave(P, dim=0)
    station = plan.station.repeat_interleave(P)
    probe = torch.arange(P).repeat(len(plan.q))
    t, temperature = _row_times(cfg, g, len(q_true))
    ctx = Context(
        q=q_true, t=t, temperature=temperature, station=station if K > 1 else None, probe=probe if P > 1 else None
    )
    model, effect_truth = _effects(cfg, truth_robot, ctx, g)
    with torch.no_grad():
        p_true = model(ctx)
    part = _measured(cfg, g, q_true, p_true, t, temperature, "torchcal simulate", nominal.limits)
    # a 6-D probe: each row's orientation of the one probe frame, seen from the row's station
    r, sigma_r, orientation = (
        _orientations(cfg, g, model, ctx) if cfg.orientation_sigma_deg is not None else (None,) * 3
    )
    train, test, turned = _station_files(cfg, part, r, sigma_r, station, probe)
    truth = _stations_truth(cfg, truth_robot, T0, Ts, levers, effect_truth, train, test)
    if orientation is not None:
        truth["orientation"] = orientation
    if turned is not None:
        truth["files"]["turned"] = {"n": turned.n}
        names_s = tuple(f"S{k + 1}" for k in range(K))
        truth["tool_axis"] = _stations_axis_spread(
            truth_robot, q_true, station, plan.share, plan.share_test, Ts, names_s
        )
    return Campaign(train=train, test=test, truth=truth, model=model, q_true=q_true, turned=turned)


def _place_stations_and_probes(cfg: SimConfig, g: torch.Generator, truth_robot, T0: Tensor):
    """The true tracker poses ``Ts (K, 4, 4)`` (the first ``T0``, the others placed anew) and the probes' true lever
    arms ``(P, 3)`` (on a nest of ``cfg.nest_radius`` around the tool's, each off it by a little), set on
    ``truth_robot``."""
    K, P = cfg.stations, cfg.probes
    Ts = torch.stack([T0] + [_place_tracker(cfg, g) for _ in range(K - 1)])
    angles = 2 * math.pi * torch.arange(P, dtype=F64) / P
    nest = torch.stack([torch.cos(angles), torch.sin(angles), torch.zeros(P, dtype=F64)], dim=1) * cfg.nest_radius
    levers = truth_robot.tool.nominal + (nest if P > 1 else torch.zeros(1, 3, dtype=F64))
    levers = levers + torch.randn(P, 3, generator=g, dtype=F64) * (1e-4 if P > 1 else 0.0)
    truth_robot.set_stations([f"S{k + 1}" for k in range(K)] if K > 1 else None)
    truth_robot.set_probes([f"P{k + 1}" for k in range(P)] if P > 1 else None)
    with torch.no_grad():
        truth_robot.instrument.nominal.copy_(Ts if K > 1 else T0)
        truth_robot.tool.nominal.copy_(levers if P > 1 else levers[0])
    return Ts, levers


@dataclass
class _StationPoses:
    """The poses of a campaign of several stations, once each: training, test, then turned, station by station."""

    q: Tensor  # (poses, dof)
    station: Tensor  # (poses,) each pose's station
    share: list[int]  # training poses per station
    share_test: list[int]  # test poses per station


def _station_poses_all(cfg: SimConfig, g, nominal, truth_robot, Ts: Tensor, lever_nominal) -> _StationPoses:
    """Each station's equal share of the training and test poses, planned for its own line of sight."""
    K = cfg.stations
    share = [cfg.poses // K + (k < cfg.poses % K) for k in range(K)]
    share_test = [cfg.test_poses // K + (k < cfg.test_poses % K) for k in range(K)]
    q_tr, q_te, q_tu, st_tr, st_te = [], [], [], [], []
    for k in range(K):
        q, turned = _station_poses(cfg, nominal, truth_robot, tf.invert(Ts[k])[:3, 3], lever_nominal, g, share, k)
        q_tr.append(q[: share[k]])
        q_te.append(q[share[k] :])
        q_tu.append(turned)
        st_tr += [k] * share[k]
        st_te += [k] * share_test[k]
    station = torch.tensor(st_tr + st_te + (st_te if cfg.tool_axis_deg is not None else []), dtype=torch.long)
    return _StationPoses(torch.cat(q_tr + q_te + q_tu), station, share, share_test)


def _row_times(cfg: SimConfig, g: torch.Generator, n: int) -> tuple[Tensor, Tensor]:
    """The rows' times (one pose interval apart, jittered) and temperatures (a warm-up of one degree, with noise)."""
    jitter = torch.rand(n, generator=g, dtype=F64) * 0.5 * cfg.pose_interval_s
    t = torch.arange(n, dtype=F64) * cfg.pose_interval_s + jitter
    duration = float(t[-1]) if n > 1 else 1.0
    temperature = 20.0 + 1.0 * (1.0 - torch.exp(-t / (0.5 * duration))) + torch.randn(n, generator=g, dtype=F64) * 0.02
    return t, temperature


def _station_files(cfg: SimConfig, part, r, sigma_r, station: Tensor, probe: Tensor):
    """The training, test and (a fixed tool axis) turned files, with their station and probe columns."""
    K, P = cfg.stations, cfg.probes
    names_s = tuple(f"S{k + 1}" for k in range(K))
    names_p = tuple(f"P{k + 1}" for k in range(P))
    # the probes of one pose are measured at one set of joint readings: the first probe row's, shared
    first = torch.arange(len(probe)) - probe

    def labelled(rows: slice, name: str) -> Measurements:
        m = part(rows, name)
        if r is not None:
            m = _with_orientation(m, r, sigma_r, rows)
        return dataclasses.replace(
            m,
            q=part(first[rows], name).q,
            station=station[rows].clone() if K > 1 else None,
            station_names=names_s if K > 1 else (),
            probe=probe[rows].clone() if P > 1 else None,
            probe_names=names_p if P > 1 else (),
        )

    n_train = cfg.poses * P
    n_test = n_train + cfg.test_poses * P
    train, test = labelled(slice(0, n_train), "train"), labelled(slice(n_train, n_test), "test")
    turned = labelled(slice(n_test, None), "turned") if cfg.tool_axis_deg is not None else None
    return train, test, turned


def _stations_truth(cfg: SimConfig, truth_robot, T0, Ts, levers, effect_truth, train, test) -> dict:
    """truth.json of a campaign of several stations or probes (before its orientation and tool axis)."""
    names_s = tuple(f"S{k + 1}" for k in range(cfg.stations))
    names_p = tuple(f"P{k + 1}" for k in range(cfg.probes))
    return {
        "generator": "torchcal simulate",
        "config": _config_dict(cfg),
        "robot": {"spec": str(cfg.robot), "name": truth_robot.name, "kind": truth_robot.kind, "dof": truth_robot.dof},
        "geometry": _geometry_truth(truth_robot.geometry),
        "instrument": {"T_tracker_base": T0.tolist(), "tracker_in_base_m": tf.invert(T0)[:3, 3].tolist()},
        "stations": {
            name: {"T_tracker_base": Ts[k].tolist(), "tracker_in_base_m": tf.invert(Ts[k])[:3, 3].tolist()}
            for k, name in enumerate(names_s)
        },
        "tool": {"t_flange_probe": levers[0].tolist(), "nominal_lever_arm": list(cfg.lever_arm)},
        "probes": {name: {"t_flange_probe": levers[k].tolist()} for k, name in enumerate(names_p)},
        "noise": {"tracker_sigma_m": cfg.sigma_tracker, "joint_sigma_rad": math.radians(cfg.sigma_joint_deg)},
        "effects": effect_truth,
        "line_of_sight": asdict(cfg.sight),
        "files": {
            "train": {"n": train.n},
            "test": {"n": test.n},
            "split": "each station's share of poses drawn independently, the first of each train; one row per probe",
        },
    }


def _stations_axis_spread(robot, q, station, share, share_test, Ts, names) -> dict:
    """truth.json's ``tool_axis`` of a fixed-axis campaign of several stations: :func:`_axis_spread` per station (its
    rows run training, test, turned), and the largest spread and the smallest turn over all."""
    spreads = [
        _axis_spread(robot, q[station == k], share[k], share[k] + share_test[k], tf.invert(Ts[k])[:3, 3])
        for k in range(len(names))
    ]
    return {
        "per_station": dict(zip(names, spreads)),
        "max_deg_train_test": max(s["max_deg_train_test"] for s in spreads),
        "min_deg_turned": min(s["min_deg_turned"] for s in spreads),
    }


def _station_poses(
    cfg: SimConfig,
    nominal: RobotModel,
    truth: RobotModel,
    tracker_in_base: Tensor,
    lever_nominal: Tensor,
    g: torch.Generator,
    share: list[int],
    k: int,
) -> tuple[Tensor, Tensor]:
    """Station ``k``'s training and test poses ``(share[k] + its test share, dof)`` and, with a fixed tool axis, its
    turned poses (its test share; else none): each placement's own tool axis faces its own instrument
    (:func:`tool_axis`), as a construction robot's prism faces the total station of each placement."""
    K = cfg.stations
    n_test = cfg.test_poses // K + (k < cfg.test_poses % K)
    scene = Scene(nominal, tracker_in_base, lever_nominal, cfg.sight)
    if cfg.tool_axis_deg is None:
        return random_poses(scene, share[k] + n_test, g), torch.zeros(0, nominal.dof, dtype=F64)
    true_scene = Scene(truth, tracker_in_base, lever_nominal, cfg.sight)
    fixed = fixed_axis_poses(true_scene, share[k] + n_test, g, tool_axis(tracker_in_base), cfg.tool_axis_deg)
    return fixed, turned_poses(scene, dataclasses.replace(cfg, test_poses=n_test), tracker_in_base, g)


def _axis_spread(robot: RobotModel, q: Tensor, n_train: int, n_test: int, tracker_in_base: Tensor) -> dict:
    """How far the true tool axis turns from the campaign's axis [deg]: in the training and test poses, and in the
    turned poses."""
    with torch.no_grad():
        cos = (robot(q)[:, :3, 2] @ tool_axis(tracker_in_base)).clamp(-1.0, 1.0)
    deg = torch.rad2deg(torch.acos(cos))
    return {
        "axis_in_base": tool_axis(tracker_in_base).tolist(),
        "max_deg_train_test": float(deg[:n_test].max()),
        "min_deg_turned": float(deg[n_test:].min()),
        "median_deg_turned": float(deg[n_test:].median()),
    }


def _config_dict(cfg: SimConfig) -> dict:
    d = asdict(cfg)
    d["effects"] = [asdict(e) for e in cfg.effects]
    return d


def write_campaign(c: Campaign, out: str | os.PathLike) -> dict[str, Path]:
    """Write ``train.csv``, ``test.csv`` (and ``turned.csv`` of a fixed-axis campaign) and ``truth.json`` into
    ``out`` (created), all or nothing."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"train": out / "train.csv", "test": out / "test.csv", "truth": out / "truth.json"}
    write_measurements(paths["train"], c.train)
    write_measurements(paths["test"], c.test)
    if c.turned is not None:
        paths["turned"] = out / "turned.csv"
        write_measurements(paths["turned"], c.turned)
    fd, tmp = tempfile.mkstemp(dir=out, prefix=".truth.", suffix=".tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        json.dump(c.truth, f, indent=1)
        f.write("\n")
    os.replace(tmp, paths["truth"])
    return paths
