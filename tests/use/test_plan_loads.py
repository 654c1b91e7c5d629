"""plan over loads (issue 45 item 5): the planned poses take the payload levels in turn, every load an equal share of
the rows over the planned region; a candidates file's load columns stay with the poses chosen."""

import json

import pytest
import torch

from tests._cli import cli_simulate
from torchcal.cli import main
from torchcal.data import read_measurements
from torchcal.errors import OptionError
from torchcal.use.plan import loads_summary, plan_loads


def test_levels_in_turn_and_counted():
    p = plan_loads(7, (0, 5, 10))
    assert p.tolist() == [0.0, 5.0, 10.0, 0.0, 5.0, 10.0, 0.0]
    assert loads_summary(p) == {"levels_kg": [0.0, 5.0, 10.0], "rows": [3, 2, 2]}
    for bad in ((), (-1.0,), (float("nan"),), (3000.0,)):
        with pytest.raises(OptionError, match="payload levels"):
            plan_loads(3, bad)


@pytest.fixture(scope="module")
def candidates(tmp_path_factory):
    out = tmp_path_factory.mktemp("cand") / "sim"
    assert cli_simulate(out, "--poses", "60", "--test-poses", "10", "--payload-levels", "0,5", "--torques") == 0
    return out / "train.csv"


def test_plan_keeps_the_candidates_load_columns(candidates, tmp_path):
    out = tmp_path / "poses.csv"
    assert main(["plan", "--robot", "ur5", "--n", "12", "--candidates", str(candidates), "--out", str(out)]) == 0
    cand, planned = (
        read_measurements(candidates, require_positions=False),
        read_measurements(out, require_positions=False),
    )
    assert planned.payload is not None and planned.tau is not None
    for i in range(planned.n):  # each planned pose carries its own candidate row's load
        j = int(torch.nonzero((cand.q == planned.q[i]).all(1))[0])
        assert float(planned.payload[i]) == float(cand.payload[j])
        assert torch.equal(planned.tau[i], cand.tau[j])
    summary = json.loads(out.with_suffix(".plan.json").read_text())
    assert sum(summary["loads"]["rows"]) == 12


def test_plan_over_payload_levels(candidates, tmp_path):
    out = tmp_path / "poses.csv"
    argv = ["plan", "--robot", "ur5", "--n", "12", "--candidates", str(candidates), "--out", str(out)]
    assert main([*argv, "--payload-levels", "0,5,10"]) == 0
    planned = read_measurements(out, require_positions=False)
    assert planned.payload.tolist() == [0.0, 5.0, 10.0] * 4
    assert planned.tau is not None  # the candidates' torques stay (they were measured at the candidates' load)
    assert json.loads(out.with_suffix(".plan.json").read_text())["loads"] == {
        "levels_kg": [0.0, 5.0, 10.0],
        "rows": [4, 4, 4],
    }
    with pytest.raises(SystemExit) as e:
        main([*argv, "--payload-levels", "0,five", "--force"])
    assert e.value.code == 2
