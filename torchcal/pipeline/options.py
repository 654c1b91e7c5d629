"""The options of a calibration run: one small frozen group per concern, validated in one place.

``Options`` holds the run-wide settings (method, seed, device, refit) and the groups: the held-out split
(:class:`SplitOptions`), the least-squares fits (:class:`FitSettings`, what :func:`torchcal.estimate.fit.solve`
reads), the test levels (:class:`Levels`), the closed loop (:class:`LoopOptions`), the learned stage
(:class:`LearnedOptions`), the correction network (:class:`NetworkOptions`) and the integrated method
(:class:`IntegratedOptions`). Every check runs in :meth:`Options.__post_init__`.

:data:`FLAGS` names each field once by a flat name, the one the command line's flag carries (``--max-iter`` is
``max_iter``, which is ``fit.max_iter``): :meth:`Options.of` builds options from flat names, :meth:`Options.with_flags`
changes some.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from torchcal import stats as S
from torchcal._bounds import MAX_RANK_TOL, MAX_SIGMA_JOINT, MAX_SIGMA_TRACKER, MAX_TOOL, SIGMA_JOINT, check_range
from torchcal._device import resolve_device
from torchcal._method import DEFAULT_METHOD, ENGINES, METHODS, Engine, Method
from torchcal.effects import MAX_JOINT_ERROR
from torchcal.errors import OptionError
from torchcal.estimate.identifiability import DEFAULT_TOL

Tensor = torch.Tensor
F64 = torch.float64


@dataclass(frozen=True)
class SplitOptions:
    """The held-out split and the validation splits cut from the training poses."""

    holdout: float = 0.2  # share of the poses (static) or last share of the samples (trajectory) held out
    group_tol: float = S.GROUP_TOL  # rad: rows whose joints all agree within it stay on one side of every split
    trajectory: bool | None = None  # None: decide from a monotonic t column


#: the a-priori size of a geometric change that is no manufacturing tolerance (1 mm, 0.1 deg): what the wrong-robot stop
#: counts corrections in (torchcal.pipeline.checks.MAX_PRIOR_RATIO was measured against it), and the sigma an update
#: from a prior run releases a changed element with (a crash moves a joint's zero by more than a tolerance)
PLAUSIBLE_LENGTH, PLAUSIBLE_ANGLE = 1e-3, math.radians(0.1)


@dataclass(frozen=True)
class FitSettings:
    """What every least-squares fit reads (:class:`torchcal.estimate.fit.FitOptions`): the stochastic model, the
    solver's limits and the priors (docs/methods.md, *A-priori information*)."""

    sigma_tracker: float = 15e-6  # m per axis, when the data carry no sx, sy, sz
    sigma_joint: float = SIGMA_JOINT  # rad, joint reading noise
    # rad per axis: a 6-D probe's orientation noise when the data carry no srx, sry, srz (None: 0.01 deg,
    # torchcal.estimate.fit.SIGMA_ORIENTATION); each row's orientation is weighted by it, no metres-to-radians factor
    sigma_orientation: float | None = None
    rank_tol: float = DEFAULT_TOL
    max_iter: int = 100
    stat_tol: float = 1e-2  # stop LM when a step gains less than 1 % of the variance factor
    prior_length: float | None = 1e-3  # m: a-priori sigma of the geometric length corrections (None: no prior)
    prior_angle: float | None = math.radians(0.1)  # rad: likewise for angles
    # the kinematic calibration's (the geometric stage's) priors instead: a robot's manufacturing tolerances (MAP: a
    # direction the poses barely excite, a joint that moved 1 deg, stays near nominal instead of taking up whatever
    # the rows hold; docs/narrow-campaigns.md). The later refits keep prior_length / prior_angle: under the
    # tolerance there the real Series B's default run lost 8.7 %; None: the geometric stage uses those too
    tolerance_length: float | None = 1e-4  # m
    tolerance_angle: float | None = math.radians(0.01)  # rad
    # the lever arm and the instrument pose: MAP where the data are weak, held where they add little
    prior_tool: float | None = 0.5  # m: a-priori sigma of the lever arm about the flange centre (None: no prior)
    prior_instrument: tuple[float, float] | None = (0.5, 0.1)  # m, rad: of the instrument pose about the start
    tool: tuple[float, float, float] | None = None  # m: a known lever arm (flange frame), the prior's centre
    tool_sigma: float = 1e-3  # m: the known lever arm's a-priori sigma

    def geometric(self) -> FitSettings:
        """The settings of the kinematic calibration (the geometric stage): the tolerance priors where set."""
        if self.prior_length is None or self.tolerance_length is None or self.tolerance_angle is None:
            return self
        return dataclasses.replace(self, prior_length=self.tolerance_length, prior_angle=self.tolerance_angle)

    @property
    def prior_lever(self) -> float | None:
        """The lever arm's a-priori sigma [m]: ``tool_sigma`` about a known ``tool``, else ``prior_tool``."""
        return self.tool_sigma if self.tool is not None else self.prior_tool

    def lever_prior(self, sigma_noise: float, device="cpu") -> tuple[Tensor, float] | None:
        """The start's lever-arm prior (:func:`~torchcal.estimate.fit.place_instrument_and_tool`): centre ``tool``
        (default the flange centre) [m] and ``sigma_noise^2 / sigma^2`` for a measurement noise ``sigma_noise`` [m]."""
        if self.prior_lever is None:
            return None
        centre = torch.tensor(self.tool if self.tool is not None else (0.0, 0.0, 0.0), dtype=F64, device=device)
        return centre, (sigma_noise / self.prior_lever) ** 2


@dataclass(frozen=True)
class Levels:
    """The significance levels of the run's tests."""

    score: float = 0.01  # closed loop: family-wise level of the score tests (Bonferroni)
    validation: float = 0.05  # paired validation tests (closed loop, pruning, the integrated selection, the guard)
    outlier: float | None = 1e-3  # gross-error screening's family-wise level (None: no screening)


@dataclass(frozen=True)
class LoopOptions:
    """The ``auto`` method's closed loop."""

    enabled: bool = True  # search the named effects before the learned stage
    max_joint_error: float | None = MAX_JOINT_ERROR  # rad: the largest size a named joint-angle effect may have
    # anywhere on its joint's range (torchcal.effects.joint.MAX_JOINT_ERROR; None: no bound)


@dataclass(frozen=True)
class LearnedOptions:
    """The ``auto`` method's learned residual model."""

    enabled: bool = True  # the learned residual model after the closed loop (False: the loop alone)
    hyper: bool = True  # refit a kept GP's hyperparameters in every alternating and pruning refit (False: hold them
    # and only re-condition the GP, pipeline.learned._conditioner: faster, decisions may differ)


@dataclass(frozen=True)
class NetworkOptions:
    """The correction network (``pcm``, ``kinematic+ann``, the learned stage's candidate, the integrated filter)."""

    hidden: int = 29
    method: str = "lm"  # its fit (torchcal.estimate.netfit)
    iterations: int = 100


@dataclass(frozen=True)
class IntegratedOptions:
    """The ``integrated`` method."""

    engine: Engine = Engine.AUTO  # (torchcal._method.Engine; its name as a string is accepted)


@dataclass(frozen=True)
class Options:
    """A run's options (module docstring). ``Options(method="kinematic", seed=3)`` sets run-wide fields;
    ``Options.of(max_iter=50, hidden=16)`` sets any field by its flat name (:data:`FLAGS`)."""

    method: Method = DEFAULT_METHOD  # (torchcal._method.Method; its name as a string is accepted)
    seed: int = 0
    device: str = "cpu"  # where the run computes: cpu, cuda, cuda:N (torchcal._device.resolve_device)
    refit: bool | None = None  # the model written fitted again on all samples, training and held-out, once chosen
    # (the held-out errors reported stay those of the fit on the training samples): None means on for the
    # integrated method's auto engine and off otherwise; True is allowed for kinematic too (see ``refits``)
    split: SplitOptions = field(default_factory=SplitOptions)
    fit: FitSettings = field(default_factory=FitSettings)
    levels: Levels = field(default_factory=Levels)
    loop: LoopOptions = field(default_factory=LoopOptions)
    learned: LearnedOptions = field(default_factory=LearnedOptions)
    network: NetworkOptions = field(default_factory=NetworkOptions)
    integrated: IntegratedOptions = field(default_factory=IntegratedOptions)

    def __post_init__(self):
        self._typed_method_and_engine()
        engine = self.integrated.engine
        mje = self.loop.max_joint_error
        if mje is not None and not 0.0 < mje <= 0.5:
            raise OptionError(f"max_joint_error must lie in (0, 0.5] rad, got {mje}")
        if not 0.0 < self.split.holdout < 0.9:
            raise OptionError(f"holdout must lie in (0, 0.9), got {self.split.holdout}")
        fit = self.fit
        check_range("sigma_tracker", fit.sigma_tracker, 0.0, MAX_SIGMA_TRACKER, low_open=True, scale=1e6, unit="um")
        check_range("sigma_joint", fit.sigma_joint, 0.0, MAX_SIGMA_JOINT, scale=180 / math.pi, unit="deg")
        if fit.sigma_orientation is not None:
            check_range(
                "sigma_orientation", fit.sigma_orientation, 0.0, 0.1, low_open=True, scale=180 / math.pi, unit="deg"
            )
        check_range("rank_tol", fit.rank_tol, 0.0, MAX_RANK_TOL, low_open=True)
        if self.refit and not (
            self.method == Method.KINEMATIC or (self.method == Method.INTEGRATED and engine == Engine.AUTO)
        ):
            raise OptionError(
                f"refit applies to the kinematic method and the integrated method's auto engine, not to method "
                f"'{self.method}'" + (f" with engine '{engine}'" if self.method == Method.INTEGRATED else "")
            )
        if fit.tool is not None and (len(fit.tool) != 3 or not fit.tool_sigma > 0):
            raise OptionError(
                f"tool must be 3 numbers [m] with a positive tool_sigma, got {fit.tool}, {fit.tool_sigma}"
            )
        if fit.tool is not None:  # a lever arm of metres is a unit mix-up (mm given as m), not a probe
            for k, v in zip("xyz", fit.tool):
                check_range(f"tool {k}", v, -MAX_TOOL, MAX_TOOL, scale=1e3, unit="mm")
            check_range("tool_sigma", fit.tool_sigma, 0.0, MAX_TOOL, low_open=True, scale=1e3, unit="mm")
        # an unknown or absent device raises here, before any work
        object.__setattr__(self, "device", str(resolve_device(self.device)))

    def _typed_method_and_engine(self) -> None:
        """The method and the engine as their types (a name given as a string is looked up; an unknown one raises)."""
        if self.method not in METHODS:
            raise OptionError(f"method '{self.method}' is not one of {', '.join(METHODS)}")
        if self.integrated.engine not in ENGINES:
            raise OptionError(f"engine '{self.integrated.engine}' is not one of {', '.join(ENGINES)}")
        object.__setattr__(self, "method", Method(self.method))
        object.__setattr__(
            self, "integrated", dataclasses.replace(self.integrated, engine=Engine(self.integrated.engine))
        )

    @classmethod
    def of(cls, **flags) -> Options:
        """Options with the fields named by their flat names (:data:`FLAGS`) set, the rest at their defaults."""
        return cls().with_flags(**flags)

    def with_flags(self, **flags) -> Options:
        """These options with the fields named by their flat names (:data:`FLAGS`) changed, validated again."""
        unknown = sorted(set(flags) - set(FLAGS))
        if unknown:
            raise OptionError(f"unknown option(s) {', '.join(unknown)}; valid: {', '.join(sorted(FLAGS))}")
        top, groups = {}, {}
        for name, value in flags.items():
            group, _, attr = FLAGS[name].rpartition(".")
            (groups.setdefault(group, {}) if group else top)[attr] = value
        for group, values in groups.items():
            top[group] = dataclasses.replace(getattr(self, group), **values)
        return dataclasses.replace(self, **top)

    def flag(self, name: str):
        """The value of the field with the flat name ``name`` (:data:`FLAGS`)."""
        group, _, attr = FLAGS[name].rpartition(".")
        return getattr(getattr(self, group) if group else self, attr)

    @property
    def refits(self) -> bool:
        """Whether the model written is fitted again on all samples once chosen (``refit``; None: the integrated
        method's auto engine does, the rest do not). On a trajectory the held-out last samples are the ones
        nearest the path's continuation, and the model a user predicts that continuation with should have them."""
        if self.refit is None:
            return self.method == Method.INTEGRATED and self.integrated.engine == Engine.AUTO
        return bool(self.refit)


#: every field by its flat name (the command line's flag, ``--max-iter`` -> ``max_iter``) -> its place in Options
FLAGS: dict[str, str] = {
    "method": "method",
    "seed": "seed",
    "device": "device",
    "refit": "refit",
    "holdout": "split.holdout",
    "group_tol": "split.group_tol",
    "trajectory": "split.trajectory",
    **{f.name: f"fit.{f.name}" for f in dataclasses.fields(FitSettings)},
    "alpha": "levels.score",
    "alpha_validation": "levels.validation",
    "outlier_alpha": "levels.outlier",
    "diagnose": "loop.enabled",
    "max_joint_error": "loop.max_joint_error",
    "learned": "learned.enabled",
    "learned_hyper": "learned.hyper",
    "hidden": "network.hidden",
    "net_method": "network.method",
    "net_iterations": "network.iterations",
    "engine": "integrated.engine",
}
