"""The residual view of a decision finds its effect: two couplings into one joint by their sources, an instrument
term by its term."""

import torchcal
from torchcal.diagnose.candidates import Candidate
from torchcal.diagnose.views import _find
from torchcal.effects import Backlash, Coupling, MeasurementModel, TrackerError


def test_the_view_finds_each_coupling_by_its_source_and_an_instrument_term_by_its_term():
    robot = torchcal.load_robot("ur5")
    model = MeasurementModel(
        robot,
        [Backlash(5, source="auto"), Coupling(5, 4), Coupling(5, 6), TrackerError("range"), TrackerError("azimuth")],
    )
    assert _find(model, Candidate("coupling", 5, source=6)) == 2
    assert _find(model, Candidate("coupling", 5, source=4)) == 1
    assert _find(model, Candidate("backlash", 5)) == 0
    assert _find(model, Candidate("instrument", None, "azimuth")) == 4
