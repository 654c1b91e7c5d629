"""The instrument's noise level as the data tell it, and what a failed global test found.

The global test compares the weighted residual with the stochastic model: the tracker's noise (the file's sx, sy, sz,
or the assumed ``sigma_tracker``) and the joints'. On a real campaign it fails by far (variance factors of 100 to 4000)
because every real model leaves more than the instrument's noise, not because anything is wrong. What a user needs
from it is two numbers and a reading:

* the noise level, measured where the data can tell it: rows that revisit one joint configuration (within the split's
  revisit tolerance) differ only by the instrument's noise and the robot's repeatability, whatever the model leaves,
  so the pooled scatter of the final model's residuals within each revisit group is a variance component the model
  cannot remove; where the data repeat too few poses, the file's own sx, sy, sz (the instrument's statement), and
  else the assumed ``sigma_tracker`` (said so);
* how much the model leaves: its held-out RMSE, in those noise levels.

The reading: a kinematic calibration of the right robot in the right units leaves a small share of the arm's reach
(real UR10s: 0.4-0.5 mm over a 1.3 m reach, 4e-4); a joint column in degrees read as radians, a length in another
unit or a description of another robot leaves a share the geometry cannot absorb. Above :data:`MISTAKE_SHARE` of the
reach, the geometric fit's held-out RMSE reads as such a mistake; below it the model leaves structure an effect may
explain (report.md's effects and unexplained structure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.stats import GROUP_TOL, revisit_groups

Tensor = torch.Tensor

#: the fewest degrees of freedom (rows in revisit groups less their groups, per axis) that measure the noise level:
#: below 10 its estimate's own relative error exceeds about 20 %
MIN_REVISIT_DOF = 10
#: the geometric fit's held-out RMSE, as a share of the arm's reach, above which it reads as a unit or description
#: mistake: real kinematic calibrations leave at most 4e-4 (docs/real-data.md); a joint in degrees read as radians
#: leaves 1e-2 and more (tests/diagnose/test_noise.py)
MISTAKE_SHARE = 2e-3


@dataclass(frozen=True)
class NoiseLevel:
    """The instrument's noise per axis and where it comes from.

    Attributes:
        sigma_m: standard deviation per axis [m].
        source: ``"revisits"`` (measured: scatter within revisit groups), ``"stated"`` (the file's sx, sy, sz) or
            ``"assumed"`` (the calibration's ``sigma_tracker``; the data could not tell it).
        dof: degrees of freedom of a measured level (rows in revisit groups less their groups), 0 otherwise.
    """

    sigma_m: float
    source: str
    dof: int = 0

    def to_dict(self) -> dict:
        return {"sigma_m": self.sigma_m, "unit": "m", "source": self.source, "dof": self.dof}

    def words(self) -> str:
        how = {
            "revisits": f"measured on the rows that revisit a pose: the instrument's noise with the robot's "
            f"repeatability, {self.dof} degrees of freedom",
            "stated": "as the file's sx, sy, sz state it",
            "assumed": "assumed (--tracker-noise; the data repeat too few poses and carry no sx, sy, sz to tell it)",
        }[self.source]
        return f"{self.sigma_m * 1e6:.3g} um per axis, {how}"


def noise_level(
    q: Tensor, residual: Tensor, sigma: Tensor | None, assumed: float, tol: float = GROUP_TOL
) -> NoiseLevel:
    """The instrument's noise level per axis (module docstring).

    Args:
        q: joint readings ``(N, dof)`` [rad or m] of the rows.
        residual: the final model's residual ``(N, 3)`` [m] on the same rows.
        sigma: the file's per-row standard deviations ``(N, 3)`` [m], or None.
        assumed: the calibration's ``sigma_tracker`` [m] per axis.
        tol: joint tolerance [rad] of a revisit (:func:`~torchcal.stats.revisit_groups`).
    """
    labels = revisit_groups(q.detach().cpu(), tol)
    r = residual.detach().cpu().to(torch.float64)
    counts = torch.bincount(labels)
    dof = int((counts[counts > 1] - 1).sum())
    if dof >= MIN_REVISIT_DOF:
        means = torch.zeros(len(counts), 3, dtype=r.dtype, device=r.device).index_add_(0, labels, r) / counts[:, None]
        ss = float((r - means[labels]).square().sum())
        return NoiseLevel(math.sqrt(ss / (3 * dof)), "revisits", dof)
    if sigma is not None:
        return NoiseLevel(float(sigma.detach().cpu().square().mean().sqrt()), "stated")
    return NoiseLevel(float(assumed), "assumed")


def global_test_reading(test: dict, noise: NoiseLevel, rmse_m: float, rmse_geometric_m: float, reach_m: float) -> dict:
    """What a global test found, for report.json's ``global_test`` (beside its statistic).

    Args:
        test: the global test (``statistic``, ``threshold``, ``passed``).
        noise: the instrument's noise level (:func:`noise_level`).
        rmse_m: the final model's held-out RMSE [m] (3-D distance).
        rmse_geometric_m: the geometric fit's held-out RMSE [m].
        reach_m: the largest distance of the probe from the robot's base over the rows [m].

    Returns:
        ``noise`` (:meth:`NoiseLevel.to_dict`), ``unexplained_mm`` (the held-out RMSE), ``times_noise`` (it over the
        noise's 3-D RMS, ``sqrt(3) sigma``), ``reach_m``, ``geometric_share_of_reach`` and ``reading``: ``"agrees"``
        (passed), ``"model"`` (the model leaves structure) or ``"mistake"`` (a unit or description mistake, by
        :data:`MISTAKE_SHARE`).
    """
    share = rmse_geometric_m / reach_m if reach_m > 0 else float("inf")
    reading = "agrees" if test.get("passed", True) else ("mistake" if share > MISTAKE_SHARE else "model")
    return {
        "noise": noise.to_dict(),
        "unexplained_mm": rmse_m * 1e3,
        "times_noise": rmse_m / (math.sqrt(3) * noise.sigma_m) if noise.sigma_m > 0 else None,
        "reach_m": reach_m,
        "geometric_share_of_reach": share,
        "reading": reading,
    }


__all__ = ["MISTAKE_SHARE", "NoiseLevel", "global_test_reading", "noise_level"]
