"""Identifiability: the paper's dependent groups on a UR5, duplicates, URDF robots."""

import math
import re
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.fit import selection as _selection
from torchcal.estimate.fit import solve
from torchcal.estimate.identifiability import DEFAULT_PRIOR_RATIO, analyse, preference_order
from torchcal.estimate.problem import FreeParameters, jacobian_of, prior_sigmas, residual_function, whitening
from torchcal.estimate.rigid import fit_instrument_and_tool
from torchcal.pipeline import Options
from torchcal.sim import SimConfig, simulate

F64 = torch.float64


def test_duplicate_columns_keep_the_preferred_one():
    g = torch.Generator().manual_seed(0)
    J = torch.randn(50, 3, generator=g, dtype=F64)
    J = torch.cat([J, 2.0 * J[:, :1], J[:, 1:2] - J[:, 2:3]], dim=1)  # col3 ~ col0, col4 = col1 - col2
    ida = analyse(J, ["a", "b", "c", "d", "e"], order=[3, 0, 1, 2, 4])
    assert ida.free.tolist() == [False, True, True, True, False]
    assert sorted(map(sorted, ida.groups)) == [["a", "d"], ["b", "c", "e"]]


def _ur5_problem(lever=(0.05, 0.0, 0.1)):
    c = simulate(
        SimConfig(
            robot="ur5",
            poses=300,
            test_poses=0,
            seed=11,
            lever_arm=lever,
            lever_arm_sigma=0.0,
            sigma_tracker=0.0,
            sigma_joint_deg=0.0,
            tracker_tilt_deg=0.0,
        )
    )
    robot = torchcal.load_robot("ur5")
    model = MeasurementModel(robot)
    with torch.no_grad():
        T, t, _ = fit_instrument_and_tool(robot(c.train.q), c.train.p)
        robot.instrument.set_matrix(T)
        robot.tool.nominal.copy_(torch.tensor(lever, dtype=F64))
    ctx = Context(q=c.train.q)
    W = whitening(model, ctx, None, 15e-6, 0.0)
    groups = robot.groups()
    sel = {f"robot.{g}.delta": groups[g].mask for g in groups}
    labels = {f"robot.{g}.delta": groups[g].names for g in groups}
    free = FreeParameters(model, sel, labels)
    J = torch.func.jacfwd(residual_function(model, free, ctx, c.train.p, W))(free.vector())
    return analyse(J, free.names, preference_order(free.names))


def test_ur5_with_a_vertical_tracker_finds_the_papers_groups():
    # Horvath & Neuner (2024), Sec. 2.2.3: {dtheta1, r_z}, {d1, t_z}, {d2, d3, d4}, {a6, t_x}, {d6, t_z},
    # {alpha6, dtheta6, t_y}, with d1, d3, d4, d6, dtheta1, dtheta6, alpha6, a6 held fixed
    ida = _ur5_problem()
    fixed = sorted(f["name"] for f in ida.fixed)
    assert fixed == sorted(["d1", "d3", "d4", "d6", "theta1", "theta6", "alpha6", "a6"])
    groups = sorted(sorted(g) for g in ida.groups)
    expected = [
        ["instrument.rz", "theta1"],
        ["d1", "instrument.tz"],
        ["d2", "d3", "d4"],
        ["a6", "tool.x"],
        ["d6", "tool.z"],
        ["alpha6", "theta6", "tool.y"],
    ]
    assert groups == sorted(sorted(g) for g in expected)
    # every structural dependency is exact to round-off, every kept parameter clearly independent
    assert max(f["independence"] for f in ida.fixed) < 1e-12
    assert float(ida.independence[ida.free].min()) > 1e-3


def test_urdf_robot_redundant_errors_are_resolved_and_noise_free_data_recovered():
    c = simulate(
        SimConfig(robot="panda.urdf", poses=250, test_poses=50, seed=12, sigma_tracker=0.0, sigma_joint_deg=0.0)
    )
    robot = torchcal.load_robot("panda.urdf")
    model = MeasurementModel(robot)
    with torch.no_grad():
        T, t, _ = fit_instrument_and_tool(robot(c.train.q), c.train.p)
        robot.instrument.set_matrix(T)
        robot.tool.nominal.copy_(t)
    opts = Options.of(sigma_joint=0.0, prior_length=None, prior_angle=None, stat_tol=0.0)  # the bare solver
    fit = solve(model, c.train, ("geometry", "instrument", "tool"), opts.fit, "geometric", trajectory=False)
    ida = fit.identifiability
    assert ida.rank < len(ida.names)  # 6 errors per joint are heavily redundant
    assert fit.result.status == "converged"
    with torch.no_grad():
        err = (model(Context(q=c.test.q)) - c.test.p).norm(dim=-1).max()
    assert float(err) < 1e-9


GEN3 = Path(__file__).resolve().parent / "data" / "gen3_rounded.urdf"


def _exact_gen3(tmp_path: Path) -> Path:
    """The fixture with exact constants: 1.5708 -> pi/2, 3.1416 -> pi."""

    def exact(v: str) -> str:
        x = float(v)
        if abs(abs(x) - 1.5708) < 1e-12:
            return repr(math.copysign(math.pi / 2, x))
        return repr(math.pi) if abs(x - 3.1416) < 1e-12 else v

    text = re.sub(
        r'rpy="(\S+) (\S+) (\S+)"', lambda m: 'rpy="' + " ".join(map(exact, m.groups())) + '"', GEN3.read_text()
    )
    assert not re.findall(r'rpy="[^"]*(1\.5708|3\.1416)', text) and text.count(repr(math.pi / 2)) == 6
    out = tmp_path / "gen3_exact.urdf"
    out.write_text(text)
    return out


def _geometric_fit(spec, train, tolerance=False, **fit):
    """The geometric fit of ``spec`` to ``train``: under the refits' priors, or with ``tolerance`` the geometric
    stage's (manufacturing tolerances, :meth:`~torchcal.pipeline.options.FitSettings.geometric`)."""
    robot = torchcal.load_robot(str(spec))
    model = MeasurementModel(robot)
    with torch.no_grad():
        T, t, _ = fit_instrument_and_tool(robot(train.q), train.p)
        robot.instrument.set_matrix(T)
        robot.tool.nominal.copy_(t)
    opts = Options.of(method="kinematic", **fit).fit
    opts = opts.geometric() if tolerance else opts
    return solve(model, train, ("geometry", "instrument", "tool"), opts, "geometric", trajectory=False)


def test_rounded_constants_keep_what_exact_constants_keep(tmp_path):
    # issue 14.5: a vendor URDF with 1.5708 for pi/2 turns exact dependencies into near ones (sine ~4e-6, above
    # the structural 1e-6); the fit kept pairs correlated at +-1.000 whose sigma was their prior
    c = simulate(SimConfig(robot=str(GEN3), poses=300, test_poses=0, seed=3))
    rounded = _geometric_fit(GEN3, c.train)
    exact = _geometric_fit(_exact_gen3(tmp_path), c.train)
    kept_r = [n for n, f in zip(rounded.identifiability.names, rounded.identifiability.free.tolist()) if f]
    kept_e = [n for n, f in zip(exact.identifiability.names, exact.identifiability.free.tolist()) if f]
    assert kept_r == kept_e
    assert rounded.result.status == "converged"
    # the structural tolerance alone keeps the rounded constants' near-dependencies
    robot = rounded.free.module.robot
    ctx = Context(q=c.train.q)
    sel, labels = _selection(rounded.free.module, ("geometry", "instrument", "tool"))
    free = FreeParameters(rounded.free.module, sel, labels)
    W = whitening(rounded.free.module, ctx, c.train.sigma, 15e-6, math.radians(0.0005))
    J = jacobian_of(residual_function(rounded.free.module, free, ctx, c.train.p, W))(free.vector())
    structural = analyse(J, free.names, preference_order(free.names))
    assert structural.rank >= rounded.identifiability.rank + 4
    assert "Actuator2.ty" in [n for n, f in zip(structural.names, structural.free.tolist()) if f]
    assert "Actuator2.ty" not in kept_r
    reason = next(f["reason"] for f in rounded.identifiability.fixed if f["name"] == "Actuator2.ty")
    assert "no better than its prior" in reason
    # every kept parameter with a prior is determined by the data, not by its prior alone
    units = {i.name: i.unit for i in robot.parameter_info() if i.group == "geometry"}
    ps = prior_sigmas(rounded.free, units, 1e-3, math.radians(0.1))
    ratio = rounded.result.cofactor.diagonal().sqrt() / ps
    assert float(ratio[torch.isfinite(ps)].max()) < 0.9


STRUCTURAL_UR = ["d1", "d3", "d4", "d6", "theta1", "theta6", "alpha6", "a6"]


def test_prior_tolerance_keeps_the_clean_ur_sets():
    # clean campaigns under a wide prior (1 mm, 0.1 deg): the tolerance from noise and prior fixes nothing the
    # structural one keeps
    for robot_name in ("ur5", "ur10"):
        c = simulate(SimConfig(robot=robot_name, poses=200, test_poses=0, seed=21))
        fit = _geometric_fit(robot_name, c.train)
        ida = fit.identifiability
        assert sorted(f["name"] for f in ida.fixed) == sorted(STRUCTURAL_UR)
        assert ida.prior_ratio == DEFAULT_PRIOR_RATIO == ida.to_dict()["prior_ratio"]


def test_the_tolerance_prior_holds_near_nominal_what_the_rows_tell_no_better():
    # the geometric stage's prior (manufacturing tolerances, 0.1 mm and 0.01 deg) holds a wrist offset 200 poses
    # tell no better than it at its nominal value, names it so and keeps its doubt in the run's covariance
    c = simulate(SimConfig(robot="ur5", poses=200, test_poses=0, seed=21))
    ida = _geometric_fit("ur5", c.train, tolerance=True).identifiability
    by_prior = [f for f in ida.fixed if f["name"] not in STRUCTURAL_UR]
    assert by_prior, ida.fixed
    for f in by_prior:
        assert "held near nominal by the prior" in f["reason"] and f["name"] in ida.prior_held
    assert not any(n in ida.prior_held for n in STRUCTURAL_UR)  # structurally dependent: no doubt of their own


def test_weak_after_fit_holds_a_parameter_its_prior_dominates():
    from torchcal.estimate.identifiability import weak_after_fit

    names = ["d2", "instrument.ty", "tool.z"]
    ps = torch.tensor([1e-3, 0.5, 0.5], dtype=F64)
    # tool.z: posterior 0.4 m against a 0.5 m prior (0.8 > 0.71): held; d2 is not a candidate
    Q = torch.diag(torch.tensor([1e-6, 1e-8, 0.16], dtype=F64))
    held = weak_after_fit(names, Q, ps, torch.tensor([False, True, True]), {n: "m" for n in names})
    assert [h["name"] for h in held] == ["tool.z"]
    assert "400 mm, 0.80 of its prior 500 mm" in held[0]["reason"]
    assert weak_after_fit(names, Q * 0.25, ps, torch.tensor([False, True, True])) == []  # 0.40: kept


def test_weak_after_fit_gives_up_the_later_of_a_correlated_pair_unless_the_data_reject_its_prior():
    from torchcal.estimate.identifiability import weak_after_fit

    names = ["instrument.tx", "instrument.ty", "tool.z"]  # tool.z comes after the instrument in preference
    ps = torch.full((3,), 0.5, dtype=F64)
    sd = torch.tensor([1e-5, 4e-3, 4e-3], dtype=F64)
    rho = torch.eye(3, dtype=F64)
    rho[1, 2] = rho[2, 1] = -0.9999
    Q = rho * sd[:, None] * sd[None, :]
    cand = torch.ones(3, dtype=torch.bool)
    held = weak_after_fit(names, Q, ps, cand, x=torch.tensor([0.0, 1e-3, 2e-3], dtype=F64))
    assert [(h["name"], h["depends_on"]) for h in held] == [("tool.z", ["instrument.ty"])]
    assert "correlated -0.9999" in held[0]["reason"]
    # fitted 95 mm from its prior's centre with a 4 mm sigma: the data determine it despite the correlation
    kept = weak_after_fit(names, Q, ps, cand, x=torch.tensor([0.0, 0.0, 0.095], dtype=F64))
    assert [(k["name"], k["held"]) for k in kept] == [("tool.z", False)]  # a warning for the report, not a hold
    assert "23.8 sigma" in kept[0]["reason"]
    rho[1, 2] = rho[2, 1] = -0.99  # below 0.999: nothing to hold
    assert weak_after_fit(names, rho * sd[:, None] * sd[None, :], ps, cand) == []


def _triple(k: float = 700.0, a: float = 1e-6):
    """Three parameters tied along ``(1, 1, -1)``: ``Q = a (I + k u u^T)``; each pair correlated ``k / (1 + k)``
    (0.9986 at k = 700: below the pairwise 0.999), the unit-diagonal normal matrix's smallest eigenvalue
    ``1 / (1 + 2 k)`` (7.1e-4: below 1 - 0.999)."""
    names = ["instrument[S1].tx", "instrument[S2].tx", "tool.z"]
    u = torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    return names, a * (torch.eye(3, dtype=F64) + k * u[:, None] * u[None, :])


def test_weak_combinations_find_a_direction_no_pair_shows():
    from torchcal.estimate.identifiability import weak_combinations

    names, Q = _triple()
    rho = Q[0, 1] / Q[0, 0]
    assert 0.998 < float(rho) < 0.999  # no pair beyond the pairwise rule
    (combo,) = weak_combinations(names, Q, torch.ones(3, dtype=torch.bool))
    assert set(combo.names) == set(names) and combo.eigenvalue == pytest.approx(1 / 1401, rel=1e-9)
    d = dict(zip(combo.names, combo.direction))
    assert d["tool.z"] / d["instrument[S1].tx"] == pytest.approx(-1.0, rel=1e-9)
    assert weak_combinations(*_triple(k=400.0), torch.ones(3, dtype=torch.bool)) == []  # 1/801 > 1e-3: not weak


def test_weak_after_fit_holds_a_weak_combination_where_its_prior_fits_or_the_fit_defies_the_prior():
    from torchcal.estimate.identifiability import weak_after_fit

    names, Q = _triple()  # tool.z's posterior sigma: 26.5 mm
    ps = torch.full((3,), 0.5, dtype=F64)
    cand = torch.ones(3, dtype=torch.bool)

    def judged(tool_z: float) -> dict:
        (e,) = weak_after_fit(names, Q, ps, cand, x=torch.tensor([0.0, 0.0, tool_z], dtype=F64))
        assert e["name"] == "tool.z" and set(e["combination"]) == set(names), e
        return e

    assert judged(0.01).get("held", True) and "held at its prior value" in judged(0.01)["reason"]  # compatible
    kept = judged(0.095)  # 3.6 posterior sigma from its prior, 0.19 prior sigma: the data determine it
    assert kept["held"] is False and "part of a weak combination" in kept["reason"]
    far = judged(2.0)  # 4 prior sigma off along a weak direction: the model's error amplified, held all the same
    assert far.get("held", True) and "4.0 of its prior sigma" in far["reason"]


def test_detectability_is_the_share_a_map_fit_gives_each_move_and_counts_the_rows_that_tell_it():
    """A linear toy: each row sees the sum of the first two parameters (weakly) and the third alone; every parameter
    has a prior of 1 (noise 1). A move of either of the first two shows at most half in itself, the rest in its
    partner: with 10 rows (information 0.5 on the sum) a 10-sigma move shows 0.25 of it in itself (2.5 sigma in the
    partner), untold; from 16 rows (0.8: share 0.31) on it is told. The third is told from the start."""
    from torchcal.estimate.identifiability import detectability

    names = ["a", "b", "c"]

    def normal(n: int, prior: float = 1.0):
        w = 0.05**0.5  # information 0.05 on the sum per row
        J = torch.tensor([[w, w, 0.0], [0.0, 0.0, 1.0]], dtype=F64).repeat(n, 1)
        return J.T @ J + torch.eye(3, dtype=F64) / prior**2, J

    N, J = normal(10)
    sigma = torch.ones(3, dtype=F64)
    d = detectability(names, N, sigma, sigma, rows=10)
    for j in range(3):  # the share is the MAP estimate's own change for a unit move (known answer)
        x = torch.linalg.solve(N, J.T @ (J @ torch.eye(3, dtype=F64)[j]))
        assert d.share[j] == pytest.approx(float(x[j]), rel=1e-12)
    untold = {u["name"]: u for u in d.untold}
    assert set(untold) == {"a", "b"} and untold["a"]["absorbed_by"] == ["b"] and untold["b"]["absorbed_by"] == ["a"]
    assert d.confounded == ["a", "b"] or d.confounded == ["b", "a"]
    # the rows it asks for tell them: with that many rows like these, every share passes 3 / 10
    N2, _ = normal(d.rows_needed)
    assert detectability(names, N2, sigma, sigma, rows=d.rows_needed).untold == ()
    N3, _ = normal(d.rows_needed - 1)
    assert detectability(names, N3, sigma, sigma, rows=d.rows_needed - 1).untold != ()
    assert d.rows_needed == 16 and d.to_dict()["poses_to_add"] == 6
