"""A covariance bounded by the robot's manufacturing tolerance (estimate.covariance.tolerance_bounded): the geometric
elements held at a wider prior come down to about their tolerance, those the rows determined stay as they were."""

import math

import pytest
import torch

from torchcal.effects import MeasurementModel
from torchcal.estimate.covariance import ParameterCovariance, tolerance_bounded
from torchcal.robot import load_robot
from torchcal.use.station import held_at_tolerance


def _cov(model, sds: dict[str, float], corr: float = 0.0) -> ParameterCovariance:
    names = list(model.robot.geometry.names)
    idx = [names.index(n) for n in sds]
    sd = torch.tensor(list(sds.values()), dtype=torch.float64)
    R = torch.full((len(sd), len(sd)), corr, dtype=torch.float64).fill_diagonal_(1.0)
    order = sorted(range(len(idx)), key=lambda k: idx[k])
    sd, R = sd[order], R[order][:, order]
    return ParameterCovariance(
        ["robot.geometry.delta"], [[idx[k] for k in order]], [list(sds)[k] for k in order], sd[:, None] * R * sd
    )


def test_an_element_held_at_a_wide_prior_comes_down_to_its_tolerance_and_a_determined_one_stays():
    model = MeasurementModel(load_robot("ur10"))
    cov = _cov(model, {"a2": 2e-6, "d5": 1e-3, "alpha5": math.radians(0.1)})
    out = tolerance_bounded(cov, model, 1e-4, math.radians(0.01))
    sd = dict(zip(out.labels, out.matrix.diagonal().sqrt().tolist()))
    assert sd["a2"] == pytest.approx(2e-6, rel=1e-12)  # below its tolerance: untouched
    assert sd["d5"] == pytest.approx((1e-6**-1 + 1e-8**-1) ** -0.5, rel=1e-9)  # the two informations added
    assert sd["alpha5"] == pytest.approx(1.0 / math.sqrt(1 / math.radians(0.1) ** 2 + 1 / math.radians(0.01) ** 2))
    assert torch.equal(out.matrix, out.matrix.T)


def test_a_correlated_element_follows_and_nothing_above_tolerance_leaves_the_covariance_as_it_was():
    model = MeasurementModel(load_robot("ur10"))
    cov = _cov(model, {"a5": 5e-5, "d5": 1e-3}, corr=0.9)
    out = tolerance_bounded(cov, model, 1e-4, math.radians(0.01))
    assert float(out.matrix[0, 1]) < 0.2 * float(cov.matrix[0, 1])  # the correlation's share of d5 went with it
    small = _cov(model, {"a2": 2e-6, "d5": 5e-5})
    assert tolerance_bounded(small, model, 1e-4, math.radians(0.01)) is small


def test_station_bounds_by_the_robots_own_tolerances_where_its_file_declares_them():
    model = MeasurementModel(load_robot("ur10"))
    cov = _cov(model, {"d5": 1e-3})
    default = float(held_at_tolerance(model, cov).matrix[0, 0]) ** 0.5
    assert default == pytest.approx((1e-6**-1 + 1e-8**-1) ** -0.5, rel=1e-9)  # the kinematic calibration's 0.1 mm
    model.robot.tolerances = (1e-5, math.radians(0.001))
    assert float(held_at_tolerance(model, cov).matrix[0, 0]) ** 0.5 == pytest.approx(
        (1e-6**-1 + 1e-10**-1) ** -0.5, rel=1e-9
    )
    assert held_at_tolerance(model, None) is None
