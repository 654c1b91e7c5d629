"""The ``auto`` method's held-out guard (:func:`torchcal.pipeline.holdout.guard_stages`): never worse than the
kinematic calibration on the held-out poses; it steps back to the last stage below it, or to the geometry."""

import dataclasses

import pytest
import torch
from _cli import golden_auto_run

from torchcal.pipeline.holdout import at_edges, guard_stages
from torchcal.report.rundir import build_report


@pytest.fixture(scope="module")
def auto_run():
    """The golden campaign's auto run: geometric, compliance(joint 2), learned (shared with tests/test_golden.py)."""
    return golden_auto_run()


def _forced(run, worse: list[str]):
    """``run`` with its stages named in ``worse`` erring 1.5 times the geometric stage on the held-out poses."""
    geo = run.stage("geometric")
    return _with_errors(run, {name: geo.holdout_errors * 1.5 for name in worse})


def _with_errors(run, held_out: dict):
    """``run`` with the held-out errors of the stages named in ``held_out`` replaced, and no guard's evidence."""
    stages = tuple(
        dataclasses.replace(s, holdout_errors=held_out[s.name]) if s.name in held_out else s for s in run.stages
    )
    return dataclasses.replace(run, stages=stages, holdout_guard=None)


def guard_holdout(run):
    """The run after the guard, and the guard's evidence."""
    result = guard_stages(run)
    assert result.stage == "held-out guard"
    return run.apply(result), result.holdout_guard


@pytest.mark.slow
def test_a_run_below_geometry_passes_and_says_so(auto_run):
    names = [s.name for s in auto_run.stages]
    assert names == ["nominal", "geometric", "compliance(joint 2)", "learned"]
    g = auto_run.holdout_guard
    assert g["passed"] and [s["name"] for s in g["stages"]] == names[1:]
    assert g["geometric_rmse_mm"] == pytest.approx(auto_run.stage("geometric").rmse * 1e3)
    assert build_report(auto_run)["holdout_guard"] == g


def test_a_final_model_worse_than_geometry_steps_back_to_the_last_stage_below_it(auto_run):
    before = _forced(auto_run, ["learned"])
    run, ev = guard_holdout(before)
    assert before.model is auto_run.model and len(before.effects) == 2  # the stage did not edit the run it read
    assert not ev["passed"] and ev["kept_stage"] == "compliance(joint 2)"
    assert [s.name for s in run.stages] == ["nominal", "geometric", "compliance(joint 2)"]
    assert [r.label for r in run.effects] == ["compliance(joint 2)"]
    # the report's global test and parameters: the fit that admitted the kept effect, not the dropped GP's refits
    assert run.fits[-1].stage == "compliance(joint 2)" and len(run.fits) < len(auto_run.fits)
    (rej,) = [r for r in run.rejections if r.name == "learned"]
    assert "held-out guard" in rej.reason and rej.evidence["holdout_guard"] is ev
    # the model written is the stage's, as it stood (the learned effect gone), and the robot the report exports
    assert [type(e).__name__ for e in run.model.effects] == [
        type(e).__name__ for e in run.stage("compliance(joint 2)").model.effects
    ]
    assert run.robot is run.model.robot
    for a, b in zip(run.model.parameters(), run.stage("compliance(joint 2)").model.parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert any(n.startswith("held-out guard:") for n in run.notes)


def test_with_no_stage_below_geometry_the_run_keeps_the_kinematic_calibration(auto_run):
    run, ev = guard_holdout(_forced(auto_run, ["learned", "compliance(joint 2)"]))
    assert ev["kept_stage"] == "geometric" and not run.effects
    assert [s.name for s in run.stages] == ["nominal", "geometric"] and not run.model.effects
    assert run.fits[-1].stage == "geometric"  # the report's global test and parameters: the geometric fit's
    assert {r.name for r in run.rejections} >= {"learned", "compliance:2"}
    report = build_report(run)
    assert report["rmse_after_mm"] == pytest.approx(report["rmse_geometric_mm"]) and report["effects"] == []
    if not report["global_test"]["passed"]:  # what geometry leaves, not what the dropped effects left
        assert report["unexplained"]


@pytest.mark.parametrize("worse", [["learned"], ["learned", "compliance(joint 2)"]])
def test_a_step_back_writes_its_run_directory(auto_run, worse, tmp_path):
    """A run the guard stepped back writes report.json and report.md (a learned rejection whose evidence is the
    guard's once crashed report.md with ``KeyError: 'chosen'``)."""
    from torchcal.report.rundir import write_run_files

    run, _ = guard_holdout(_forced(auto_run, worse))
    out = write_run_files(run, tmp_path)
    md = (out / "report.md").read_text()
    assert "Learned residual model: " in md and "held-out guard" in md
    assert (out / "report.json").is_file() and (out / "model.pt").is_file()


def test_a_final_model_that_wins_in_the_middle_and_loses_at_the_edges_steps_back(auto_run):
    edge = at_edges(auto_run.train.q, auto_run.data.q[auto_run.holdout_idx])
    assert int(edge.sum()) >= 10  # held-out poses at the edges of the training poses' joint ranges
    geo = auto_run.stage("geometric")
    # better than the geometry overall, worse at the edges
    run = _with_errors(auto_run, {"learned": torch.where(edge, geo.holdout_errors * 1.4, geo.holdout_errors * 0.3)})
    assert run.stage("learned").rmse < geo.rmse
    run, ev = guard_holdout(run)
    assert not ev["passed"] and ev["kept_stage"] == "compliance(joint 2)" and ev["n_edge"] == int(edge.sum())
    (rej,) = [r for r in run.rejections if r.name == "learned"]
    assert "at the edges of the joint ranges" in rej.reason and "better in the middle" in rej.reason


def test_too_few_held_out_poses_are_not_judged(auto_run):
    """Three held-out poses say nothing about a model the validation poses chose: the guard does not step back on
    them, and says it did not judge; ten are judged."""
    from torchcal.pipeline.holdout import GUARD_MIN_POSES

    def shrunk(n: int):
        geo = auto_run.stage("geometric")
        errs = {s.name: s.holdout_errors[:n] for s in auto_run.stages}
        errs["learned"] = geo.holdout_errors[:n] * 1.5  # worse than the geometry on every one of them
        run = _with_errors(auto_run, errs)
        return dataclasses.replace(run, holdout_idx=auto_run.holdout_idx[:n])

    run, ev = guard_holdout(shrunk(3))
    assert ev["judged"] is False and ev["passed"] is True and "kept_stage" not in ev
    assert [s.name for s in run.stages][-1] == "learned" and [r.label for r in run.effects][-1] == "learned"
    assert any("not judged, 3 held-out pose(s)" in n for n in run.notes)
    run, ev = guard_holdout(shrunk(GUARD_MIN_POSES))
    assert ev["judged"] is True and not ev["passed"] and ev["kept_stage"] == "compliance(joint 2)"


def test_the_integrated_guard_judges_on_as_many_held_out_samples_as_the_auto_guard(auto_run):
    """:func:`guard_against_geometry` (the integrated method's) passes a model 1 mm off everywhere unjudged on one
    held-out sample fewer than :data:`GUARD_MIN_POSES`, as the auto guard does, and refuses it on that many."""
    import copy

    from torchcal.effects import MeasurementModel
    from torchcal.pipeline.holdout import GUARD_MIN_POSES, guard_against_geometry

    geometric = MeasurementModel(copy.deepcopy(auto_run.model.robot))
    worse = copy.deepcopy(geometric)
    with torch.no_grad():
        worse.robot.tool.delta.add_(1e-3)
    few = guard_against_geometry(worse, geometric, auto_run.hold.subset(slice(0, GUARD_MIN_POSES - 1)))
    assert few == {"passed": True, "n": GUARD_MIN_POSES - 1, "rule": "too few held-out samples to judge"}
    judged = guard_against_geometry(worse, geometric, auto_run.hold.subset(slice(0, GUARD_MIN_POSES)))
    assert judged["passed"] is False and judged["rmse_mm"] > 10 * judged["geometry_rmse_mm"]
