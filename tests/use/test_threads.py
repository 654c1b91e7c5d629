"""predict, the trust columns and plan choose one torch thread for their small kernels and give the caller's back."""

import pytest
import torch

from torchcal.use import plan, rundir


class _Seen(Exception):
    pass


@pytest.mark.parametrize(
    "call, inner",
    [
        (lambda: rundir.predict_with(_Model(), {}, _Data()), "check_placement"),
        (lambda: rundir.row_trust("no-run", _Model(), {}, _Ctx()), "load_trust"),
    ],
)
def test_one_thread_inside_and_the_callers_after(monkeypatch, call, inner):
    seen = []

    def record(*a, **k):
        seen.append(torch.get_num_threads())
        raise _Seen

    monkeypatch.setattr(rundir, inner, record)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with pytest.raises(_Seen):
            call()
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_plan_poses_runs_on_one_thread(monkeypatch):
    seen = []

    def record(*a, **k):
        seen.append(torch.get_num_threads())
        raise _Seen

    monkeypatch.setattr(plan, "design_problem", record)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with pytest.raises(_Seen):
            plan.plan_poses(_Model(), torch.zeros(3, 6, dtype=torch.float64), plan.PlanOptions(k=2))
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


class _Robot:
    dof = 6


class _Model:
    robot = _Robot()

    def to(self, device):
        return self

    def extrapolation(self, q):
        return torch.zeros(0)


class _Data:
    dof = 6

    def to(self, device):
        return self


class _Ctx:
    q = torch.zeros(0, 6, dtype=torch.float64)
