"""What remains on the real UR10 after the geometric fit (issue 5, item 5): noise, configuration, reach, drift.

Data: the ipa-robot-accuracy set (Landgraf et al., IEEE CASE 2021, MIT licence; UR10 CB3 + Leica tracker
with a T-Mac probe), read with :func:`torchcal.data.read_ipa`; the commanded orientation (``Goal roll,
pitch, yaw``), which the reader drops, is re-parsed from the same file.

Per series, a kinematic calibration on every row (``calibrate()`` keeps one pose out; Series A: on a
seeded ``--a-rows`` subsample, the residuals are then taken on all its rows), then the position
residual ``r = p_measured - p_model`` of every pose is examined:

1. pairs of poses: revisits (every joint within ``--tol`` rad of an earlier visit), the same commanded
   position with another commanded orientation (same elbow/wrist branch), and the same commanded pose
   reached with another IK branch (Series B). For each class, the RMS of the measured-position
   differences and of the residual differences; ``per pose`` = RMS(dr) / sqrt(2) is what one pose
   carries that its partner does not, to compare with the residual RMS (independent residuals give
   per pose = RMS, identical ones 0). For revisits also the median, the pairs whose residuals differ by
   more than 0.5 mm (gross errors; their file lines), and the revisits more than 50 rows apart (drift);
   poses whose |r| exceeds 4 x RMS are listed by file line;
2. |r| against reach (distance of the probe from the base z axis), height and distance from the
   tracker: binned RMS, OLS slope of |r| with its t statistic, Spearman correlation, and the residual
   split into radial / tangential / vertical (base frame) and line-of-sight / transverse (tracker);
3. |r| against the probe orientation (viewing angle of the tracker in the T-Mac frame, from the measured
   orientation; tilt of the flange axis from vertical, from the model), temperature, acquisition order
   (row) and, for Series A, time; all covariates in one standardised regression; per-component drift
   slopes against the row, alone and with a quadratic function of the probe position fitted alongside
   (the acquisition order sweeps through space), and block means;
4. the correlation of the residual vectors of pairs of poses against their joint-space (Euclidean, six
   joints, rad) and Cartesian (probe, m) distance, all pairs and nearest neighbours, on at most
   ``--pair-rows`` seeded rows; the half-correlation distance; the same against the arm joints q1-q3
   alone, and against the wrist q4-q6 for pairs whose arm joints agree within 0.05 rad.

t statistics are the ordinary least-squares ones: the residuals are correlated between nearby poses
(item 4), so they overstate the significance; read them as "clearly there" or "not there".

Usage::

    python scripts/ur10_investigate.py PATH/TO/ur10-ipa                 # series A,B,C,D
    python scripts/ur10_investigate.py PATH/TO/ur10-ipa --series D --json

The summary goes to stderr; with ``--json`` the last stdout line is one JSON object with the numbers.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch

from experiments.ipa_series import series_file, subsample_idx
from torchcal.data import read_ipa
from torchcal.effects import Context
from torchcal.pipeline import Options, calibrate
from torchcal.robot import transforms as tf

ROBOT = "ur10"
SERIES = ("A", "B", "C", "D")
SEED = 0
MM = 1e3
GOAL_ROT = ("Goal roll", "Goal pitch", "Goal yaw")
POS_DECIMALS = 5  # commanded positions equal to 1e-5 m are "the same position"
SAME_ROT = 1e-3  # rad: commanded rotations closer than this are the same
BRANCH_MIN = 1e-2  # rad: the same commanded pose with joints further apart than this is another IK branch
JOINT_BINS = (1e-3, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 3.2, math.inf)  # rad, Euclidean over 6 joints
CART_BINS = (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8, math.inf)  # m, probe in the base frame
NN_BINS = (1e-3, 0.05, 0.1, 0.2, 0.4, 0.8, math.inf)
ROT_BINS = (SAME_ROT, 0.1, 0.2, 0.4, math.inf)  # rad, commanded orientation difference at one position
N_BINS = 5  # quantile bins of the covariates
N_BLOCKS = 10  # consecutive blocks of rows for the drift check
OUTLIER_DR = 0.5e-3  # m: a revisit whose residuals differ by more than this is an outlier pair
OUTLIER_RMS = 4.0  # a pose whose |r| exceeds this many times the RMS is listed
LONG_GAP = 50  # rows: revisits further apart than this are also reported on their own (drift)


# ----------------------------------------------------------------------------- data


def read_goal_rotation(path: Path, n: int) -> torch.Tensor:
    """Commanded T-Mac orientation ``(n, 3, 3)`` in base_link from the Goal roll/pitch/yaw columns.

    Same row rules as :func:`read_ipa` (``;``, decimal commas, NUL bytes and spaces stripped, blank lines
    skipped). R = Rz(yaw) Ry(pitch) Rx(roll); only differences between rows are used, so the base_link
    vs DH base frame does not matter.
    """
    text = path.read_bytes().decode("utf-8-sig").replace("\r\n", "\n").replace("\r", "\n")
    lines = [ln.strip(" \t\x00") for ln in text.split("\n")]
    lines = [ln for ln in lines if ln]
    header = [c.strip(" \t\x00") for c in lines[0].split(";")]
    cols = [header.index(c) for c in GOAL_ROT]
    rows = [
        [float(cells[k].strip(" \t\x00").replace(",", ".")) for k in cols]
        for cells in (ln.split(";") for ln in lines[1:])
    ]
    if len(rows) != n:
        raise SystemExit(f"{path}: {len(rows)} goal rows but read_ipa gave {n}")
    return tf.rpy_to_matrix(torch.tensor(rows, dtype=torch.float64))


# ----------------------------------------------------------------------------- statistics


def rms(x: torch.Tensor) -> float:
    """RMS of the norms of ``x (N, 3)`` or of the values ``x (N,)``."""
    if x.numel() == 0:
        return float("nan")
    sq = x.square().sum(-1) if x.ndim == 2 else x.square()
    return float(sq.mean().sqrt())


def normal_p(t: float) -> float:
    """Two-sided p-value of a t statistic, normal approximation (n is large here)."""
    return math.erfc(abs(t) / math.sqrt(2.0)) if math.isfinite(t) else float("nan")


def ranks(x: torch.Tensor) -> torch.Tensor:
    r = torch.empty_like(x)
    r[torch.argsort(x)] = torch.arange(len(x), dtype=x.dtype)
    return r


def pearson(x: torch.Tensor, y: torch.Tensor) -> float:
    x, y = x - x.mean(), y - y.mean()
    den = float((x.square().sum() * y.square().sum()).sqrt())
    return float((x * y).sum()) / den if den > 0 else float("nan")


def regression(x: torch.Tensor, y: torch.Tensor) -> dict:
    """OLS ``y = a + b x``: slope, its standard error, t, p, Pearson and Spearman correlations."""
    n = len(x)
    xc = x - x.mean()
    sxx = float(xc.square().sum())
    if n < 3 or sxx <= 0:
        return {
            "slope": float("nan"),
            "se": float("nan"),
            "t": float("nan"),
            "p": float("nan"),
            "pearson": float("nan"),
            "spearman": float("nan"),
            "n": n,
        }
    b = float((xc * (y - y.mean())).sum()) / sxx
    resid = y - y.mean() - b * xc
    se = math.sqrt(float(resid.square().sum()) / (n - 2) / sxx)
    t = b / se if se > 0 else float("inf")
    return {
        "slope": b,
        "se": se,
        "t": t,
        "p": normal_p(t),
        "pearson": pearson(x, y),
        "spearman": pearson(ranks(x), ranks(y)),
        "n": n,
    }


def binned(
    x: torch.Tensor, r: torch.Tensor, comps: dict[str, torch.Tensor] | None = None, bins: int = N_BINS
) -> list[dict]:
    """Quantile bins of ``x``: range, count, RMS |r| [mm] (and RMS of each component) per bin."""
    order = torch.argsort(x)
    out = []
    for chunk in torch.tensor_split(order, bins):
        if chunk.numel() == 0:
            continue
        row = {
            "lo": float(x[chunk].min()),
            "hi": float(x[chunk].max()),
            "n": int(chunk.numel()),
            "rms_mm": rms(r[chunk]) * MM,
        }
        for k, v in (comps or {}).items():
            row[f"{k}_mm"] = rms(v[chunk]) * MM
        out.append(row)
    return out


def vector_corr(a: torch.Tensor, b: torch.Tensor) -> float:
    """Correlation of paired residual vectors ``(N, 3)``: sum a.b / sqrt(sum|a|^2 sum|b|^2) (means ~0)."""
    den = float((a.square().sum() * b.square().sum()).sqrt())
    return float((a * b).sum()) / den if den > 0 else float("nan")


def multiple_regression(covs: dict[str, torch.Tensor], y: torch.Tensor) -> dict:
    """|r| on all covariates at once, each standardised: coefficient [mm per SD] and t."""
    names = [k for k, v in covs.items() if float(v.std()) > 0]
    X = torch.stack([torch.ones_like(y)] + [(covs[k] - covs[k].mean()) / covs[k].std() for k in names], 1)
    sol = torch.linalg.lstsq(X, y.unsqueeze(1)).solution.squeeze(1)
    resid = y - X @ sol
    dof = len(y) - X.shape[1]
    s2 = float(resid.square().sum()) / dof
    cov = torch.linalg.inv(X.T @ X) * s2
    se = cov.diagonal().sqrt()
    r2 = 1.0 - float(resid.square().sum()) / float((y - y.mean()).square().sum())
    return {
        "r2": r2,
        "coef": {
            k: {"mm_per_sd": float(sol[i + 1]) * MM, "t": float(sol[i + 1] / se[i + 1])} for i, k in enumerate(names)
        },
    }


def row_trend_controlled(order: torch.Tensor, controls: torch.Tensor, y: torch.Tensor) -> tuple[float, float]:
    """Slope per 1000 rows and t statistic of the ``order`` coefficient in OLS of ``y`` on [1, order, controls]."""
    X = torch.cat([torch.ones_like(y)[:, None], ((order - order.mean()) / order.std())[:, None], controls], 1)
    sol = torch.linalg.lstsq(X, y.unsqueeze(1)).solution.squeeze(1)
    resid = y - X @ sol
    s2 = float(resid.square().sum()) / (len(y) - X.shape[1])
    se = math.sqrt(float(torch.linalg.inv(X.T @ X)[1, 1]) * s2)
    return float(sol[1] / order.std()) * 1000, float(sol[1]) / se


# ----------------------------------------------------------------------------- pairs


def revisit_pairs(q: torch.Tensor, tol: float) -> torch.Tensor:
    """Pairs ``(P, 2)``, i < j, whose joints all agree within ``tol`` rad.

    Sorted by the first joint, a pair can only lie within the run of rows whose first joint is within ``tol``:
    compare each row with the k-th next one for k = 1, 2, ... while any such run is still open.
    """
    order = torch.argsort(q[:, 0])
    qs = q[order]
    out = []
    for k in range(1, len(q)):
        open_ = (qs[k:, 0] - qs[:-k, 0]) < tol
        if not bool(open_.any()):
            break
        hit = ((qs[k:] - qs[:-k]).abs() < tol).all(1)
        idx = hit.nonzero().squeeze(1)
        a, b = order[idx], order[idx + k]
        out.append(torch.stack([torch.minimum(a, b), torch.maximum(a, b)], 1))
    return torch.cat(out) if out else torch.zeros(0, 2, dtype=torch.long)


def goal_pairs(goal_p: torch.Tensor, goal_R: torch.Tensor, q: torch.Tensor, tol: float):
    """Pairs with the same commanded position: (other orientation, same branch), (same pose, other branch) and
    (same pose, joints within ``BRANCH_MIN`` but not within ``tol``: revisits the controller reached with a few
    mrad of wrist difference, as in Series A).

    Returns ``orient (P, 2)`` with the orientation difference angles ``(P,)``, ``branch (B, 2)`` and ``near (K, 2)``.
    """
    groups: dict[tuple, list[int]] = {}
    for i, key in enumerate(torch.round(goal_p * 10**POS_DECIMALS).long().tolist()):
        groups.setdefault(tuple(key), []).append(i)
    orient, angles, branch, near = [], [], [], []
    for rows in groups.values():
        if len(rows) < 2:
            continue
        idx = torch.tensor(rows)
        ii, jj = torch.triu_indices(len(rows), len(rows), 1)
        a, b = idx[ii], idx[jj]
        ang = so3_angle(goal_R[a].transpose(-1, -2) @ goal_R[b])
        dq = (q[a] - q[b]).abs()
        maxdq = dq.amax(-1)
        same_branch = ((q[a, 2] > 0) == (q[b, 2] > 0)) & ((q[a, 4] > 0) == (q[b, 4] > 0)) & (dq[:, 0] < 0.5)
        o = (ang >= SAME_ROT) & (maxdq >= tol) & same_branch
        br = (ang < SAME_ROT) & (maxdq >= BRANCH_MIN)
        nr = (ang < SAME_ROT) & (maxdq >= tol) & (maxdq < BRANCH_MIN)
        orient.append(torch.stack([a[o], b[o]], 1))
        angles.append(ang[o])
        branch.append(torch.stack([a[br], b[br]], 1))
        near.append(torch.stack([a[nr], b[nr]], 1))
    empty = torch.zeros(0, 2, dtype=torch.long)
    return (
        torch.cat(orient) if orient else empty,
        torch.cat(angles) if angles else torch.zeros(0),
        torch.cat(branch) if branch else empty,
        torch.cat(near) if near else empty,
    )


def so3_angle(R: torch.Tensor) -> torch.Tensor:
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    return torch.arccos(((tr - 1.0) / 2.0).clamp(-1.0, 1.0))


def pair_stats(
    pairs: torch.Tensor, p: torch.Tensor, r: torch.Tensor, r_nom: torch.Tensor, rms_r: float, robust: bool = False
) -> dict:
    """Measured and residual differences over ``pairs`` [mm]; ``per_pose`` = RMS(dr) / sqrt 2.

    With ``robust`` (revisits, where |dr| should be noise): the median |dr|, and the per-pose RMS without the
    pairs whose |dr| exceeds ``OUTLIER_DR`` (counted in ``n_outliers``).
    """
    if len(pairs) == 0:
        return {"n_pairs": 0}
    a, b = pairs[:, 0], pairs[:, 1]
    drv = (r[a] - r[b]).norm(dim=1)
    ok = drv <= OUTLIER_DR
    dr = rms(drv)
    extra = {"median_dr_mm": float(drv.median()) * MM}
    if robust:
        extra.update({"n_outliers": int((~ok).sum()), "per_pose_without_outliers_mm": rms(drv[ok]) / math.sqrt(2) * MM})
    return {
        "n_pairs": int(len(pairs)),
        "rms_dp_mm": rms(p[a] - p[b]) * MM,
        "rms_dr_mm": dr * MM,
        "per_pose_mm": dr / math.sqrt(2.0) * MM,
        "per_pose_nominal_mm": rms(r_nom[a] - r_nom[b]) / math.sqrt(2.0) * MM,
        "per_pose_over_rms": dr / math.sqrt(2.0) / rms_r,
        "corr": vector_corr(r[a], r[b]),
        **extra,
    }


def branch_breakdown(pairs: torch.Tensor, q: torch.Tensor, r: torch.Tensor, r_base: torch.Tensor) -> dict:
    """IK-branch pairs: which joints differ (> 0.5 rad), the per-pose residual difference per pattern, and the
    mean residual difference (the pose with q3 > 0 minus the one with q3 < 0) in the base frame."""
    if len(pairs) == 0:
        return {}
    a, b = pairs[:, 0], pairs[:, 1]
    big = (q[a] - q[b]).abs() > 0.5
    patterns: dict[str, list[int]] = {}
    for k, row in enumerate(big.tolist()):
        key = ",".join(f"q{j + 1}" for j, v in enumerate(row) if v) or "none"
        patterns.setdefault(key, []).append(k)
    by_pattern = {
        key: {"n_pairs": len(ks), "per_pose_mm": rms(r[a[ks]] - r[b[ks]]) / math.sqrt(2) * MM}
        for key, ks in sorted(patterns.items(), key=lambda kv: -len(kv[1]))
    }
    # orient every pair: the pose with the larger elbow angle q3 minus the other
    flip = q[a, 2] < q[b, 2]
    hi = torch.where(flip, b, a)
    lo = torch.where(flip, a, b)
    d = r_base[hi] - r_base[lo]
    mean = d.mean(0)
    se = d.std(0) / math.sqrt(len(d))
    return {
        "joints_differing": by_pattern,
        "mean_diff_q3_high_minus_low_base_mm": [float(v) * MM for v in mean],
        "mean_diff_t": [float(v) for v in mean / se],
        "rms_diff_about_mean_mm": rms(d - mean) * MM,
    }


# ----------------------------------------------------------------------------- spatial correlation


def correlation_curves(q: torch.Tensor, pb: torch.Tensor, r: torch.Tensor, tol: float, revisits: torch.Tensor) -> dict:
    """Residual correlation against joint-space and Cartesian distance (all pairs; nearest neighbours).

    Revisits (joints within ``tol``, and the pairs ``revisits (K, 2)``) are left out: item 1 reports them.
    The correlation of a set of pairs is sum r_i.r_j / sum (|r_i|^2 + |r_j|^2) / 2.
    """
    n = len(q)
    i, j = torch.triu_indices(n, n, 1)

    def upper(M: torch.Tensor) -> torch.Tensor:
        return M[i, j]

    maxdq = torch.zeros(n, n, dtype=q.dtype)
    for k in range(q.shape[1]):
        maxdq = torch.maximum(maxdq, (q[:, None, k] - q[None, :, k]).abs())
    revisit = maxdq < tol
    del maxdq
    revisit[revisits[:, 0], revisits[:, 1]] = True
    revisit[revisits[:, 1], revisits[:, 0]] = True
    revisit.fill_diagonal_(True)
    valid = ~upper(revisit)
    dj_full = torch.cdist(q, q)
    # nearest neighbour in joint space that is not a revisit
    d1, j1 = torch.where(revisit, torch.full_like(dj_full, math.inf), dj_full).min(1)
    del revisit
    dj = upper(dj_full)
    del dj_full
    dc = upper(torch.cdist(pb, pb))
    d_arm = upper(torch.cdist(q[:, :3], q[:, :3]))
    d_wrist = upper(torch.cdist(q[:, 3:], q[:, 3:]))
    g = (r[i] * r[j]).sum(1)
    a = r.square().sum(1)
    aa = 0.5 * (a[i] + a[j])

    def curve(d: torch.Tensor, edges, sel: torch.Tensor | None = None) -> list[dict]:
        e = torch.tensor(edges, dtype=d.dtype)
        b = torch.bucketize(d, e, right=True) - 1  # edges[b] <= d < edges[b + 1]
        keep = valid & (b >= 0) & (b < len(edges) - 1)
        if sel is not None:
            keep &= sel
        b = b[keep]
        cnt = torch.bincount(b, minlength=len(edges) - 1)
        sg = torch.bincount(b, weights=g[keep], minlength=len(edges) - 1)
        sa = torch.bincount(b, weights=aa[keep], minlength=len(edges) - 1)
        return [
            {"lo": lo, "hi": hi, "n_pairs": int(c), "corr": float(x / y) if c else None}
            for lo, hi, c, x, y in zip(edges[:-1], edges[1:], cnt.tolist(), sg.tolist(), sa.tolist())
        ]

    joint = curve(dj, JOINT_BINS)
    cart = curve(dc, CART_BINS)
    arm = curve(d_arm, JOINT_BINS)  # the arm joints q1-q3 only, whatever the wrist does
    wrist = curve(d_wrist, JOINT_BINS, d_arm < 0.05)  # the wrist q4-q6 for pairs whose arm agrees within 0.05 rad
    nn = []
    for lo, hi in zip(NN_BINS[:-1], NN_BINS[1:]):
        idx = ((d1 >= lo) & (d1 < hi)).nonzero().squeeze(1)
        nn.append(
            {
                "lo": lo,
                "hi": hi,
                "n": int(idx.numel()),
                "corr": vector_corr(r[idx], r[j1[idx]]) if idx.numel() else None,
            }
        )
    close_far = valid & (dc < 0.02) & (dj > 0.5)
    cf = int(close_far.sum())
    return {
        "n_rows": n,
        "joint": joint,
        "cartesian": cart,
        "arm": arm,
        "wrist_at_same_arm": wrist,
        "nearest_neighbour": nn,
        "nn_median_rad": float(d1[torch.isfinite(d1)].median()),
        "half_corr_rad": half_distance(joint),
        "half_corr_m": half_distance(cart),
        "close_in_space_far_in_joints": {
            "n_pairs": cf,
            "corr": float(g[close_far].sum() / aa[close_far].sum()) if cf else None,
        },
    }


def half_distance(curve: list[dict]) -> float | None:
    """Distance at which the correlation first falls below 0.5 (log-linear between bin centres)."""
    prev = None
    for b in curve:
        if b["corr"] is None or b["n_pairs"] < 20:
            continue
        lo = b["lo"] if b["lo"] > 0 else b["hi"] / 2
        hi = b["hi"] if math.isfinite(b["hi"]) else 2 * lo
        centre = math.sqrt(lo * hi)
        if b["corr"] < 0.5:
            if prev is None:
                return centre
            (c0, r0), (c1, r1) = prev, (centre, b["corr"])
            f = (r0 - 0.5) / (r0 - r1)
            return math.exp(math.log(c0) + f * (math.log(c1) - math.log(c0)))
        prev = (centre, b["corr"])
    return None


# ----------------------------------------------------------------------------- one series


def investigate(name: str, path: Path, a_rows: int, pair_rows: int, tol: float) -> dict:
    t0 = time.perf_counter()
    m_all = read_ipa(path)
    goal_R = read_goal_rotation(path, m_all.n)
    fit_idx = subsample_idx(m_all.n, a_rows if name == "A" else 0, SEED)
    m_fit = m_all.subset(fit_idx)
    run = calibrate(ROBOT, m_fit, Options.of(method="kinematic", seed=SEED, holdout=0.5 / m_fit.n, trajectory=False))
    model, nominal = run.model, run.stages[0].model
    m = m_all
    ctx = Context.from_measurements(m, trajectory=False)
    with torch.no_grad():
        r = m.p - model(ctx)
        r_nom = m.p - nominal(ctx)
        pb = model.probe_in_base(ctx)
        T_bf = model.robot(m.q)
        R_tb = model.robot.T_tracker_base()[:3, :3]
    r_base = r @ R_tb  # R_tb^T r per row
    rn = r.norm(dim=1)
    rms_r = rms(r)
    in_fit = torch.zeros(m.n, dtype=torch.bool)
    in_fit[fit_idx] = True
    in_fit[fit_idx[run.holdout_idx]] = False

    # --- covariates
    reach = pb[:, :2].norm(dim=1)
    e_rad = torch.cat([pb[:, :2] / reach[:, None], torch.zeros(m.n, 1, dtype=pb.dtype)], 1)
    e_tan = torch.stack([-e_rad[:, 1], e_rad[:, 0], torch.zeros_like(reach)], 1)
    comp_base = {"radial": (r_base * e_rad).sum(1), "tangential": (r_base * e_tan).sum(1), "vertical": r_base[:, 2]}
    dist = m.p.norm(dim=1)
    los = m.p / dist[:, None]
    r_los = (r * los).sum(1)
    comp_tracker = {"line_of_sight": r_los, "transverse": (r - r_los[:, None] * los).norm(dim=1)}
    rotvec = m.r
    R_tm = tf.so3_exp(rotvec)
    u = (R_tm.transpose(-1, -2) @ (-los).unsqueeze(-1)).squeeze(-1)  # direction to the tracker, T-Mac frame
    u_mean = u.mean(0)
    u_mean = u_mean / u_mean.norm()
    view = torch.arccos((u @ u_mean).clamp(-1, 1))
    tilt = torch.arccos((-T_bf[:, 2, 2]).clamp(-1, 1))  # flange z axis from straight down [rad]
    covs = {
        "reach_m": reach,
        "height_m": pb[:, 2],
        "tracker_distance_m": dist,
        "view_angle_rad": view,
        "tool_tilt_rad": tilt,
        "temperature_c": m.temperature,
        "row": m.extra["row"],
    }
    if "timestamp_s" in m.extra or m.t is not None:
        covs["time_h"] = (m.t if m.t is not None else m.extra["timestamp_s"]) / 3600.0
    cov_out = {}
    for k, x in covs.items():
        cov_out[k] = {
            "range": [float(x.min()), float(x.max())],
            **regression(x, rn * MM),
            "bins": binned(x, r, comp_base if k == "reach_m" else None),
        }
    cov_out["reach_m"]["components"] = {k: regression(reach, v.abs() * MM) for k, v in comp_base.items()}
    cov_out["tracker_distance_m"]["components"] = {k: regression(dist, v.abs() * MM) for k, v in comp_tracker.items()}
    joint_reg = multiple_regression({k: v for k, v in covs.items() if k != "time_h"}, rn)

    # --- drift: per-component trend against row order, block means
    order = m.extra["row"]
    drift = {
        k: {"slope_mm_per_1000_rows": regression(order, v * MM)["slope"] * 1000, "t": regression(order, v * MM)["t"]}
        for k, v in (("x", r_base[:, 0]), ("y", r_base[:, 1]), ("z", r_base[:, 2]))
    }
    blocks = torch.stack([r_base[c].mean(0) for c in torch.tensor_split(torch.arange(m.n), N_BLOCKS)])
    drift["block_means_rms_mm"] = rms(blocks) * MM
    # the row trend with a quadratic function of the probe position (base frame) fitted alongside: acquisition
    # order follows the goals through space, so a spatial pattern can pose as a drift
    x = (pb - pb.mean(0)) / pb.std(0)
    quad = torch.cat([x, x.square(), x[:, [0, 0, 1]] * x[:, [1, 2, 2]]], 1)
    for k, v in (("x", r_base[:, 0]), ("y", r_base[:, 1]), ("z", r_base[:, 2])):
        slope, t = row_trend_controlled(order, quad, v * MM)
        drift[k]["position_controlled"] = {"slope_mm_per_1000_rows": slope, "t": t}
    drift["block_means_if_independent_mm"] = rms_r / math.sqrt(m.n / N_BLOCKS) * MM
    temp_order = pearson(m.temperature, order)

    # --- pairs: revisits, other orientation at the same position, other IK branch
    goal_p = torch.stack([m.extra[f"goal_{a}"] for a in "xyz"], 1)
    orient, orient_ang, branch, near = goal_pairs(goal_p, goal_R, m.q, tol)
    rev_joints = revisit_pairs(m.q, tol)
    rev = torch.cat([rev_joints, near])
    pairs = {
        "revisit": pair_stats(rev, m.p, r, r_nom, rms_r, robust=True),
        "other_orientation": pair_stats(orient, m.p, r, r_nom, rms_r),
        "other_ik_branch": pair_stats(branch, m.p, r, r_nom, rms_r),
    }
    if len(rev):
        gap = order[rev[:, 1]] - order[rev[:, 0]]
        drn = (r[rev[:, 0]] - r[rev[:, 1]]).norm(dim=1) * MM
        pairs["revisit"]["gap_rows_median"] = float(gap.median())
        pairs["revisit"]["gap_rows_max"] = float(gap.max())
        pairs["revisit"]["dr_vs_gap"] = regression(gap, drn)
        pairs["revisit"]["max_dq_rad"] = float((m.q[rev[:, 0]] - m.q[rev[:, 1]]).abs().max())
        bad = (r[rev[:, 0]] - r[rev[:, 1]]).norm(dim=1) > OUTLIER_DR
        worse = torch.where(rn[rev[:, 0]] > rn[rev[:, 1]], rev[:, 0], rev[:, 1])[bad]
        pairs["revisit"]["outlier_lines"] = sorted(m.lines[i] for i in worse.tolist())
        long = gap > LONG_GAP
        if long.any():
            pairs["revisit"]["long_gap"] = pair_stats(rev[long], m.p, r, r_nom, rms_r)
            if "time_h" in covs:
                pairs["revisit"]["long_gap"]["gap_h_median"] = float(
                    (covs["time_h"][rev[long, 1]] - covs["time_h"][rev[long, 0]]).abs().median()
                )
        pairs["revisit"]["n_joints_within_tol"] = int(len(rev_joints))
        pairs["revisit"]["n_same_goal_within_branch_min"] = int(len(near))
        if "time_h" in covs:
            pairs["revisit"]["gap_s_median"] = (
                float((covs["time_h"][rev[:, 1]] - covs["time_h"][rev[:, 0]]).abs().median()) * 3600
            )
    if len(orient):
        pairs["other_orientation"]["by_angle"] = []
        for lo, hi in zip(ROT_BINS[:-1], ROT_BINS[1:]):
            sel = (orient_ang >= lo) & (orient_ang < hi)
            if sel.any():
                pairs["other_orientation"]["by_angle"].append(
                    {"lo": lo, "hi": hi, **pair_stats(orient[sel], m.p, r, r_nom, rms_r)}
                )
    if len(branch):
        pairs["other_ik_branch"].update(branch_breakdown(branch, m.q, r, r_base))
    branches = {}
    for label, mask in (("elbow q3<0", m.q[:, 2] < 0), ("elbow q3>0", m.q[:, 2] > 0)):
        if mask.any():
            branches[label] = {"n": int(mask.sum()), "rms_mm": rms(r[mask]) * MM}

    # --- spatial correlation on a seeded subsample
    sub = subsample_idx(m.n, pair_rows, SEED + 1)
    local = torch.full((m.n,), -1, dtype=torch.long)
    local[sub] = torch.arange(len(sub))
    rev_sub = local[rev]
    rev_sub = rev_sub[(rev_sub >= 0).all(1)]
    corr = correlation_curves(m.q[sub], pb[sub], r_base[sub], tol, rev_sub)

    sigma = None if m.sigma is None else float(m.sigma.norm(dim=1).median()) * MM
    fit = run.fits[-1].global_test
    return {
        "series": name,
        "file": path.name,
        "n": m.n,
        "n_fit": int(run.train_idx.numel()),
        "fit": (
            "kinematic on all rows but one"
            if name != "A"
            else f"kinematic on a seeded {m_fit.n}-row subsample (all but one of them); residuals on all {m.n} rows"
        ),
        "rms_mm": rms_r * MM,
        "max_mm": float(rn.max()) * MM,
        "large_residual_lines": [m.lines[i] for i in (rn > OUTLIER_RMS * rms_r).nonzero().squeeze(1).tolist()],
        "rms_fit_rows_mm": rms(r[in_fit]) * MM,
        "rms_other_rows_mm": rms(r[~in_fit]) * MM if int((~in_fit).sum()) >= 10 else None,
        "rms_nominal_mm": rms(r_nom) * MM,
        "variance_factor": fit["statistic"],
        "tracker_sigma_median_mm": sigma,
        "components_rms_mm": {k: rms(v) * MM for k, v in {**comp_base, **comp_tracker}.items()},
        "temperature_spread_c": float(m.temperature.max() - m.temperature.min()),
        "temperature_vs_row_corr": temp_order,
        "pairs": pairs,
        "branches": branches,
        "covariates": cov_out,
        "joint_regression": joint_reg,
        "drift": drift,
        "correlation": corr,
        "runtime_s": time.perf_counter() - t0,
    }


# ----------------------------------------------------------------------------- output


def _f(x, nd=3) -> str:
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{nd}f}"


def _bins(bins: list[dict], nd: int, count: str = "n_pairs") -> str:
    """Correlation bins as ``<upper: corr (count)`` with the upper edge to ``nd`` decimals."""
    return "  ".join(f"<{_f(b['hi'], nd)}: {_f(b['corr'], 2)} ({b[count]})" for b in bins)


def summary(res: dict) -> str:
    L = []
    for s in res["series"]:
        L.append(f"=== Series {s['series']} ({s['file']}, {s['n']} rows; {s['fit']}; {_f(s['runtime_s'], 1)} s)")
        L.append(
            f"  residual RMS {_f(s['rms_mm'])} mm (max {_f(s['max_mm'])}; nominal {_f(s['rms_nominal_mm'])}); "
            f"fit rows {_f(s['rms_fit_rows_mm'])}, other rows {_f(s['rms_other_rows_mm'])}; variance factor "
            f"{_f(s['variance_factor'], 0)}; tracker sigma (median |s|) {_f(s['tracker_sigma_median_mm'], 4)} mm"
        )
        L.append(
            f"  poses with |r| > {_f(OUTLIER_RMS, 0)} x RMS: {len(s['large_residual_lines'])} (file lines "
            f"{s['large_residual_lines'][:12]})"
        )
        c = s["components_rms_mm"]
        L.append(
            "  components RMS [mm]: "
            + ", ".join(f"{k} {_f(v)}" for k, v in c.items())
            + f" (transverse per axis {_f(c['transverse'] / math.sqrt(2))})"
        )
        L.append("  1. pairs (per pose = RMS(dr)/sqrt2, vs the residual RMS; corr of the two residual vectors):")
        for k, p in s["pairs"].items():
            if not p.get("n_pairs"):
                L.append(f"     {k:18s} none")
                continue
            extra = ""
            if k == "revisit":
                extra = (
                    f"; gap median {_f(p['gap_rows_median'], 0)} rows (max {_f(p['gap_rows_max'], 0)})"
                    + (f" ({_f(p['gap_s_median'], 0)} s)" if "gap_s_median" in p else "")
                    + f", |dr| vs gap slope {_f(p['dr_vs_gap']['slope'], 5)} mm/row "
                    f"(t {_f(p['dr_vs_gap']['t'], 1)})"
                )
            L.append(
                f"     {k:18s} {p['n_pairs']:5d} pairs: |dp| {_f(p['rms_dp_mm'])} mm, per pose "
                f"{_f(p['per_pose_mm'])} mm = {_f(p['per_pose_over_rms'], 2)} x RMS (nominal geometry "
                f"{_f(p['per_pose_nominal_mm'])}), corr {_f(p['corr'], 2)}{extra}"
            )
            if "long_gap" in p:
                lg = p["long_gap"]
                L.append(
                    f"        {lg['n_pairs']} revisit(s) more than {LONG_GAP} rows apart"
                    + (f" (median {_f(lg['gap_h_median'], 1)} h)" if "gap_h_median" in lg else "")
                    + f": |dp| {_f(lg['rms_dp_mm'])} mm, per pose {_f(lg['per_pose_mm'])} mm"
                )
            if "n_outliers" in p:
                L.append(
                    f"        median |dr| {_f(p['median_dr_mm'])} mm; {p['n_outliers']} pair(s) with |dr| > "
                    f"{_f(OUTLIER_DR * MM, 1)} mm, without them per pose {_f(p['per_pose_without_outliers_mm'])} "
                    "mm" + (f" (file lines of the worse visit: {p['outlier_lines']})" if p["outlier_lines"] else "")
                )
            else:
                L.append(f"        median |dr| {_f(p['median_dr_mm'])} mm")
            for b in p.get("by_angle", []):
                L.append(
                    f"        orientation diff {_f(b['lo'], 3)}-{_f(b['hi'], 2)} rad: {b['n_pairs']} pairs, "
                    f"per pose {_f(b['per_pose_mm'])} mm, corr {_f(b['corr'], 2)}"
                )
            if "joints_differing" in p:
                pats = ", ".join(
                    f"[{kk}] {v['n_pairs']}: {_f(v['per_pose_mm'])} mm" for kk, v in p["joints_differing"].items()
                )
                L.append(f"        joints differing by > 0.5 rad: {pats}")
                md = p["mean_diff_q3_high_minus_low_base_mm"]
                L.append(
                    f"        mean r(larger q3) - r(smaller q3), base frame: ({', '.join(_f(v) for v in md)}) mm, "
                    f"t ({', '.join(_f(v, 1) for v in p['mean_diff_t'])}); RMS about it "
                    f"{_f(p['rms_diff_about_mean_mm'])} mm"
                )
        if s["branches"]:
            L.append(
                "     per elbow branch RMS: "
                + ", ".join(f"{k}: {v['n']} poses {_f(v['rms_mm'])} mm" for k, v in s["branches"].items())
            )
        L.append("  2./3. |r| against covariates (OLS slope of |r| in mm per unit, t, Spearman; binned RMS [mm]):")
        for k, v in s["covariates"].items():
            bins = " ".join(f"{_f(b['rms_mm'])}" for b in v["bins"])
            L.append(
                f"     {k:19s} [{_f(v['range'][0], 2)}, {_f(v['range'][1], 2)}] slope {_f(v['slope'], 4)} "
                f"t {_f(v['t'], 1)} rho {_f(v['spearman'], 2)} | bins: {bins}"
            )
        rb = s["covariates"]["reach_m"]["bins"]
        L.append(
            "     reach bins radial/tangential/vertical [mm]: "
            + "; ".join(
                f"{_f(b['lo'], 2)}-{_f(b['hi'], 2)} m: "
                f"{_f(b['radial_mm'])}/{_f(b['tangential_mm'])}/{_f(b['vertical_mm'])}"
                for b in rb
            )
        )
        jr = s["joint_regression"]
        L.append(
            f"     joint regression (R2 {_f(jr['r2'], 3)}), mm per SD (t): "
            + ", ".join(f"{k} {_f(v['mm_per_sd'], 4)} ({_f(v['t'], 1)})" for k, v in jr["coef"].items())
        )
        d = s["drift"]
        L.append(
            "     drift vs row [mm/1000 rows (t)]: "
            + ", ".join(
                f"{k} {_f(d[k]['slope_mm_per_1000_rows'], 4)} ({_f(d[k]['t'], 1)}); with position "
                f"{_f(d[k]['position_controlled']['slope_mm_per_1000_rows'], 4)} "
                f"({_f(d[k]['position_controlled']['t'], 1)})"
                for k in "xyz"
            )
            + f"; block means RMS {_f(d['block_means_rms_mm'])} mm vs {_f(d['block_means_if_independent_mm'])} "
            f"if independent; temperature spread {_f(s['temperature_spread_c'], 2)} C, corr(temperature, row) "
            f"{_f(s['temperature_vs_row_corr'], 2)}"
        )
        c = s["correlation"]
        L.append(f"  4. residual correlation ({c['n_rows']} rows; revisits excluded):")
        L.append("     joint distance [rad]: " + _bins(c["joint"], 2))
        L.append("     Cartesian distance [m]: " + _bins(c["cartesian"], 3))
        L.append("     arm joints q1-q3 [rad]: " + _bins(c["arm"], 2))
        L.append("     wrist q4-q6 with the arm within 0.05 rad [rad]: " + _bins(c["wrist_at_same_arm"], 2))
        L.append(
            "     nearest neighbour [rad]: "
            + _bins(c["nearest_neighbour"], 2, "n")
            + f"; median NN distance {_f(c['nn_median_rad'], 3)} rad"
        )
        cf = c["close_in_space_far_in_joints"]
        L.append(
            f"     half-correlation distance: {_f(c['half_corr_rad'], 3)} rad, {_f(c['half_corr_m'], 3)} m; "
            f"pairs < 2 cm apart but > 0.5 rad in joints: {cf['n_pairs']} (corr {_f(cf['corr'], 2)})"
        )
        L.append("")
    L.append(f"Total runtime {_f(res['runtime_s'], 1)} s ({res['threads']} torch thread(s))")
    return "\n".join(L)


def _clean(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    return x


def run(data_dir: Path, names: tuple[str, ...], a_rows: int, pair_rows: int, tol: float) -> dict:
    """Investigate the series ``names`` of the ur10-ipa folder ``data_dir``.

    Args:
        data_dir: the ur10-ipa folder (holds Series_A ... Series_D).
        names: series letters, a subset of :data:`SERIES`.
        a_rows: Series A is fitted on this many seeded rows (0: all).
        pair_rows: rows for the correlation curves (seeded subsample).
        tol: a revisit has every joint within this [rad].

    Returns:
        The result as JSON-ready data (non-finite floats as None), with the runtime [s].
    """
    t0 = time.perf_counter()
    out = [investigate(s, series_file(data_dir, s), a_rows, pair_rows, tol) for s in names]
    return _clean(
        {
            "robot": ROBOT,
            "data_dir": str(data_dir),
            "seed": SEED,
            "tol_rad": tol,
            "threads": torch.get_num_threads(),
            "series": out,
            "runtime_s": time.perf_counter() - t0,
        }
    )
