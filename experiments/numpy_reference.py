"""A plain numpy Gauss-Newton kinematic calibration: the reference that ``torchcal calibrate --method kinematic`` is
timed against (``scripts/bench_kinematic.py``, docs/benchmarks.md).

What one would write without torchcal for the problem its ``kinematic`` method solves: read the measurement file
(CONTRACT.md section 1) with numpy; standard-DH forward kinematics vectorised over the rows, link i =
``Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)`` (Hayati's ``beta`` only where consecutive axes are
parallel, as in :class:`torchcal.robot.model.DHGeometry`); the instrument pose ``T_tracker_base = T_0 [exp(r) | t]``
and the lever arm ``t_flange_probe`` from a closed-form start (rigid fit and linear lever arm, alternated); the DH
errors that the poses identify, chosen by a greedy independence test of the Jacobian's normalised columns in
torchcal's order of preference (instrument, lever arm, then the geometry); then Gauss-Newton on the unweighted
positions with a central-difference Jacobian, stopped on a relative step below 1e-10 or after 50 iterations.

What it leaves out, against torchcal: the stochastic model (per-point sigmas, joint noise), the priors, the screening
for gross errors, the orientations of a 6-D probe, the statistics and the report. It imports numpy only, so that as a
command its time is the interpreter, numpy's import, reading the file and the fit::

    python experiments/numpy_reference.py DATA.csv --problem PROBLEM.json

``PROBLEM.json`` (:func:`experiments.bench_kinematic.write_problem`, from torchcal, once): the robot's nominal DH
table ``dh: [[a, alpha, d, theta], ...]`` (standard convention, revolute joints) and the row indices ``train`` and
``holdout`` of torchcal's split, so that both fit the same rows. Prints one JSON object.
"""

from __future__ import annotations

import time

T_START, CPU_START = time.perf_counter(), time.process_time()

import argparse  # noqa: E402  (after the clock: the command's time includes every import)
import json  # noqa: E402

import numpy as np  # noqa: E402

#: Gauss-Newton stops when ``|dx| < STEP_TOL |x|`` or after ``MAX_ITER`` steps
STEP_TOL, MAX_ITER = 1e-10, 50
#: central-difference step [m or rad]: truncation ~h^2, round-off ~1e-16 * 3 m / h, both far below the noise
DIFF_STEP = 1e-6
#: a column whose normalised part outside the kept columns is below this is dependent (torchcal's rank_tol)
INDEPENDENCE_TOL = 1e-3
DH_COLUMNS = ("a", "alpha", "d", "theta", "beta")


def read_csv(path: str) -> dict[str, np.ndarray]:
    """The numeric columns of a measurement file (``#`` comment lines first, one header row), by header name."""
    with open(path, encoding="utf-8") as f:
        lines = [ln for ln in f.read().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    header = [h.strip() for h in lines[0].split(",")]
    table = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    if table.shape[1] != len(header):
        raise ValueError(f"{path}: {len(header)} header names but {table.shape[1]} values per row")
    return {name: table[:, i] for i, name in enumerate(header)}


def so3_exp(r: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, ``(3,)`` -> ``(3, 3)``."""
    theta = float(np.linalg.norm(r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(theta) / theta * K + (1.0 - np.cos(theta)) / theta**2 * K @ K


def forward(dh: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``T_base_flange (N, 4, 4)`` of the DH table ``dh (dof, 5)`` [a, alpha, d, theta, beta] at ``q (N, dof)``."""
    n = len(q)
    T = np.broadcast_to(np.eye(4), (n, 4, 4))
    for i, (a, alpha, d, theta, beta) in enumerate(dh):
        ct, st = np.cos(q[:, i] + theta), np.sin(q[:, i] + theta)
        ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
        # Rz(q + theta) Tz(d) Tx(a) Rx(alpha): the textbook closed form, then Ry(beta) (a constant) on the right
        A = np.zeros((n, 4, 4))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = ct, -st * ca, st * sa, a * ct
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = st, ct * ca, -ct * sa, a * st
        A[:, 2, 1], A[:, 2, 2], A[:, 2, 3], A[:, 3, 3] = sa, ca, d, 1.0
        if beta != 0.0:  # A Ry(beta): Ry turns the columns x and z of A's rotation
            x, z = A[:, :3, 0].copy(), A[:, :3, 2].copy()
            A[:, :3, 0], A[:, :3, 2] = cb * x - sb * z, sb * x + cb * z
        T = T @ A
    return T


def rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R, t`` minimising ``sum |R a_i + t - b_i|^2`` (Kabsch) for ``a, b (N, 3)``."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def place_instrument_and_lever(T: np.ndarray, p: np.ndarray, rounds: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """The start: ``T_tracker_base (4, 4)`` and lever arm ``(3,)`` for flange poses ``T (N, 4, 4)`` and measured
    ``p (N, 3)``, alternating a rigid fit for a fixed lever arm and a linear solve of translation and lever arm for a
    fixed rotation (each lowers the same cost)."""
    Rf, pf = T[:, :3, :3], T[:, :3, 3]
    lever = np.zeros(3)
    for _ in range(rounds):
        R, t0 = rigid_fit(pf + Rf @ lever, p)
        A = np.concatenate([np.broadcast_to(np.eye(3), Rf.shape), R @ Rf], axis=2).reshape(-1, 6)
        sol = np.linalg.lstsq(A, (p - pf @ R.T).reshape(-1), rcond=None)[0]
        done = np.linalg.norm(sol[3:] - lever) < 1e-12
        t0, lever = sol[:3], sol[3:]
        if done:
            break
    Tt = np.eye(4)
    Tt[:3, :3], Tt[:3, 3] = R, t0
    return Tt, lever


class Layout:
    """The parameter vector ``x``: the free DH elements (absolute values), the instrument correction ``[t, r]``
    on the start pose ``T_0``, the lever arm (absolute)."""

    def __init__(self, dh: np.ndarray, free: np.ndarray, T0: np.ndarray):
        self.dh, self.free, self.T0 = dh, free, T0  # free: (dof, 5) bool

    @property
    def names(self) -> list[str]:
        geom = [f"{DH_COLUMNS[j]}{i + 1}" for i, j in zip(*np.nonzero(self.free))]
        inst = [f"instrument.{c}" for c in ("tx", "ty", "tz", "rx", "ry", "rz")]
        return geom + inst + ["tool.x", "tool.y", "tool.z"]

    def start(self, lever: np.ndarray) -> np.ndarray:
        return np.concatenate([self.dh[self.free], np.zeros(6), lever])

    def predict(self, x: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Probe positions in the tracker frame ``(N, 3)`` [m] at parameters ``x`` for joints ``q (N, dof)``."""
        k = int(self.free.sum())
        dh = self.dh.copy()
        dh[self.free] = x[:k]
        T = forward(dh, q)
        p_base = T[:, :3, :3] @ x[k + 6 : k + 9] + T[:, :3, 3]
        delta = np.eye(4)
        delta[:3, :3], delta[:3, 3] = so3_exp(x[k + 3 : k + 6]), x[k : k + 3]
        Tt = self.T0 @ delta
        return p_base @ Tt[:3, :3].T + Tt[:3, 3]


def jacobian(f, x: np.ndarray) -> np.ndarray:
    """Central-difference Jacobian ``(M, P)`` of ``f: (P,) -> (M,)``, one column per pair of evaluations."""
    cols = []
    for j in range(len(x)):
        e = np.zeros_like(x)
        e[j] = DIFF_STEP
        cols.append((f(x + e) - f(x - e)) / (2 * DIFF_STEP))
    return np.stack(cols, axis=1)


def independent(J: np.ndarray, order: list[int]) -> list[int]:
    """The columns of ``J`` kept by a greedy independence test in ``order``: a column is kept when the part of it
    (normalised) outside the span of those kept before is above :data:`INDEPENDENCE_TOL`."""
    basis, kept = [], []
    for j in order:
        v = J[:, j] / np.linalg.norm(J[:, j])
        for _ in range(2):  # Gram-Schmidt twice: one pass loses orthogonality at this tolerance
            for b in basis:
                v = v - (b @ v) * b
        if np.linalg.norm(v) > INDEPENDENCE_TOL:
            basis.append(v / np.linalg.norm(v))
            kept.append(j)
    return sorted(kept)


def gauss_newton(f, x: np.ndarray) -> tuple[np.ndarray, int, str]:
    """Minimise ``|f(x)|^2``: Gauss-Newton steps from least squares on the central-difference Jacobian."""
    for it in range(1, MAX_ITER + 1):
        dx = np.linalg.lstsq(jacobian(f, x), -f(x), rcond=None)[0]
        x = x + dx
        if np.linalg.norm(dx) < STEP_TOL * np.linalg.norm(x):
            return x, it, "converged"
    return x, MAX_ITER, "max iterations"


def candidates(dh: np.ndarray) -> np.ndarray:
    """Every DH element a calibration may free ``(dof, 5)``: a, alpha, d, theta of each joint, beta where the joint's
    axis and the next are parallel (``|sin alpha| < 0.1``; not after the last joint)."""
    free = np.ones((len(dh), 5), dtype=bool)
    free[:, 4] = np.abs(np.sin(dh[:, 1])) < 0.1
    free[-1, 4] = False
    return free


def identify(dh: np.ndarray, q: np.ndarray, p: np.ndarray, T0: np.ndarray, lever: np.ndarray) -> Layout:
    """The layout of the identifiable parameters: instrument and lever arm kept first, then each DH candidate that
    is independent of those before it (:func:`independent`) at the start."""
    full = Layout(dh, candidates(dh), T0)
    k = int(full.free.sum())
    J = jacobian(lambda x: full.predict(x, q).reshape(-1), full.start(lever))
    kept = independent(J, list(range(k, k + 9)) + list(range(k)))
    if kept[-9:] != list(range(k, k + 9)):
        raise ValueError("the poses do not determine the instrument pose and the lever arm")
    free = np.zeros(full.free.size, dtype=bool)
    free[np.flatnonzero(full.free.reshape(-1))[[j for j in kept if j < k]]] = True
    return Layout(dh, free.reshape(full.free.shape), T0)


def rmse_mm(p_pred: np.ndarray, p: np.ndarray) -> float:
    """RMS over rows of the 3-D position error [mm]."""
    return float(np.sqrt(np.mean(np.sum((p_pred - p) ** 2, axis=1)))) * 1e3


def calibrate(dh4: np.ndarray, q: np.ndarray, p: np.ndarray, train: np.ndarray, hold: np.ndarray) -> dict:
    """Fit on the rows ``train`` of ``q (N, dof)``, ``p (N, 3)`` [m] from the nominal ``dh4 (dof, 4)``; errors on
    ``hold``. Returns the held-out and training RMSE [mm], the iterations, the status and the free parameters."""
    dh = np.concatenate([dh4, np.zeros((len(dh4), 1))], axis=1)
    qt, pt = q[train], p[train]
    T0, lever = place_instrument_and_lever(forward(dh, qt), pt)
    layout = identify(dh, qt, pt, T0, lever)
    x0 = layout.start(lever)
    x, iterations, status = gauss_newton(lambda x: (layout.predict(x, qt) - pt).reshape(-1), x0)
    return {
        "rmse_holdout_mm": rmse_mm(layout.predict(x, q[hold]), p[hold]),
        "rmse_train_mm": rmse_mm(layout.predict(x, qt), pt),
        "rmse_start_holdout_mm": rmse_mm(layout.predict(x0, q[hold]), p[hold]),
        "iterations": iterations,
        "status": status,
        "n_parameters": len(x),
        "parameters": dict(zip(layout.names, x.tolist())),
    }


def main(argv: list[str] | None = None) -> dict:
    """The command: read, fit, print one JSON object with the result and the times (``total_*``: since the
    interpreter reached this module, numpy's import included; ``fit_*``: the fit alone)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="measurement file (CONTRACT.md section 1), metres and radians")
    ap.add_argument("--problem", required=True, help="JSON with the nominal DH table and the split's row indices")
    a = ap.parse_args(argv)
    with open(a.problem, encoding="utf-8") as f:
        problem = json.load(f)
    dh4 = np.asarray(problem["dh"], dtype=float)
    cols = read_csv(a.data)
    q = np.stack([cols[f"q{i + 1}"] for i in range(len(dh4))], axis=1)
    p = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    t0, c0 = time.perf_counter(), time.process_time()
    out = calibrate(dh4, q, p, np.asarray(problem["train"]), np.asarray(problem["holdout"]))
    out.update(fit_wall_s=time.perf_counter() - t0, fit_cpu_s=time.process_time() - c0)
    out.update(total_wall_s=time.perf_counter() - T_START, total_cpu_s=time.process_time() - CPU_START)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
