"""The far-off geometric fit names one bad row only where that row stands alone: a large effect the geometry lacks
makes many rows miss alike and is left to the closed loop."""

from types import SimpleNamespace

import pytest
import torch

from torchcal.errors import EstimationError
from torchcal.pipeline.checks import _check_one_bad_row
from torchcal.sim import SimConfig, simulate


def test_a_lone_miss_is_named_and_a_smooth_one_is_not():
    c = simulate(SimConfig(robot="ur5", poses=80, test_poses=0, seed=2))
    far = SimpleNamespace(global_test={"statistic": 1e9, "threshold": 1.0})
    lone = c.train.subset(torch.arange(c.train.n))
    lone.p[7] += torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)  # one row 10 mm off
    with pytest.raises(EstimationError, match="one bad row: line [0-9]+ misses by 10 mm"):
        _check_one_bad_row(far, c.model, lone)
    smooth = c.train.subset(torch.arange(c.train.n))
    smooth.p[:, 2] += 5e-3 * torch.sin(smooth.q[:, 1])  # millimetres along z, following joint 2: many rows alike
    _check_one_bad_row(far, c.model, smooth)
