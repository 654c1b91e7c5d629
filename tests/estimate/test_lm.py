"""Levenberg-Marquardt: known answers, agreement with LBFGS, statuses, statistics."""

import math

import pytest
import torch

from torchcal.estimate.lm import chi2_quantile, global_test, levenberg_marquardt

F64 = torch.float64


def test_linear_toy_equals_closed_form_least_squares():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(200, 4, generator=g, dtype=F64)
    x_true = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=F64)
    sigma = 0.1
    b = A @ x_true + sigma * torch.randn(200, generator=g, dtype=F64)
    res = levenberg_marquardt(lambda x: (A @ x - b) / sigma, torch.zeros(4, dtype=F64))
    x_ls = torch.linalg.lstsq(A, b[:, None]).solution[:, 0]
    assert res.status == "converged"
    assert torch.allclose(res.x, x_ls, atol=1e-10)
    # cofactor (A^T A / sigma^2)^-1 and the variance factor near 1 for the right sigma
    assert torch.allclose(res.cofactor, torch.linalg.inv(A.T @ A) * sigma**2, rtol=1e-8)
    assert abs(res.sigma0_sq - 1.0) < 0.25
    assert global_test(res)["passed"]


def test_lm_and_lbfgs_agree_on_a_well_posed_nonlinear_problem():
    x = torch.linspace(0, 2, 50, dtype=F64)
    y = 2.5 * torch.exp(-1.3 * x) + 0.4 + 0.001 * torch.sin(17 * x)

    def fun(p):
        return p[0] * torch.exp(-p[1] * x) + p[2] - y

    res = levenberg_marquardt(fun, torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    p = torch.tensor([1.0, 1.0, 0.0], dtype=F64, requires_grad=True)
    opt = torch.optim.LBFGS(
        [p], max_iter=500, tolerance_grad=1e-14, tolerance_change=1e-16, line_search_fn="strong_wolfe"
    )

    def closure():
        opt.zero_grad()
        loss = fun(p).square().sum()
        loss.backward()
        return loss

    for _ in range(5):
        opt.step(closure)
    assert res.status == "converged"
    assert torch.allclose(res.x, p.detach(), atol=1e-7)


def test_rank_deficiency_is_reported_not_hidden():
    A = torch.tensor([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]], dtype=F64)  # two identical columns
    b = torch.tensor([1.0, 2.0, 3.1], dtype=F64)
    res = levenberg_marquardt(lambda x: A @ x - b, torch.zeros(2, dtype=F64))
    assert res.status == "failed_solve"
    with pytest.raises(Exception, match="not positive definite"):
        _ = res.std


def test_a_fit_singular_from_the_start_stops_early_and_one_singular_only_at_its_start_goes_on():
    from torchcal.estimate.lm import SINGULAR_WINDOW

    # a slowly converging fit (Rosenbrock) with a third parameter that nothing depends on: singular throughout
    def idle(x):
        return torch.stack([10 * (x[1] - x[0] ** 2), 1 - x[0], 0.0 * x[2]])

    x0 = torch.tensor([-1.2, 1.0, 0.0], dtype=F64)
    rosenbrock = levenberg_marquardt(lambda x: idle(torch.cat([x, x[:1]]))[:2], x0[:2])
    assert rosenbrock.iterations > SINGULAR_WINDOW  # without the idle parameter: more iterations than that
    res = levenberg_marquardt(idle, x0, max_iter=100)
    assert res.status == "failed_solve" and f"singular (rank deficient) in {SINGULAR_WINDOW} of" in res.message
    assert res.iterations == SINGULAR_WINDOW - 1
    # amplitude and phase: the phase's derivative vanishes at zero amplitude (singular at the start only)
    t = torch.linspace(0.0, 3.0, 40, dtype=F64)
    y2 = 0.5 * torch.sin(2.0 * t + 0.3)
    res = levenberg_marquardt(lambda x: x[0] * torch.sin(2.0 * t + x[1]) - y2, torch.zeros(2, dtype=F64))
    assert res.status == "converged"
    assert torch.allclose(res.x, torch.tensor([0.5, 0.3], dtype=F64), atol=1e-6)


def _unit_diagonal_with_eigenvalues(lam: list[float]) -> torch.Tensor:
    """``Q diag(lam) Q^T`` for ``Q = H / sqrt(8)``, ``H`` the 8 x 8 Sylvester-Hadamard matrix: every entry is
    ``sum_k +-lam_k / 8``, exact in float64 for dyadic ``lam`` (no rounding, so no dependence on the BLAS kernels),
    and the diagonal is ``mean(lam)`` (1 here: a Jacobi-scaled normal matrix)."""
    from fractions import Fraction

    H = [[(-1) ** bin(i & j).count("1") for j in range(8)] for i in range(8)]
    exact = [
        [sum(Fraction(H[i][k] * H[j][k]) * Fraction(lam[k]) for k in range(8)) / 8 for j in range(8)] for i in range(8)
    ]
    Hs = torch.tensor(H, dtype=F64)
    Ns = Hs @ torch.diag(torch.tensor(lam, dtype=F64)) @ Hs.T / 8
    assert all(Fraction(float(Ns[i, j])) == exact[i][j] for i in range(8) for j in range(8))  # exact, not rounded
    assert torch.equal(Ns.diagonal(), torch.ones(8, dtype=F64))
    return Ns


def test_a_null_space_counts_as_singular_where_the_factorisation_succeeds():
    """:func:`_singular` judges the smallest eigenvalue against SINGULAR_EIGENVALUE = 1e-13, not by whether the plain
    Cholesky factorisation happens to fail. Exact matrices with chosen eigenvalues keep every outcome clear of
    rounding (the factorisation's rounding is about 1e-15 here): a fitted normal matrix with an exact null space has
    rounding-size eigenvalues of either sign, and whether its factorisation failed changed with the BLAS kernels."""
    from torchcal.estimate.lm import SINGULAR_EIGENVALUE, _singular

    tiny = 2.0**-45  # 2.8e-14: positive, so the factorisation succeeds, yet below 1e-13
    rest = [0.5, 1.5, 1.0, 1.0, 1.0, 2.0]
    assert 10 * 1e-15 < tiny < SINGULAR_EIGENVALUE / 3
    near = _unit_diagonal_with_eigenvalues([tiny, 1.0 - tiny] + rest)
    assert int(torch.linalg.cholesky_ex(near)[1]) == 0
    assert _singular(near)
    # an exact null space of dimension 2 (the plain factorisation may fail or not: rounding decides), and a well
    # conditioned matrix
    assert _singular(_unit_diagonal_with_eigenvalues([0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 2.0, 2.0]))
    assert not _singular(_unit_diagonal_with_eigenvalues([2.0**-30, 1.0 - 2.0**-30] + rest))  # 9.3e-10: regular


def test_non_finite_start_is_divergence():
    res = levenberg_marquardt(lambda x: x / 0.0 * 0.0, torch.zeros(2, dtype=F64))
    assert res.status == "diverged"


def test_max_iterations_status():
    res = levenberg_marquardt(
        lambda x: torch.stack([10 * (x[1] - x[0] ** 2), 1 - x[0]]), torch.tensor([-1.2, 1.0], dtype=F64), max_iter=2
    )
    assert res.status == "max_iterations" and res.iterations == 2


@pytest.mark.parametrize("dof,expected", [(10, 18.307), (100, 124.342), (1000, 1074.679)])
def test_chi2_quantile(dof, expected):
    assert chi2_quantile(0.95, dof) == pytest.approx(expected, rel=2e-3)


def test_standardized_residuals_flag_an_outlier():
    g = torch.Generator().manual_seed(1)
    A = torch.randn(100, 3, generator=g, dtype=F64)
    b = A @ torch.ones(3, dtype=F64) + torch.randn(100, generator=g, dtype=F64)
    b[17] += 8.0
    res = levenberg_marquardt(lambda x: A @ x - b, torch.zeros(3, dtype=F64))
    w = res.standardized_residuals()
    assert int(w.abs().argmax()) == 17 and float(w.abs().max()) > 3.29
    assert not math.isnan(res.sigma0_sq)


def test_a_fit_that_ends_where_no_step_helps_reuses_its_last_jacobian():
    """When the last iteration takes no step, the solution's Jacobian is the one evaluated at its start: one
    Jacobian per iteration, none more; a fit that ends on a step evaluates one more at the new point."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(40, 3, generator=g, dtype=F64)
    b = torch.randn(40, generator=g, dtype=F64)
    calls = []

    def jac(x):
        calls.append(x.clone())
        return torch.cos(A @ x)[:, None] * A

    def fun(x):
        return torch.sin(A @ x) - 0.1 * b

    x0 = torch.zeros(3, dtype=F64)
    res = levenberg_marquardt(fun, x0, jacobian=jac, max_iter=3)
    assert res.iterations == 3 and len(calls) == 4 and torch.equal(calls[-1], res.x)
    # x0 is a strict minimum of this one (every step raises the cost), its Jacobian a stand-in that points away
    calls.clear()
    res = levenberg_marquardt(lambda x: (1.0 + 1e20 * x.abs().sum()) * b, x0, jacobian=jac)
    assert res.message == "no step lowers the cost any more" and res.iterations == 1
    assert len(calls) == 1 and torch.equal(res.x, x0) and torch.equal(res.jacobian, jac(x0))


def test_a_fit_judged_by_its_solution_alone_skips_the_solutions_jacobian():
    """``solution_jacobian=False`` (the closed loop's validation refits): the same iterates, solution and residuals,
    one Jacobian fewer, and no normal matrix returned as if it were the solution's; a rank-deficient problem still
    fails."""
    x = torch.linspace(0, 2, 50, dtype=F64)
    y = 2.5 * torch.exp(-1.3 * x) + 0.4 + 0.001 * torch.sin(17 * x)

    def fun(p):
        return p[0] * torch.exp(-p[1] * x) + p[2] - y

    calls = {True: 0, False: 0}

    def counted(flag):
        def jac(p):
            calls[flag] += 1
            return torch.func.jacfwd(fun)(p)

        return jac

    x0 = torch.tensor([1.0, 1.0, 0.0], dtype=F64)
    full = levenberg_marquardt(fun, x0, jacobian=counted(True))
    lean = levenberg_marquardt(fun, x0, jacobian=counted(False), solution_jacobian=False)
    assert lean.status == full.status == "converged"
    assert torch.equal(lean.x, full.x) and torch.equal(lean.residuals, full.residuals)
    assert lean.cost_history == full.cost_history
    assert calls[False] == calls[True] - 1 == full.iterations
    assert full.normal is not None and lean.normal is None and lean.jacobian is None
    A = torch.tensor([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]], dtype=F64)
    b = torch.tensor([1.0, 2.0, 3.1], dtype=F64)
    assert levenberg_marquardt(lambda v: A @ v - b, torch.zeros(2, dtype=F64), solution_jacobian=False).status == (
        "failed_solve"
    )


def _exponential_fit():
    x = torch.linspace(0, 2, 50, dtype=F64)
    y = 2.5 * torch.exp(-1.3 * x) + 0.4 + 0.001 * torch.sin(17 * x)

    def fun(p):
        return p[0] * torch.exp(-p[1] * x) + p[2] - y

    return fun


def test_the_damping_ladder_is_one_batched_call_with_the_steps_of_single_trials():
    # each iteration evaluates its five trial points in one torch.func.vmap call: the same iterates as evaluating
    # them one by one (the same steps to the bit, residuals to rounding), one call instead of five
    from torchcal.estimate import lm

    fun = _exponential_fit()
    calls = {"batched": 0, "single": 0}

    def counted(p):
        calls["batched" if p.dim() == 1 and torch._C._functorch.is_batchedtensor(p) else "single"] += 1
        return fun(p)

    res = levenberg_marquardt(counted, torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    assert res.status == "converged"
    assert calls["batched"] == res.iterations  # one vmap call per iteration (the trace sees one batched tensor)
    x = torch.tensor([1.0, 1.0, 0.0], dtype=F64)
    J = torch.func.jacfwd(fun)(x)
    N = J.T @ J
    s = lm._jacobi(N)
    Ns, gs, cost = N * s[:, None] * s[None, :], (J.T @ fun(x)) * s, 0.5 * float(fun(x).square().sum())
    for lam in (1e-3, 1.0, 1e3):
        single = [lm._attempt(fun, x, cost, Ns, gs, s, lam * f) for f in lm.LADDER]
        single = min((t for t in single if t is not None), key=lambda t: t[0])
        batched = lm._ladder(lm._Trials(fun), x, cost, Ns, gs, s, lam)
        assert batched[1] == single[1] and torch.equal(batched[2], single[2])
        assert batched[0] == pytest.approx(single[0], rel=1e-12)


def test_a_residual_function_vmap_cannot_batch_falls_back_to_one_call_per_trial_point():
    fun = _exponential_fit()
    calls = []

    def unbatchable(p):  # an in-place write of the parameters into a plain tensor: vmap raises
        q = torch.zeros(3, dtype=F64)
        calls.append(torch._C._functorch.is_batchedtensor(p))
        q[:] = p
        return fun(q)

    x0 = torch.tensor([1.0, 1.0, 0.0], dtype=F64)
    ref = levenberg_marquardt(fun, x0)
    res = levenberg_marquardt(unbatchable, x0, jacobian=torch.func.jacfwd(fun))
    assert res.status == ref.status and res.iterations == ref.iterations
    assert torch.allclose(res.x, ref.x, rtol=1e-12, atol=1e-14)
    # one failed vmap call (the first iteration's), then single calls only: five per iteration at least
    assert calls.count(True) == 1 and calls.index(True) == 1
    assert len(calls) >= 2 + 5 * res.iterations
