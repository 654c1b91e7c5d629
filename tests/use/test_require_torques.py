"""A run whose compliance reads the measured torques refuses rows without them, naming the file (the effect's own
refusal named none)."""

from types import SimpleNamespace

import pytest
import torch

from torchcal.data import Measurements
from torchcal.effects import Compliance, TorqueCompliance
from torchcal.errors import MeasurementFileError
from torchcal.use.conditions import require_torques


def _rows(tau):
    q = torch.zeros(3, 6, dtype=torch.float64)
    return Measurements(q=q, extra={} if tau is None else {f"tau{k + 1}": tau[:, k] for k in range(6)})


def test_rows_without_torques_are_refused_naming_the_file_and_the_columns():
    model = SimpleNamespace(effects=[TorqueCompliance(2)], robot=SimpleNamespace(dof=6))
    with pytest.raises(MeasurementFileError, match="tau1..tau6") as e:
        require_torques(model, _rows(None), "targets.csv")
    assert "targets.csv" in str(e.value)
    require_torques(model, _rows(torch.ones(3, 6, dtype=torch.float64)), "targets.csv")  # with them: accepted


def test_a_run_without_a_torque_driven_compliance_needs_none():
    model = SimpleNamespace(effects=[Compliance(2)], robot=SimpleNamespace(dof=6))
    require_torques(model, _rows(None), "targets.csv")
