"""The options of a calibration run, validated in one place."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal import stats as S
from torchcal._bounds import MAX_RANK_TOL, MAX_SIGMA_JOINT, MAX_SIGMA_TRACKER, MAX_TOOL, check_range
from torchcal._device import resolve_device
from torchcal.effects import MAX_JOINT_ERROR
from torchcal.errors import OptionError
from torchcal.estimate.identifiability import DEFAULT_TOL

Tensor = torch.Tensor
F64 = torch.float64

METHODS = ("auto", "kinematic", "pcm", "kinematic+ann", "integrated")
#: engines of the integrated method (:mod:`torchcal.pipeline.integrated`)
ENGINES = ("auto", "adaptive", "ekf")
DEFAULT_METHOD = "auto"


@dataclass
class Options:
    method: str = DEFAULT_METHOD
    seed: int = 0
    holdout: float = 0.2
    sigma_tracker: float = 15e-6  # m per axis, when the data carry no sx, sy, sz
    sigma_joint: float = math.radians(0.0005)  # rad, joint reading noise
    rank_tol: float = DEFAULT_TOL
    max_iter: int = 100
    hidden: int = 29
    prior_length: float | None = 1e-3  # m: a-priori sigma of the geometric length corrections (None: no prior)
    prior_angle: float | None = math.radians(0.1)  # rad: likewise for angles
    # the lever arm and the instrument pose (README, "Priors"): MAP where the data are weak, held where they add little
    prior_tool: float | None = 0.5  # m: a-priori sigma of the lever arm about the flange centre (None: no prior)
    prior_instrument: tuple[float, float] | None = (0.5, 0.1)  # m, rad: of the instrument pose about the start
    tool: tuple[float, float, float] | None = None  # m: a known lever arm (flange frame), the prior's centre
    tool_sigma: float = 1e-3  # m: the known lever arm's a-priori sigma
    stat_tol: float = 1e-2  # stop LM when a step gains less than 1 % of the variance factor
    net_method: str = "lm"
    net_iterations: int = 100
    trajectory: bool | None = None  # None: decide from a monotonic t column
    diagnose: bool = True  # auto: search the named effects (the closed loop) before the learned stage
    learned: bool = True  # auto: the learned residual model after the closed loop (False: the loop alone)
    learned_hyper: bool = True  # auto: refit a kept GP's hyperparameters in every alternating and pruning refit
    # (False: hold them and only re-condition the GP, pipeline.learned._conditioner: faster, decisions may differ)
    alpha: float = 0.01  # closed loop: family-wise level of the score tests (Bonferroni)
    alpha_validation: float = 0.05  # closed loop: level of the paired validation test
    engine: str = "auto"  # integrated: "auto" (chosen on validation, geometry alone among the candidates),
    # "adaptive" (geometry in the filter state) or "ekf" (the paper's filter)
    outlier_alpha: float | None = 1e-3  # gross-error screening's family-wise level (None: no screening)
    group_tol: float = S.GROUP_TOL  # rad: rows whose joints all agree within it stay on one side of every split
    device: str = "cpu"  # where the run computes: cpu, cuda, cuda:N (torchcal._device.resolve_device)
    max_joint_error: float | None = MAX_JOINT_ERROR  # rad: the largest size a named joint-angle effect may have
    # anywhere on its joint's range (torchcal.effects.joint.MAX_JOINT_ERROR; None: no bound)
    refit: bool | None = None  # the model written fitted again on all samples, training and held-out, once chosen
    # (the held-out errors reported stay those of the fit on the training samples): None means on for the
    # integrated method's auto engine and off otherwise; True is allowed for kinematic too (see ``refits``)

    def __post_init__(self):
        if self.method not in METHODS:
            raise OptionError(f"method '{self.method}' is not one of {', '.join(METHODS)}")
        if self.engine not in ENGINES:
            raise OptionError(f"engine '{self.engine}' is not one of {', '.join(ENGINES)}")
        if self.max_joint_error is not None and not 0.0 < self.max_joint_error <= 0.5:
            raise OptionError(f"max_joint_error must lie in (0, 0.5] rad, got {self.max_joint_error}")
        if not 0.0 < self.holdout < 0.9:
            raise OptionError(f"holdout must lie in (0, 0.9), got {self.holdout}")
        check_range("sigma_tracker", self.sigma_tracker, 0.0, MAX_SIGMA_TRACKER, low_open=True, scale=1e6, unit="um")
        check_range("sigma_joint", self.sigma_joint, 0.0, MAX_SIGMA_JOINT, scale=180 / math.pi, unit="deg")
        check_range("rank_tol", self.rank_tol, 0.0, MAX_RANK_TOL, low_open=True)
        if self.refit and not (self.method == "kinematic" or (self.method == "integrated" and self.engine == "auto")):
            raise OptionError(
                f"refit applies to the kinematic method and the integrated method's auto engine, not to method "
                f"'{self.method}'" + (f" with engine '{self.engine}'" if self.method == "integrated" else "")
            )
        if self.tool is not None and (len(self.tool) != 3 or not self.tool_sigma > 0):
            raise OptionError(
                f"tool must be 3 numbers [m] with a positive tool_sigma, got {self.tool}, {self.tool_sigma}"
            )
        if self.tool is not None:  # a lever arm of metres is a unit mix-up (mm given as m), not a probe
            for k, v in zip("xyz", self.tool):
                check_range(f"tool {k}", v, -MAX_TOOL, MAX_TOOL, scale=1e3, unit="mm")
            check_range("tool_sigma", self.tool_sigma, 0.0, MAX_TOOL, low_open=True, scale=1e3, unit="mm")
        self.device = str(resolve_device(self.device))  # an unknown or absent device raises here, before any work

    @property
    def prior_lever(self) -> float | None:
        """The lever arm's a-priori sigma [m]: ``tool_sigma`` about a known ``tool``, else ``prior_tool``."""
        return self.tool_sigma if self.tool is not None else self.prior_tool

    def lever_prior(self, sigma_noise: float) -> tuple[Tensor, float] | None:
        """The start's lever-arm prior (:func:`~torchcal.estimate.fit.place_instrument_and_tool`): centre ``tool``
        (default the flange centre) [m] and ``sigma_noise^2 / sigma^2`` for a measurement noise ``sigma_noise`` [m]."""
        if self.prior_lever is None:
            return None
        centre = torch.tensor(self.tool if self.tool is not None else (0.0, 0.0, 0.0), dtype=F64, device=self.device)
        return centre, (sigma_noise / self.prior_lever) ** 2

    @property
    def refits(self) -> bool:
        """Whether the model written is fitted again on all samples once chosen (``refit``; None: the integrated
        method's auto engine does, the rest do not). On a trajectory the held-out last samples are the ones
        nearest the path's continuation, and the model a user predicts that continuation with should have them."""
        return self.method == "integrated" and self.engine == "auto" if self.refit is None else bool(self.refit)
