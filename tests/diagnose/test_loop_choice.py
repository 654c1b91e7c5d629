"""The loop's choice among candidates that all passed validation: lowest validation RMSE, BIC among ties."""

from types import SimpleNamespace

import torch

from torchcal.pipeline.loop import _choose, _Validation


def _v(name: str, errors: torch.Tensor, bic: float) -> _Validation:
    rmse = float(errors.square().mean().sqrt()) * 1e3
    return _Validation(None, 1, SimpleNamespace(name=name), None, None, errors, {"rmse_after_mm": rmse}, True, "", bic)


def test_a_tie_on_validation_goes_to_the_lower_bic():
    g = torch.Generator().manual_seed(3)
    e = 30e-6 + 1e-6 * torch.randn(200, generator=g, dtype=torch.float64)
    f = e.clone()  # a hair lower RMSE on validation, but pose by pose no better: not significant
    f[::2] -= 1.0e-6
    f[1::2] += 0.9e-6
    flexible = _v("cyclic:2", f, bic=628.7)
    physical = _v("compliance:2", e, bic=623.5)
    assert flexible.validation["rmse_after_mm"] < physical.validation["rmse_after_mm"]
    notes = []
    run = SimpleNamespace(notes=notes, note=notes.append)  # a stage's work, as far as _choose uses it
    assert _choose([flexible, physical], False, 0.05, run) is physical
    assert run.notes and "compliance:2 preferred to cyclic:2" in run.notes[0]


def test_a_significantly_better_candidate_wins_whatever_its_bic():
    g = torch.Generator().manual_seed(4)
    e = 30e-6 + 1e-6 * torch.randn(200, generator=g, dtype=torch.float64)
    better = _v("cyclic:5", 0.8 * e, bic=700.0)
    worse = _v("compliance:5", e, bic=600.0)
    notes = []
    run = SimpleNamespace(notes=notes, note=notes.append)  # a stage's work, as far as _choose uses it
    assert _choose([worse, better], False, 0.05, run) is better and run.notes == []
