"""Device cleanliness (issue 14.5): every tensor the calibration builds lands on the device of the data.

Three kinds of evidence:

* ``meta`` tensors (shapes, no values): the forward kinematics, the measurement model with every named effect,
  the analytic tracker Jacobian and the residuals and normal equations of LM. Anything that builds a CPU tensor
  and combines it with a meta one raises. Paths that need values (``.item()``, data-dependent shapes) stop on
  meta, so they run on the
* virtual device (``tests/_virtual_device.py``): CPU tensors that claim to live elsewhere, with real values,
  raising where a plain CPU tensor meets them as CUDA would. The rigid start, a least-squares fit, the named
  effects' score columns, the learned stage's fits, a whole calibration and ``predict`` run on it and agree with
  the CPU to round-off.
* CUDA, when this machine has it: a small calibration on the GPU against the CPU.

And a static count of the tensor constructors in the package that pass no ``device=`` (``ALLOWED`` says why each
one left is right).
"""

from __future__ import annotations

import ast
import importlib
import json
import math
import os
from pathlib import Path

import pytest
import torch
from _virtual_device import Virtual, cpu, virtual_device

import torchcal
from torchcal.effects import Context, MeasurementModel
from torchcal.effects.drift import Drift
from torchcal.effects.joint import Backlash, Compliance, Cyclic, Transmission
from torchcal.effects.kernel import KernelCorrection, fit_kernel_correction
from torchcal.effects.learned import CorrectionNet, LearnedEffect
from torchcal.estimate.fit import GEOMETRIC_GROUPS, place_instrument_and_tool, selection, solve
from torchcal.estimate.lm import _jacobi
from torchcal.estimate.problem import FreeParameters, prior_sigmas, residual_function, whitening
from torchcal.pipeline import Options, calibrate
from torchcal.robot import load_robot
from torchcal.sim import EffectSpec, SimConfig, simulate

F64 = torch.float64
META = torch.device("meta")


@pytest.fixture(scope="module")
def campaign():
    return simulate(
        SimConfig(robot="ur5", poses=48, test_poses=12, seed=4, effects=[EffectSpec.parse("compliance:2=60um")])
    )


def meta_robot(name: str = "ur5"):
    robot = load_robot(name).to(META)
    assert all(t.device == META for t in robot.state_dict().values())
    return robot


def on_meta(*shape: int) -> torch.Tensor:
    return torch.empty(*shape, dtype=F64, device=META)


# ---------------------------------------------------------------------------------------------- meta: shapes only


def test_meta_catches_a_constructor_without_device():
    """The premise of the meta tests: a CPU tensor meeting a meta one raises."""
    with pytest.raises(RuntimeError, match="device"):
        on_meta(5, 3) + torch.zeros(3, dtype=F64)


@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_meta_forward_kinematics(name):
    robot = meta_robot(name)
    q = on_meta(7, robot.dof)
    assert robot(q).shape == (7, 4, 4) and robot(q).device == META
    assert robot.probe_position(q).shape == (7, 3)
    p, J = robot.probe_jacobian(q)
    assert p.device == META and J.shape == (7, 3, robot.dof)
    F, T = robot.joint_frames(q)
    assert F.shape == (7, robot.dof, 4, 4) and T.device == META
    assert robot.gravity_torques(q, payload=1.5).shape == (7, robot.dof)


def test_meta_tracker_jacobian():
    import torch.fx.experimental._config as fx_config

    robot = meta_robot()
    q = on_meta(6, robot.dof)
    cols = [(g, i) for g, grp in robot.groups().items() for i in range(grp.delta.numel())]
    # which origin entries a parameter moves is found by torch.nonzero, data-dependent: on meta it may assume all
    with fx_config.patch(meta_nonzero_assume_all_nonzero=True):
        p, J = robot.tracker_jacobian(q, cols)
    assert p.shape == (6, 3) and J.shape == (6, 3, len(cols)) and J.device == META


def test_meta_measurement_model_with_every_named_effect():
    robot = meta_robot()
    effects = [
        Compliance(2, k=1e-6),
        Backlash(3, b=1e-5),
        Cyclic(4),
        Transmission(5, degree=2),
        Drift("t", "scale", rates=[1e-7]),
        Drift("temperature", "instrument"),
        KernelCorrection(6, 4),
        LearnedEffect(CorrectionNet(6, 5, seed=0)),
    ]
    model = MeasurementModel(robot, effects)  # effects are built on the CPU and follow the robot
    assert all(t.device == META for t in model.state_dict().values())
    ctx = Context(q=on_meta(9, 6), t=on_meta(9), temperature=on_meta(9), direction=on_meta(9, 6))
    out = model(ctx)
    assert out.shape == (9, 3) and out.device == META
    model.add(Compliance(5))
    assert model.effects[-1].k.device == META


def test_meta_residuals_jacobians_and_normal_equations():
    """What LM builds per iteration: whitened residuals with the prior's pseudo-observations, the Jacobian
    (analytic without effects, ``torch.func.jacfwd`` with them), ``N = J^T J``, its Jacobi scaling and the
    damped Cholesky factor."""
    import torch.fx.experimental._config as fx_config

    n = 8
    ctx, p = Context(q=on_meta(n, 6)), on_meta(n, 3)
    W = on_meta(n, 3, 3)  # whitening() stops at its positive-definiteness check (.item()); virtual test below
    for effects in ([], [Compliance(2), Cyclic(3)]):
        robot = load_robot("ur5")
        model = MeasurementModel(robot, effects)
        # which elements are free is read from the masks' values: chosen on the CPU, then the model moves
        sel, labels = selection(model, GEOMETRIC_GROUPS, effects=bool(effects))
        free = FreeParameters(model, sel, labels)
        model.to(META)
        units = {i.name: i.unit for i in robot.parameter_info() if i.group == "geometry"}
        prior = prior_sigmas(free, units, 1e-3, math.radians(0.1))
        assert prior.device == META
        fun = residual_function(model, free, ctx, p, W)  # a prior needs finite() checks on its values
        x = free.vector()
        assert x.device == META and fun(x).shape == (3 * n,)
        with fx_config.patch(meta_nonzero_assume_all_nonzero=True):
            J = fun.jacobian(x)
        assert J.shape == (3 * n, len(free)) and J.device == META
        N = J.T @ J
        s = _jacobi(N)
        Ns = N * s[:, None] * s[None, :]
        gs = (J.T @ fun(x)) * s
        L, _ = torch.linalg.cholesky_ex(Ns + 1e-3 * torch.eye(len(x), dtype=F64, device=x.device))
        assert L.device == META and gs.shape == (len(x),)


# ------------------------------------------------------------------------------------ the virtual device: values


def test_virtual_device_catches_a_constructor_without_device(monkeypatch):
    """The premise of the virtual tests: a CPU tensor of a forgotten device raises, values are real."""
    with virtual_device(monkeypatch) as dev:
        x = torch.ones(4, 3, dtype=F64, device=dev)
        assert isinstance(x, Virtual) and x.device == dev
        assert float((x * 2).sum()) == 24.0
        with pytest.raises(RuntimeError, match="without device"):
            x + torch.zeros(3, dtype=F64)
        assert float((x + torch.zeros(3, dtype=F64, device=x.device)).sum()) == 12.0


def test_place_instrument_and_tool_on_another_device(campaign, monkeypatch):
    """The review's failure: the rigid start once the robot is on another device."""
    m = campaign.train
    ref = load_robot("ur5")
    rms_ref = place_instrument_and_tool(ref, m.q, m.p)
    with virtual_device(monkeypatch) as dev:
        robot = load_robot("ur5").to(dev)
        d = m.to(dev)
        assert isinstance(d.q, Virtual) and isinstance(robot.tool.nominal, Virtual)
        rms = place_instrument_and_tool(robot, d.q, d.p)
        T, t = cpu(robot.instrument.nominal), cpu(robot.tool.nominal)
    assert rms == pytest.approx(rms_ref, rel=1e-12)
    torch.testing.assert_close(T, ref.instrument.nominal, rtol=0, atol=1e-12)
    torch.testing.assert_close(t, ref.tool.nominal, rtol=0, atol=1e-12)


def _fit(m, dev=None):
    robot = load_robot("ur5") if dev is None else load_robot("ur5").to(dev)
    m = m if dev is None else m.to(dev)
    place_instrument_and_tool(robot, m.q, m.p)
    model = MeasurementModel(robot)
    fit = solve(model, m, GEOMETRIC_GROUPS, Options().fit, "geometric", trajectory=False)
    W = whitening(model, Context(q=m.q), None, 15e-6, 1e-5)
    return model, fit, cpu(fit.result.x), cpu(W)


def test_least_squares_fit_on_another_device(campaign, monkeypatch):
    """Whitening, the identifiability analysis, the prior and weighted LM of the geometric stage."""
    _, fit_ref, x_ref, W_ref = _fit(campaign.train)
    with virtual_device(monkeypatch) as dev:
        _, fit, x, W = _fit(campaign.train, dev)
    assert fit.result.names == fit_ref.result.names
    torch.testing.assert_close(W, W_ref, rtol=1e-12, atol=0)
    torch.testing.assert_close(x, x_ref, rtol=1e-9, atol=1e-15)


def test_named_and_learned_effects_on_another_device(campaign, monkeypatch):
    """Score-test columns of candidate effects, and the kernel and network fits of the learned stage."""
    from torchcal.diagnose.candidates import Candidate
    from torchcal.diagnose.score import candidate_columns
    from torchcal.estimate.netfit import fit_net

    def run(dev=None):
        m = campaign.train if dev is None else campaign.train.to(dev)
        model, _, _, _ = _fit(campaign.train, dev)
        ctx = Context(q=m.q)
        W = whitening(model, ctx, None, 15e-6, 1e-5)
        cols = [
            cpu(candidate_columns(model, Candidate(k, j), ctx, m.p, W)) for k, j in (("compliance", 2), ("cyclic", 3))
        ]
        y = (m.p - model(ctx)).detach() @ model.robot.T_tracker_base()[:3, :3].detach()
        kern, info = fit_kernel_correction(model.robot, m.q[:36], y[:36], q_val=m.q[36:], y_val=y[36:], seed=0)
        net = CorrectionNet(6, 5, device=m.q.device)
        net.reset_parameters(torch.Generator().manual_seed(0))
        fit_net(net, m.q[:36], y[:36], val=(m.q[36:], y[36:]), iterations=5)
        with torch.no_grad():
            return cols, cpu(kern(model.robot, ctx)), cpu(net(m.q)), info["best"]

    cols_ref, k_ref, n_ref, best_ref = run()
    with virtual_device(monkeypatch) as dev:
        cols, k, n, best = run(dev)
    for a, b in zip(cols, cols_ref):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)  # jacfwd against columns of autograd JVPs
    assert best == best_ref
    torch.testing.assert_close(k, k_ref, rtol=1e-9, atol=1e-15)
    torch.testing.assert_close(n, n_ref, rtol=1e-9, atol=1e-15)


@pytest.mark.slow
def test_calibrate_and_predict_on_another_device(campaign, monkeypatch, tmp_path):
    """A whole kinematic calibration (gross-error screening, nominal and geometric fits, held-out errors),
    the run directory written from it, and ``predict`` on the same device; all equal to the CPU's."""
    from torchcal.estimate import robust
    from torchcal.report.rundir import write_run
    from torchcal.use.rundir import predict

    weighted = robust._weighted

    def with_jacobian(fun, sqrt_w, group):
        # the screening's reweighted residuals, given the analytic Jacobian their function carries: the virtual
        # device emulates torch.func.jacfwd column by column, twenty times slower (both runs use it)
        f = weighted(fun, sqrt_w, group)
        if hasattr(fun, "jacobian"):
            f.jacobian = lambda x: fun.jacobian(x) * robust._expand(sqrt_w, group, f(x).shape[-1])[:, None]
        return f

    monkeypatch.setattr(robust, "_weighted", with_jacobian)
    data = campaign.train
    ref = calibrate("ur5", data, Options(method="kinematic"))
    opts = Options(method="kinematic")
    with virtual_device(monkeypatch) as dev:
        object.__setattr__(opts, "device", str(dev))  # Options accepts cpu and cuda only; set the virtual one directly
        run = calibrate("ur5", data, opts)
        assert isinstance(run.data.q, Virtual) and isinstance(run.robot.geometry.delta, Virtual)
        out = write_run(run, tmp_path / "run")
        p = predict(out, campaign.test, device=dev)
        assert not isinstance(p, Virtual)  # predict hands back CPU tensors
    assert [s.name for s in run.stages] == [s.name for s in ref.stages]
    for a, b in zip(run.stages, ref.stages):
        assert a.rmse == pytest.approx(b.rmse, rel=1e-9)
    state = torch.load(out / "model.pt", weights_only=True)
    assert all(type(v) is torch.Tensor and v.device.type == "cpu" for v in state.values())
    assert all(v.dtype in (F64, torch.bool) for v in state.values())
    torch.testing.assert_close(p, predict(out, campaign.test), rtol=1e-9, atol=1e-12)


class _InlineExecutor:
    """A ``ThreadPoolExecutor`` that runs each job at once in the calling thread."""

    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args, **kwargs):
        from concurrent.futures import Future

        f = Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except BaseException as e:  # handed to result(), as a pool does
            f.set_exception(e)
        return f

    def map(self, fn, *iterables):
        return [fn(*a) for a in zip(*iterables)]


def test_adaptive_filters_features_on_the_data_device():
    """The integrated method's adaptive filter draws its random features on the CPU's generator and places them on
    the data's device: on a GPU they once stayed on the CPU, and the filter's first step failed."""
    from torchcal.filter.adaptive import random_features

    ref = random_features(dof=6, hidden=8, seed=3)
    with virtual_device() as dev:
        net = random_features(dof=6, hidden=8, seed=3, device=dev)
        assert all(isinstance(p, Virtual) for p in net.parameters())
    for a, b in zip(net.parameters(), ref.parameters(), strict=True):
        torch.testing.assert_close(cpu(a), b, rtol=0, atol=0)


def _default_method_on_virtual(monkeypatch) -> None:
    """What the default method needs to run on the virtual device (module docstring)."""
    import torchcal.pipeline.options as pipeline_run
    from torchcal.effects import gp
    from torchcal.estimate import robust
    from torchcal.pipeline import learned

    candidates = importlib.import_module("torchcal.diagnose.candidates")  # the package exports a function so named
    weighted, resolve = robust._weighted, pipeline_run.resolve_device
    # the virtual device is a dispatch mode, and modes are per thread: the learned stage's worker threads (the GP
    # beside the network, the evidence fit's starts, the posterior's blocks) run inline here
    monkeypatch.setattr(learned, "ThreadPoolExecutor", _InlineExecutor)
    monkeypatch.setattr(gp, "ThreadPoolExecutor", _InlineExecutor)
    monkeypatch.setattr(gp, "BLOCK_WORKERS", 1)

    def with_jacobian(fun, sqrt_w, group):  # as in test_calibrate_and_predict_on_another_device
        f = weighted(fun, sqrt_w, group)
        if hasattr(fun, "jacobian"):
            f.jacobian = lambda x: fun.jacobian(x) * robust._expand(sqrt_w, group, f(x).shape[-1])[:, None]
        return f

    monkeypatch.setattr(robust, "_weighted", with_jacobian)
    # Options re-checks its device when the learned stage copies it (dataclasses.replace): let the virtual one pass
    monkeypatch.setattr(pipeline_run, "resolve_device", lambda d: META if str(d) == "meta" else resolve(d))
    # two stations make the tracker's own terms candidates: 20 score tests and refits, each op a Python call on the
    # virtual device (155 s with all of them, 93 s with the range offset alone, this machine quiet); one term keeps
    # the instrument effects' device path in the chain, the others' selection is tested on the CPU (test_instrument)
    monkeypatch.setattr(candidates, "INSTRUMENT_TERMS", ("range",))


@pytest.mark.slow
def test_chain_of_the_default_method_on_another_device(monkeypatch, tmp_path):
    """The default method on two stations and two probes with a 6-D probe's orientation (the learned stage's
    groups, the orientation rows' Jacobian), then predict and an update from the prior, on the virtual device:
    on a GPU the learned stage's group split once indexed the CPU's row indices with the GPU's group labels."""
    from torchcal.report.rundir import write_run
    from torchcal.use.rundir import load_prior, predict

    _default_method_on_virtual(monkeypatch)
    camp = simulate(
        SimConfig(
            robot="ur5",
            poses=80,
            test_poses=24,
            seed=3,
            stations=2,
            probes=2,
            orientation_sigma_deg=0.01,
            effects=[EffectSpec.parse("compliance:2=200um")],
        )
    )
    ref = calibrate("ur5", camp.train, Options())
    opts = Options()
    with virtual_device(monkeypatch) as dev:
        object.__setattr__(opts, "device", str(dev))
        run = calibrate("ur5", camp.train, opts)
        out = write_run(run, tmp_path / "run")
        p = predict(out, camp.test, device=dev)
        update = calibrate("ur5", camp.test.subset(torch.arange(0, 12)), opts, prior=load_prior(out))
        assert isinstance(update.data.q, Virtual)
    assert [s.name for s in run.stages] == [s.name for s in ref.stages]
    assert run.stages[-1].rmse == pytest.approx(ref.stages[-1].rmse, rel=1e-6)
    torch.testing.assert_close(p, predict(out, camp.test), rtol=1e-9, atol=1e-12)


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("TORCHCAL_DEVICE_AUTO") != "1",
    reason="the default method on the virtual device takes about 90 s; set TORCHCAL_DEVICE_AUTO=1 to run it",
)
def test_default_method_on_another_device(monkeypatch):
    """The default method end to end (screening, kinematic, the closed loop's score tests and joint refits, the
    Gaussian process, kernel and network of the learned stage) on the virtual device, against the CPU."""
    _default_method_on_virtual(monkeypatch)
    effects = [EffectSpec.parse("compliance:2=60um"), EffectSpec.parse("field=0.05mm")]
    camp = simulate(SimConfig(robot="ur5", poses=150, test_poses=10, seed=2, effects=effects))
    ref = calibrate("ur5", camp.train, Options())
    opts = Options()
    with virtual_device(monkeypatch) as dev:
        object.__setattr__(opts, "device", str(dev))
        run = calibrate("ur5", camp.train, opts)
    assert [s.name for s in run.stages] == [s.name for s in ref.stages]
    assert len(run.stages) >= 3  # a named effect or the learned stage was found, so their paths ran
    for a, b in zip(run.stages, ref.stages):
        assert a.rmse == pytest.approx(b.rmse, rel=1e-6)  # score columns by autograd JVPs instead of jacfwd


# ------------------------------------------------------------------------------------------------------ CUDA


NO_CUDA = pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="no CUDA device on this machine (the meta and virtual-device tests check device cleanliness without one)",
)


@NO_CUDA
@pytest.mark.parametrize("method", ["kinematic", "auto", "pcm", "kinematic+ann", "integrated"])
def test_calibrate_on_cuda_matches_cpu(method):
    effects = [EffectSpec.parse("compliance:2=60um")]
    if method == "integrated":  # a continuous trajectory: the filter's samples in order
        size = dict(trajectory=True, path="multisine", samples=200, train_samples=160)
    else:
        size = dict(poses=150, test_poses=30)
    camp = simulate(SimConfig(robot="ur5", seed=5, effects=effects, **size))
    ref = calibrate("ur5", camp.train, Options(method=method))
    run = calibrate("ur5", camp.train, Options(method=method, device="cuda"))
    assert run.data.q.device.type == "cuda" and run.robot.device.type == "cuda"
    assert [s.name for s in run.stages] == [s.name for s in ref.stages]
    # the geometric fit to 1e-9; the learned stage's iterative fits (L-BFGS, network LM) carry the last-bit
    # differences of CUDA's reduction order further
    rel = 1e-9 if method == "kinematic" else 1e-6
    for a, b in zip(run.stages, ref.stages, strict=True):
        assert a.rmse == pytest.approx(b.rmse, rel=rel)
        assert a.holdout_errors.dtype == F64 and a.holdout_errors.device.type == "cuda"


@NO_CUDA
def test_cli_calibrate_and_predict_on_cuda(tmp_path):
    from torchcal.cli import main
    from torchcal.data import read_measurements

    sim = tmp_path / "sim"
    assert (
        main(["simulate", "--robot", "ur5", "--out", str(sim), "--poses", "120", "--test-poses", "20", "--quiet"]) == 0
    )
    for dev in ("cpu", "cuda"):
        args = ["calibrate", str(sim / "train.csv"), "--robot", "ur5", "--method", "kinematic", "--quiet"]
        assert main([*args, "--out", str(tmp_path / f"cal-{dev}"), "--device", dev]) == 0
        pred = ["predict", str(tmp_path / f"cal-{dev}"), str(sim / "test.csv"), "--quiet"]
        assert main([*pred, "--out", str(tmp_path / f"pred-{dev}.csv"), "--device", dev]) == 0
    a, b = (read_measurements(tmp_path / f"pred-{d}.csv", require_positions=True).p for d in ("cpu", "cuda"))
    torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-12)


def _csv_numbers(path) -> dict[str, list[float]]:
    """A torchcal CSV's numeric columns, by name (comment lines and text columns left out)."""
    import csv

    lines = [line for line in open(path) if not line.startswith("#")]
    rows = list(csv.DictReader(lines))
    out: dict[str, list[float]] = {}
    for name in rows[0]:
        try:
            out[name] = [float(r[name]) for r in rows]
        except ValueError:
            continue
    return out


def _assert_same_numbers(a, b, what: str, atol: float) -> None:
    got, ref = _csv_numbers(b), _csv_numbers(a)
    assert got.keys() == ref.keys(), what
    for name in ref:
        torch.testing.assert_close(
            torch.tensor(got[name]), torch.tensor(ref[name]), rtol=1e-6, atol=atol, msg=f"{what}: {name}"
        )


@NO_CUDA
def test_chain_of_a_cuda_run_matches_cpu(tmp_path):
    """A user's chain on a run calibrated on the GPU (the default method, two stations and two probes with a 6-D
    probe's orientation): ``predict`` on the GPU, then ``compensate``, ``station`` and ``calibrate --prior`` (on
    the GPU), each against the same chain of a CPU run: a run written from the GPU reads back as the CPU's."""
    from torchcal.cli import main
    from torchcal.data import read_measurements, write_measurements

    sim = tmp_path / "sim"
    args = ["simulate", "--robot", "ur5", "--out", str(sim), "--poses", "80", "--test-poses", "24", "--seed", "3"]
    args += ["--stations", "2", "--probes", "2", "--orientation", "0.01", "--effect", "compliance:2=200um"]
    assert main([*args, "--quiet"]) == 0
    test = read_measurements(sim / "test.csv", require_positions=True)
    first = test.subset(torch.arange(0, 12))
    write_measurements(tmp_path / "points.csv", first)
    write_measurements(tmp_path / "targets.csv", test.subset(torch.arange(12, 20)))
    for dev in ("cpu", "cuda"):
        run = tmp_path / f"cal-{dev}"
        cal = ["calibrate", str(sim / "train.csv"), "--robot", "ur5", "--seed", "1", "--quiet", "--device", dev]
        assert main([*cal, "--out", str(run)]) == 0
        pred = ["predict", str(run), str(sim / "test.csv"), "--out", str(tmp_path / f"pred-{dev}.csv")]
        assert main([*pred, "--device", dev, "--quiet"]) == 0
        comp = ["compensate", str(run), str(tmp_path / "targets.csv"), "--out", str(tmp_path / f"q-{dev}.csv")]
        assert main([*comp, "--quiet"]) == 0
        st = ["station", str(run), str(tmp_path / "points.csv"), "--out", str(tmp_path / f"st-{dev}"), "--quiet"]
        assert main(st) == 0
        prior = ["calibrate", str(tmp_path / "points.csv"), "--robot", "ur5", "--prior", str(run), "--quiet"]
        assert main([*prior, "--out", str(tmp_path / f"upd-{dev}"), "--device", dev]) == 0
    reports = [json.loads((tmp_path / f"cal-{d}" / "report.json").read_text()) for d in ("cpu", "cuda")]
    assert [e["name"] if isinstance(e, dict) else e for e in reports[1]["effects"]] == [
        e["name"] if isinstance(e, dict) else e for e in reports[0]["effects"]
    ]
    assert reports[1]["rmse_after_mm"] == pytest.approx(reports[0]["rmse_after_mm"], rel=1e-6)
    _assert_same_numbers(tmp_path / "pred-cpu.csv", tmp_path / "pred-cuda.csv", "predict", atol=1e-9)
    _assert_same_numbers(tmp_path / "q-cpu.csv", tmp_path / "q-cuda.csv", "compensate", atol=1e-9)
    for name in ("st", "upd"):
        a, b = (json.loads((tmp_path / f"{name}-{d}" / "report.json").read_text()) for d in ("cpu", "cuda"))
        assert b["rmse_after_mm"] == pytest.approx(a["rmse_after_mm"], rel=1e-6, abs=1e-9), name


def test_device_option_errors():
    from torchcal._device import resolve_device
    from torchcal.errors import OptionError

    assert resolve_device("cpu") == torch.device("cpu") and resolve_device(None) == torch.device("cpu")
    with pytest.raises(OptionError, match="expected cpu, cuda or cuda:N"):
        Options(device="mps")
    with pytest.raises(OptionError, match="not a device name"):
        Options(device="gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(OptionError, match="no CUDA device"):
            Options(device="cuda")
    else:
        with pytest.raises(OptionError, match="CUDA device"):
            resolve_device(f"cuda:{torch.cuda.device_count()}")


def test_cli_device_without_cuda_exits_2(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: the error path needs a machine without it")
    from torchcal.cli import main

    camp = simulate(SimConfig(robot="ur5", poses=40, test_poses=5, seed=1))
    from torchcal.data import write_measurements

    write_measurements(tmp_path / "train.csv", camp.train)
    code = main(
        [
            "calibrate",
            str(tmp_path / "train.csv"),
            "--robot",
            "ur5",
            "--out",
            str(tmp_path / "cal"),
            "--device",
            "cuda",
            "--quiet",
        ]
    )
    assert code == 2 and "no CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "cal").exists()


# ------------------------------------------------------------------------------------------ the static count

#: Packages and modules whose tensors stay on the CPU by design: file readers and writers (data are read on the
#: CPU and moved once by the run), the simulator (seeded campaigns, written to files), plots, the experiments
#: behind the scripts, and the seeded splits of ``stats`` (integer indices, valid on every device).
CPU_BY_DESIGN = (
    "torchcal/data/",
    "torchcal/sim/",
    "torchcal/robot/load.py",
    "torchcal/robot/export.py",
    "torchcal/report/markdown.py",
    "torchcal/report/ekf_plots.py",
    "torchcal/stats.py",
)

#: Constructors without ``device=`` that are right where they are: (file, the call's source) -> why.
ALLOWED = {
    (
        "torchcal/use/compensate.py",
        "torch.tensor([length if k == 'prismatic' else angle for k in joint_types], dtype=F64)",
    ): "a file's unit factors at the I/O edge, where the rows are on the CPU as the files they are written to",
    ("torchcal/use/station.py", "torch.rand(REGION_POSES, model.robot.dof, generator=g, dtype=F64)"): (
        "CPU generator (the same poses on every device), moved (.to) to the region's device"
    ),
    ("torchcal/robot/readings.py", "torch.as_tensor(A, dtype=torch.float64)"): (
        "validates the description's nested list before any robot exists: host-side, read with float()"
    ),
    ("torchcal/estimate/problem.py", "torch.tensor([i for _, i in kin], dtype=torch.long)"): (
        "host-side indices: linear_kinematics reads them with int() and moves them (.to) where it indexes"
    ),
    ("torchcal/robot/ur_urdf.py", "torch.tensor(qs[:, order], dtype=torch.float64)"): (
        "the generator's self-check against pytorch-kinematics, numpy in and out"
    ),
    ("torchcal/estimate/lm.py", "torch.tensor(p, dtype=torch.float64)"): "a Python number in, a float out",
    ("torchcal/estimate/robust.py", "torch.tensor(k / 2.0, dtype=F64)"): "a Python number in, a float out",
    ("torchcal/estimate/robust.py", "torch.tensor(max(x, 0.0) / 2.0, dtype=F64)"): "a Python number in, a float out",
    ("torchcal/use/compensate.py", "torch.rand(robot.dof, generator=g, dtype=F64)"): "CPU generator, moved (.to)",
    ("torchcal/effects/learned.py", "torch.randn(layer.weight.shape, generator=generator, dtype=torch.float64)"): (
        "CPU generator (the same weights on every device), copied into the layer"
    ),
    ("torchcal/effects/learned.py", "torch.randn(layer.bias.shape, generator=generator, dtype=torch.float64)"): (
        "CPU generator (the same weights on every device), copied into the layer"
    ),
    ("torchcal/effects/gp.py", "torch.full((d,), 0.4 / d, dtype=F64)"): "_initial: numbers only, moved by the caller",
    ("torchcal/effects/base.py", "torch.tensor([lo, hi], dtype=torch.float64)"): (
        "a constructor's numbers: effects are built on CPU and moved with the model (MeasurementModel.add)"
    ),
    ("torchcal/effects/gp.py", "torch.full((d,), 0.5 if periodic else 0.5, dtype=F64)"): "_initial, as above",
    ("torchcal/effects/gp.py", "torch.tensor([math.log(0.5)], dtype=F64)"): "_initial, as above",
    ("torchcal/effects/gp.py", "torch.full((d,), math.log(1.0), dtype=F64)"): "_initial, as above",
    ("torchcal/effects/gp.py", "torch.tensor([math.log(0.1)], dtype=F64)"): "_initial, as above",
    ("torchcal/effects/gp.py", "torch.rand(k, generator=generator, dtype=F64)"): "_random_initial: CPU generator",
    ("torchcal/effects/gp.py", "torch.rand(1, generator=generator, dtype=F64)"): "_random_initial: CPU generator",
    ("torchcal/effects/gp.py", "torch.rand(d + 1, generator=generator, dtype=F64)"): "_random_initial: CPU generator",
    ("torchcal/effects/gp.py", "torch.tensor([math.log(1.0 - signal)], dtype=F64)"): "_random_initial, as above",
    ("torchcal/effects/registry.py", "torch.zeros(cfg['n_region'], cfg['dof'], dtype=torch.float64)"): (
        "a model rebuilt from model.json on the CPU, then loaded and moved"
    ),
    ("torchcal/diagnose/forms.py", "torch.zeros(0, dtype=F64)"): "the empty 'none' form, never combined",
    ("torchcal/diagnose/forms.py", "torch.zeros(0, 0, dtype=F64)"): "the empty 'none' form, never combined",
    (
        "torchcal/diagnose/forms.py",
        "torch.logspace(math.log10(span / 200), math.log10(span * 30), n_grid, dtype=F64)",
    ): ("a grid of numbers (.tolist())"),
    ("torchcal/diagnose/localise.py", "torch.linspace(lo, hi, N_GRID, dtype=F64)"): "a grid moved on the next line",
    ("torchcal/diagnose/localise.py", "torch.tensor([-1.0, 1.0], dtype=F64)"): "a grid moved on the next line",
    ("torchcal/filter/adaptive.py", "torch.linspace(0, len(q) - 1, min(len(q), max_poses))"): "an index (.long())",
    ("torchcal/filter/adaptive.py", "torch.tensor([b[0], b[0] + len(b[2]) - 1])"): "an integer index",
}

CONSTRUCTORS = {
    "zeros", "ones", "eye", "tensor", "as_tensor", "arange", "empty", "full", "linspace", "logspace", "randn",
    "rand", "randint", "randperm", "from_numpy",
}  # fmt: skip
INTEGER_INDEX = {"arange", "randperm", "randint"}  # without a floating dtype: indices, valid on every device


def _floating_dtype(call: ast.Call) -> bool:
    kw = {k.arg: k.value for k in call.keywords}
    return "dtype" in kw and "long" not in ast.unparse(kw["dtype"]) and "int" not in ast.unparse(kw["dtype"])


def constructors_without_device(root: Path) -> list[tuple[str, int, str]]:
    """``(file, line, source)`` of every ``torch.<constructor>(...)`` in the package without ``device=`` (or
    ``**kw``), outside :data:`CPU_BY_DESIGN`, outside an ``__init__`` (modules are built on the CPU and moved as a
    whole; ``MeasurementModel`` moves its effects) and not an integer index."""
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).as_posix()
        if rel.startswith(CPU_BY_DESIGN):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        in_init = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef) and node.name == "__init__":
                in_init |= {id(n) for n in ast.walk(node)}
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            f = node.func
            if not (isinstance(f.value, ast.Name) and f.value.id == "torch" and f.attr in CONSTRUCTORS):
                continue
            if any(k.arg in ("device", None) for k in node.keywords) or id(node) in in_init:
                continue
            if f.attr in INTEGER_INDEX and not _floating_dtype(node):
                continue
            out.append((rel, node.lineno, ast.unparse(node)))
    return out


def test_constructors_take_the_device_of_their_data():
    root = Path(torchcal.__file__).parent
    found = constructors_without_device(root)
    unexplained = [f"{f}:{line}: {src}" for f, line, src in found if (f, src) not in ALLOWED]
    assert not unexplained, (
        "tensor constructors without device= (give them the device of the tensor they combine with, e.g. "
        "device=q.device, or add them to ALLOWED with the reason):\n" + "\n".join(unexplained)
    )
    stale = set(ALLOWED) - {(f, src) for f, _, src in found}
    assert not stale, f"ALLOWED entries that no longer occur: {sorted(stale)}"


def test_the_static_count_sees_a_missing_device(tmp_path):
    pkg = tmp_path / "torchcal"
    pkg.mkdir()
    (pkg / "m.py").write_text(
        "import torch\n"
        "def f(q):\n"
        "    return q + torch.zeros(3, dtype=torch.float64)\n"
        "def g(q):\n"
        "    return q[torch.arange(2)] + torch.ones(3, dtype=q.dtype, device=q.device)\n"
        "class A:\n"
        "    def __init__(self):\n"
        "        self.x = torch.zeros(3)\n"
    )
    assert [(line, src) for _, line, src in constructors_without_device(pkg)] == [
        (3, "torch.zeros(3, dtype=torch.float64)")
    ]


def test_calibration_path_is_float64():
    """No float32 anywhere in the package, and every floating constructor outside CPU_BY_DESIGN names its dtype
    (torch's default is float32)."""
    root = Path(torchcal.__file__).parent
    for path in root.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "torch.float32" not in text and ".float()" not in text and "set_default_dtype" not in text, path
    floating = {"zeros", "ones", "eye", "empty", "full", "linspace", "logspace", "randn", "rand"}
    missing = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).as_posix()
        if rel.startswith(CPU_BY_DESIGN):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                f = node.func
                if isinstance(f.value, ast.Name) and f.value.id == "torch" and f.attr in floating:
                    if not any(k.arg in ("dtype", None) for k in node.keywords):
                        missing.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
    allowed = {"torchcal/filter/adaptive.py"}  # the linspace of ALLOWED: an index, cast with .long()
    assert [m for m in missing if m.split(":")[0] not in allowed] == []
