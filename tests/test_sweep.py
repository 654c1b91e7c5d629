"""torchcal.sweep: independent tasks one after another or on Ray, with the same results in the items' order; every
failure named after the others ran; a killed worker's task run again. The Ray tests start and stop their own local
instance (2 CPUs) and run an experiment's own seed sweep (experiments.plan_poses) both ways."""

import functools
import os
from pathlib import Path

import pytest
import torch

from torchcal import sweep as S
from torchcal._threads import torch_threads
from torchcal.errors import OptionError

try:
    import ray
except ImportError:
    ray = None
needs_ray = pytest.mark.skipif(ray is None, reason="Ray is not installed (pip install torchcal[fleet]): Ray untested")
ROOT = Path(__file__).resolve().parents[1]


def _draw(x: int) -> tuple[int, float]:
    """The item and a draw from the global torch generator: equal for every item when each call starts afresh."""
    return x, float(torch.rand(()))


def _fails_on_odd(x: int) -> int:
    if x % 2:
        raise ValueError(f"odd item {x}")
    return 10 * x


def test_serial_results_in_order_each_call_from_the_same_seed():
    before = torch.get_rng_state()
    got = S.map_tasks(_draw, range(4))
    assert [x for x, _ in got] == [0, 1, 2, 3]
    assert len({d for _, d in got}) == 1  # no call saw what the one before drew
    assert torch.equal(torch.get_rng_state(), before)  # and the caller's generator is as it was
    assert S.map_tasks(_draw, []) == []


def test_every_failure_is_named_after_the_others_ran():
    seen = []
    with pytest.raises(S.SweepError) as info:
        S.map_tasks(_fails_on_odd, range(5), progress=lambda i, r: seen.append(i))
    e = info.value
    assert seen == [0, 1, 2, 3, 4]
    assert [e.results[i] for i in (0, 2, 4)] == [0, 20, 40]
    assert [(f.index, f.error, f.lost) for f in e.failures] == [
        (1, "ValueError: odd item 1", False),
        (3, "ValueError: odd item 3", False),
    ]
    assert "2 of 5 tasks failed" in str(e) and "item 1 (1): ValueError: odd item 1" in str(e)
    assert "item 3 (3)" in str(e) and "_fails_on_odd" in e.failures[0].traceback


def test_without_ray_workers_run_one_after_another_and_say_so_once(monkeypatch, capsys):
    monkeypatch.setattr(S, "ray_available", lambda: False)
    monkeypatch.setattr(S, "_said_serial", False)
    assert S.map_tasks(_fails_on_odd, [0, 2], workers=2) == [0, 20]
    assert S.map_tasks(_fails_on_odd, [4], workers=2) == [40]
    err = capsys.readouterr().err
    assert err.count("one after another") == 1 and "pip install torchcal[fleet]" in err
    with pytest.raises(OptionError, match="needs Ray"):
        S.map_tasks(_fails_on_odd, [0], address="ray://head:10001")


def test_bad_workers_are_refused():
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(OptionError, match="workers must be a whole number"):
            S.map_tasks(_fails_on_odd, [0], workers=bad)


def test_workers_inherit_this_process_path_and_one_thread(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    with S.worker_env():
        path = os.environ["PYTHONPATH"].split(os.pathsep)
        assert path[0] == str(ROOT) and str(tmp_path) in path and os.environ["OMP_NUM_THREADS"] == "1"
    assert "OMP_NUM_THREADS" not in os.environ


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance of 2 CPUs for this module's tests, its workers started as :func:`torchcal.sweep.on_ray`
    starts them (this process's path: they import this test module and the checkout's experiments/)."""
    if ray is None:
        pytest.skip("Ray is not installed (pip install torchcal[fleet]): Ray untested")
    with S.worker_env():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def campaign():
    from torchcal.sim import SimConfig, simulate

    return simulate(SimConfig(robot="ur5", poses=60, test_poses=30, seed=5))


@pytest.mark.slow
@needs_ray
def test_an_experiment_sweep_on_ray_gives_the_serial_results(local_ray, campaign, monkeypatch):
    """plan_poses' designs (each planned and calibrated, a random design calibrated): 2 seeds one after another,
    then on the 2 workers."""
    monkeypatch.syspath_prepend(str(ROOT))
    from experiments import plan_poses

    protocol = plan_poses.Protocol(ks=(20,), seeds=2, reference=None)
    run = functools.partial(plan_poses.compare, "ur5", campaign.train, campaign.test, protocol)
    with torch_threads(1):  # the experiments' default --threads, as each Ray task runs
        serial = run()
    on_ray = run(workers=2)
    for res in (serial, on_ray):
        res.pop("seconds")
        res["sizes"][0].pop("plan_s")
    assert on_ray == serial
    assert len(set(serial["sizes"][0]["planned_values_mm"])) == 2  # two seeds, two designs


def _dies_once_or_raises(item: tuple[str, str]) -> str:
    """``("die", marker)``: the worker is killed on the first try (the marker file says whether it was tried);
    ``("raise", _)``: an error of the task itself."""
    kind, mark = item
    if kind == "raise":
        raise RuntimeError("the task's own error")
    if not Path(mark).exists():
        Path(mark).write_text("x")
        os._exit(1)
    return "ran again"


@needs_ray
def test_on_ray_a_killed_worker_is_retried_and_an_error_is_the_item_own(local_ray, tmp_path):
    items = [("die", str(tmp_path / "tried")), ("raise", "")]
    with pytest.raises(S.SweepError) as info:
        S.map_tasks(_dies_once_or_raises, items, workers=2)
    (f,) = info.value.failures
    assert info.value.results[0] == "ran again"
    assert (f.index, f.error, f.lost) == (1, "RuntimeError: the task's own error", False)


def test_an_address_nothing_answers_at_is_refused_at_once():
    """own: fleet --address 127.0.0.1:1 ran over 10 minutes, Ray retrying with a warning every few seconds; nothing
    listening there is refused before Ray is asked (``auto`` is left to Ray)."""
    from torchcal.errors import OptionError
    from torchcal.sweep import _check_reachable

    for address in ("127.0.0.1:1", "ray://127.0.0.1:1"):
        with pytest.raises(OptionError, match="nothing answers there"):
            _check_reachable(address)
    _check_reachable("auto")
