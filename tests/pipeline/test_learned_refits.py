"""The learned stage's refits: hyperparameters refitted by default, held (re-conditioning only) on request."""

import pytest
import torch
from _cli import golden_auto_run, golden_campaign

from torchcal._threads import torch_threads
from torchcal.effects.gp import GPCorrection
from torchcal.pipeline import Options, calibrate
from torchcal.sim import EffectSpec, SimConfig, simulate


def test_held_hyperparameters_are_the_selected_ones_and_refitted_ones_move():
    c = golden_campaign()
    with torch_threads(1):
        held = calibrate("ur5", c.train, Options.of(seed=7, learned_hyper=False))
    refit = golden_auto_run()  # Options(seed=7), the default refits; shared with tests/test_golden.py
    out = {}
    for name, run in (("held", held), ("refit", refit)):
        gp = run.model.effects[len(run.model.effects) - 1]
        assert isinstance(gp, GPCorrection)
        chosen = next(e for e in run.effects if e.kind == "learned").params
        selected = torch.tensor(list(chosen["ard_length_scale"].values()), dtype=torch.float64)
        out[name] = (gp.ard_len, selected)
        assert any("alternating refits" in n for n in run.notes)
    # held: the final GP keeps the hyperparameters chosen by the evidence at the selection, through every refit
    assert torch.allclose(out["held"][0], out["held"][1], rtol=1e-12)
    # refitted (the default): the alternating refits moved them
    assert not torch.allclose(out["refit"][0], out["refit"][1], rtol=1e-6)
    # both calibrate the campaign well below the geometric stage
    for run in (held, refit):
        assert run.stages[-1].rmse < 0.8 * run.stage("geometric").rmse


@pytest.mark.slow
@pytest.mark.parametrize("drop_all", [False, True])
def test_pruning_with_the_next_refit_ahead_decides_as_one_effect_after_the_other(monkeypatch, drop_all):
    """prune_named refits the geometry without the next effect while the GP refits (and again when the effect
    before is dropped): its decisions, notes and kept model are those of the plain loop, one effect after the
    other (:func:`_refit_with_learned` per effect, on the model as the decisions before left it). Here both
    named effects are kept; with ``drop_all`` (no paired test can pass) each is dropped, so that every refit
    made ahead is discarded and done again."""
    import copy
    from dataclasses import replace

    from torchcal.errors import EstimationError
    from torchcal.pipeline import learned as L

    cfg = SimConfig(
        robot="ur5",
        poses=240,
        test_poses=20,
        seed=5,
        effects=[
            EffectSpec.parse("compliance:2=60um"),
            EffectSpec.parse("cyclic:3=40um"),
            EffectSpec.parse("field=0.05mm"),
        ],
    )
    c = simulate(cfg)
    before = {}
    original = L.prune_named

    def recording(work, train, trajectory, e_val, gp=None):
        if drop_all:
            work.run = replace(work.run, options=work.options.with_flags(alpha_validation=0.0))
        before["run"], before["args"] = copy.deepcopy(work), (train, trajectory, e_val.clone())
        return original(work, train, trajectory, e_val, gp=gp)

    monkeypatch.setattr(L, "prune_named", recording)
    with torch_threads(1):
        run = calibrate("ur5", c.train, Options(seed=5))
    assert "run" in before, "the campaign must reach the pruning of named effects"
    ref, (train, trajectory, e_val) = before["run"], before["args"]
    labels = [e.label() for e in ref.model.effects if e.kind in L.NAMED_KINDS]
    assert len(labels) >= 2  # so that a refit ran ahead
    for label in labels:  # the plain loop
        k = next(i for i, e in enumerate(ref.model.effects) if e.label() == label)
        trial = copy.deepcopy(ref.model)
        del trial.effects[k]
        try:
            fit, e_without = L._refit_with_learned(ref, trial, train, trajectory)
        except EstimationError as err:
            ref.note(f"diagnosis: {label} kept: the refit without it failed ({err})")
            continue
        if L._prune_one(ref, ref.model, ref.model.effects[k], trial=trial, fit=fit, e_without=e_without, e_val=e_val):
            e_val = e_without
    n = len(ref.notes)  # the learned stage's notes (a stage's work holds its own)
    assert [t for t in run.notes if t.stage == "learned"][:n] == ref.notes
    assert [e.label() for e in run.model.effects[: len(ref.model.effects)]] == [e.label() for e in ref.model.effects]
    got, want = run.model.state_dict(), ref.model.state_dict()
    assert all(torch.equal(got[k], want[k]) for k in want if k.startswith("robot.") or "effects" not in k)
    assert [e.label for e in run.effects] == [e.label for e in ref.effects]
    dropped = [n for n in run.notes if " dropped: the learned model explains it" in n]
    assert len(dropped) == (len(labels) if drop_all else 0)
