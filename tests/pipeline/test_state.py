"""The run state and its stages: a stage reads a frozen run and returns what it changed; only calibrate applies it.
And the options: one frozen group per concern, every field named once by its flat name, validated in one place."""

import dataclasses

import pytest
import torch

from torchcal._threads import torch_threads
from torchcal.errors import OptionError
from torchcal.pipeline import METHODS, Options, calibrate
from torchcal.pipeline.methods import METHOD_TABLE, closed_loop, geometric, nominal
from torchcal.pipeline.options import FLAGS
from torchcal.pipeline.records import EffectRecord, Note
from torchcal.pipeline.run import start
from torchcal.pipeline.state import StageResult, StageWork
from torchcal.sim import EffectSpec, SimConfig, simulate


@pytest.fixture(scope="module")
def started():
    """A run after its nominal and geometric stages, on a campaign with a compliance for the loop to find."""
    c = simulate(SimConfig(robot="ur5", poses=160, test_poses=10, seed=11, effects=[EffectSpec.parse("compliance:2")]))
    with torch_threads(1):
        run = start("ur5", c.train, Options(seed=11))
        for stage in (nominal, geometric):
            run = run.apply(stage(run))
    return run


def _snapshot(run):
    return (
        {k: v.clone() for k, v in run.model.state_dict().items()},
        len(run.model.effects),
        tuple(run.stages),
        tuple(run.fits),
        tuple(run.effects),
        tuple(run.notes),
    )


def test_every_method_name_has_its_declared_stages():
    assert tuple(METHOD_TABLE) == METHODS
    for name, method in METHOD_TABLE.items():
        assert method.name == name and method.stages[-1].__name__ == "finish"


def test_a_stage_reads_the_run_and_returns_what_it_changed(started):
    before = _snapshot(started)
    with torch_threads(1):
        result = closed_loop(started)
    state, n_effects, stages, fits, effects, notes = _snapshot(started)
    # the run it read is as it was: its model's values and effects, its story and records
    assert n_effects == before[1] and stages == before[2] and fits == before[3] and effects == before[4]
    assert notes == before[5] and all(torch.equal(state[k], before[0][k]) for k in state)
    assert result.stage == "closed loop" and result.model is not started.model
    assert [r.label for r in result.effects] == [s.name for s in result.checkpoints] == ["compliance(joint 2)"]
    assert all(isinstance(n, Note) and n.stage == "closed loop" for n in result.notes)
    after = started.apply(result)
    assert after is not started and after.model is result.model and after.diagnosis is result.diagnosis
    assert [s.name for s in after.stages] == ["nominal", "geometric", "compliance(joint 2)"]
    assert after.fits == started.fits + result.fits and after.effects == result.effects


def test_the_run_state_cannot_be_edited_in_place(started):
    with pytest.raises(dataclasses.FrozenInstanceError):
        started.model = None
    with pytest.raises(AttributeError):
        started.notes.append("x")  # a tuple


def test_apply_drops_amends_and_truncates(started):
    rec = EffectRecord("compliance", 2, {}, {}, name="compliance:2", label="c2")
    other = EffectRecord("cyclic", 3, {}, {}, name="cyclic:3", label="y3")
    run = dataclasses.replace(started, effects=(rec, other))
    work = StageWork(run, "test", model=run.model)
    work.amend(rec, checked=True)
    work.effects[:] = [r for r in work.effects if r is not other]
    del work.fits[1:]
    work.note("said")
    result = work.result(model_changed=False)
    assert result.model is None and result.dropped_effects == ("y3",) and result.fits_kept == 1
    out = run.apply(result)
    assert [r.label for r in out.effects] == ["c2"] and out.effects[0].evidence == {"checked": True}
    assert rec.evidence == {}  # the run's own record is unchanged
    assert len(out.fits) == 1 and out.notes[-1] == "said" and out.notes[-1].stage == "test"
    assert run.apply(StageResult("nothing")).effects == run.effects


def test_calibrate_applies_the_methods_stages_in_order(monkeypatch, started):
    seen = []

    def recording(name):
        def stage(run):
            seen.append(name)
            return StageResult(name)

        return stage

    fake = dataclasses.replace(
        METHOD_TABLE["kinematic"], stages=(recording("a"), recording("b"), METHOD_TABLE["kinematic"].stages[-1])
    )
    monkeypatch.setitem(METHOD_TABLE, "kinematic", fake)
    run = calibrate("ur5", started.data, Options(method="kinematic"))
    assert seen == ["a", "b"] and run.stages == ()


def test_every_option_has_one_flat_name_and_one_place():
    leaves = []
    for f in dataclasses.fields(Options):
        if dataclasses.is_dataclass(f.default_factory if f.default_factory is not dataclasses.MISSING else None):
            leaves += [f"{f.name}.{g.name}" for g in dataclasses.fields(f.default_factory)]
        else:
            leaves.append(f.name)
    assert sorted(FLAGS.values()) == sorted(leaves)
    opts = Options.of(max_iter=7, hidden=5, alpha_validation=0.01, diagnose=False, holdout=0.3, seed=4)
    assert (opts.fit.max_iter, opts.network.hidden, opts.levels.validation) == (7, 5, 0.01)
    assert (opts.loop.enabled, opts.split.holdout, opts.seed) == (False, 0.3, 4)
    assert all(opts.flag(name) == Options().with_flags(**{name: opts.flag(name)}).flag(name) for name in FLAGS)


def test_options_are_validated_in_one_place_whichever_way_they_are_made():
    with pytest.raises(OptionError, match="unknown option.*valid:"):
        Options.of(max_iterations=3)
    with pytest.raises(OptionError, match="sigma_tracker must lie in"):
        Options().with_flags(sigma_tracker=1e300)
    with pytest.raises(OptionError, match="holdout must lie in"):
        Options(split=dataclasses.replace(Options().split, holdout=0.95))
    with pytest.raises(OptionError, match="engine 'fast'"):
        Options.of(engine="fast")


def test_each_calibrate_flag_sets_one_option():
    from torchcal.cli import CALIBRATE_FLAGS, METHOD_CHOICES, build_parser

    assert METHOD_CHOICES == METHODS

    names = [field for field, _ in CALIBRATE_FLAGS.values()]
    assert len(names) == len(set(names)) and set(names) <= set(FLAGS)
    args = build_parser().parse_args(["calibrate", "data.csv", "--robot", "ur5", "--out", "o"])
    assert all(hasattr(args, dest) for dest in CALIBRATE_FLAGS)


def test_every_replacing_field_of_a_stage_result_is_a_field_of_the_run_and_is_applied():
    """A StageResult field marked ``replaces`` names a field of the run, and apply() carries it over; a field added
    to StageResult without the mark or a structural rule would be silently dropped, so the set is pinned here."""
    import dataclasses

    from torchcal.pipeline.state import CalibrationRun, StageResult

    run_fields = {f.name for f in dataclasses.fields(CalibrationRun)}
    marked = {f.name for f in dataclasses.fields(StageResult) if f.metadata.get("replaces")}
    assert marked and marked <= run_fields
    structural = {
        "stage", "model", "checkpoints", "dropped_stages", "fits_kept", "fits", "effects", "amended",
        "dropped_effects", "rejections", "notes",
    }  # fmt: skip
    assert {f.name for f in dataclasses.fields(StageResult)} == structural | marked
