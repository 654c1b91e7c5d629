"""Plan a measurement campaign: the ``K`` poses that make a kinematic calibration most informative.

Candidates are given (a file of joint configurations the robot may take) or sampled within the joint limits where the
tracker sees the probe (:func:`sample_candidates`, the simulator's line-of-sight rule). Among them :func:`plan_poses`
picks ``K`` greedily by the I-optimal criterion (the mean position variance over the candidates; or the D-optimal one)
on the identifiable geometric, instrument and lever-arm parameters (:mod:`torchcal.estimate.design`), a share of the
picks (``edge_share``, default 10 %) among the candidates at the edges of the region (some joint beyond the 2.5 % or
97.5 % quantile of the candidates', as calibrate's held-out guard defines them,
:func:`~torchcal.stats.at_edges`): an optimal design favours poses that separate parameters, which are not
always those at the limits of where the robot will work, and a calibration is trusted there only if it was measured
there.

The prediction: the parameters' standard deviations after ``K`` poses and the predicted held-out RMSE over the
candidates (the region), for ``K`` and for a grid of sizes (the curve), with the same for ``K`` random candidates as a
reference.

With a run whose model has a learned correction with a predictive standard deviation (a Gaussian process,
:func:`~torchcal.estimate.covariance.learned_std`), a share of the picks (``learned_share``, none by default) can go
to where that correction is least certain instead: the candidate with the largest predictive variance, discounted by
``1 - exp(-d^2 / 2 l^2)`` for each pose planned so far at distance ``d`` (joints scaled to the candidates' range,
``l`` = :data:`LEARNED_LENGTH`), a squared-exponential kernel's variance reduction, so that these picks spread over the
uncertain region instead of piling up at its worst point. The kinematic prediction does not count what they add. On
the real UR10 they did not help a second campaign planned with the first one's run (docs/real-data.md, *Planning the
poses*): the least certain poses are those where the robot seldom works, and every one of them is a pose less where
it does.

A share of the picks (``spread_share``, default 50 %) spreads the design over where the robot works instead, by kernel
herding on the candidates (:class:`SpreadTurns`). The I and D criteria assume the geometric model is right; a real
robot also has a non-geometric residual, a smooth field over the joints that the geometry absorbs wherever the design
samples it, and a design that piles up where the geometry is most informative lets that field bias it. Poses that
follow the candidates' density average the field out as a random design does (docs/real-data.md, *Planning the
poses*, has the measurements).

The design depends on the method the poses will be calibrated with (:meth:`PlanOptions.for_method`). For
``kinematic`` it is the one above. Every other method ends in a learned correction, which needs poses where the robot
works, as densely as it will work there: the criterion's picks, at the poses that separate the parameters, and the
edge picks are poses it lacks. There the first :data:`GEOMETRY_PICKS` picks are the criterion's (the geometry is
settled on about that many planned poses) and every later pick but the edges' (``edge_share`` 2 %) is a spread pick,
with the kernel length of the learned correction's discount (:data:`LEARNED_LENGTH`): the density is matched at the
scale the correction varies on.
The predicted error still counts the kinematic calibration only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal import _console
from torchcal import stats as S
from torchcal._method import Method
from torchcal._threads import torch_threads
from torchcal.effects import Context
from torchcal.effects.model import MeasurementModel
from torchcal.errors import OptionError
from torchcal.estimate.covariance import learned_std
from torchcal.estimate.design import (
    Priors,
    covariance,
    design_problem,
    greedy_design,
    information,
    log_det,
    predicted_rmse,
)
from torchcal.robot import transforms as tf
from torchcal.sim.poses import Scene, sample_joints
from torchcal.stats import HOLDOUT_EDGE, at_edges

Tensor = torch.Tensor

#: the sizes of the curve of predicted error against K (those up to twice K or the candidates' number, K and that)
CURVE = (5, 10, 20, 30, 50, 100, 200, 300, 500, 1000, 2000, 5000, 10000)
#: the correlation length of the learned correction's discount between planned poses, in joints scaled to the
#: candidates' range [1]: a tenth of each joint's range
LEARNED_LENGTH = 0.1
#: the kernel length of the spreading picks (:class:`SpreadTurns`), in joints scaled to the candidates' range [1]
SPREAD_LENGTH = 0.25
#: a design for a learned correction (module docstring): the picks left to the criterion before the spread picks
#: take over, and the share of the edge picks (one in fifty: the learned correction's region reaches the joints'
#: edges, and every edge pick is a pose less where the robot works)
GEOMETRY_PICKS = 30
LEARNED_EDGE_SHARE = 0.02
#: the methods whose design is the kinematic one; every other method of calibrate ends in a learned correction
KINEMATIC_METHODS = (Method.KINEMATIC,)
#: where a tracker stands when nothing says where: 2.5 m in front of the base, 0.2 m above its plane (the simulator
#: draws 2-3 m and -0.3..0.5 m)
DEFAULT_TRACKER = (2.5, 0.0, 0.2)
#: the probe's lever arm on the flange when nothing says which [m] (the simulator's nominal)
DEFAULT_LEVER = (0.0, 0.0, 0.1)


@dataclass(frozen=True)
class PlanOptions:
    """What :func:`plan_poses` reads.

    Attributes:
        k: poses to pick.
        criterion: ``"I"`` (default) or ``"D"`` (:mod:`torchcal.estimate.design`).
        edge_share: share of the picks made among the candidates at the edges of the region (0: none).
        learned_share: share of the picks made where the learned correction is least certain (where the model has
            one with a predictive standard deviation; 0: none).
        spread_share: share of the picks that follow the candidates' density (0: none; module docstring).
        spread_from: the first this many picks are left to the criterion (and the edges) before the spread picks begin.
        spread_length: the spread picks' kernel length, in joints scaled to the candidates' range [1].
        method: the method the poses will be calibrated with, as reported (:meth:`for_method` sets the shares).
        sigma_tracker: tracker noise per axis [m]; sigma_joint: joint noise [rad] (the fits' stochastic model).
        s0_sq: variance factor of the stochastic model (a run's own; 1 for simulated data).
        priors: the fits' priors.
        seed: of the random reference design.
    """

    k: int
    criterion: str = "I"
    edge_share: float = 0.1
    learned_share: float = 0.0
    spread_share: float = 0.5
    spread_from: int = 0
    spread_length: float = SPREAD_LENGTH
    method: str = "kinematic"
    sigma_tracker: float = 15e-6
    sigma_joint: float = math.radians(0.0005)
    s0_sq: float = 1.0
    priors: Priors = field(default_factory=Priors)
    seed: int = 0

    @classmethod
    def for_method(cls, method: str, k: int, **given) -> PlanOptions:
        """The design for poses calibrated with ``method`` (module docstring); ``given`` options override it (a
        None among them keeps the method's)."""
        given = {n: v for n, v in given.items() if v is not None}
        if method in KINEMATIC_METHODS:
            return cls(k=k, method=method, **given)
        learned = {
            "edge_share": LEARNED_EDGE_SHARE,
            "spread_share": 1.0,
            "spread_from": GEOMETRY_PICKS,
            "spread_length": LEARNED_LENGTH,
        }
        return cls(k=k, method=method, **(learned | given))


@dataclass
class Plan:
    """The planned poses and what they predict.

    Attributes:
        index: ``(K,)`` the chosen candidates' indices, in the order picked.
        q: ``(K, dof)`` their joints [rad].
        edge: ``(K,)`` bool, at the edges of the region.
        learned: ``(K,)`` bool, picked where the learned correction is least certain.
        spread: ``(K,)`` bool, picked to follow the candidates' (or the work poses') density.
        names, units, sigma: the identifiable parameters and their predicted standard deviations after the ``K``
            poses [m or rad].
        held: the parameters no choice among the candidates determines (held in the fit), with the reason.
        predicted_rmse: predicted held-out RMSE over the candidates after the ``K`` poses [m].
        random_rmse: the same for ``K`` random candidates (seeded) [m].
        curve: ``[(k, predicted RMSE [m])]`` of the planned order's first ``k``.
        log_det, random_log_det: the D criterion of the planned and the random design.
    """

    index: Tensor
    q: Tensor
    edge: Tensor
    learned: Tensor
    spread: Tensor
    names: list[str]
    units: list[str]
    sigma: Tensor
    held: list[dict]
    predicted_rmse: float
    random_rmse: float
    curve: list[tuple[int, float]]
    log_det: float
    random_log_det: float
    n_candidates: int
    options: PlanOptions
    n_work: int = 0  # the work poses the spread picks followed (0: the candidates)
    n_identifiable: int = 0  # the parameters poses spread over the joint ranges identify (:func:`identifying`)
    identifying_k: int | None = None  # the fewest planned poses (of the curve's sizes) that identify them all

    @property
    def identifies(self) -> bool:
        """Whether the ``K`` planned poses identify every parameter poses spread over the joint ranges do: where
        not, the calibration of these poses cannot determine the geometry and no accuracy is predicted."""
        return self.identifying_k is not None and self.identifying_k <= len(self.index)

    def to_dict(self) -> dict:
        scale = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg")}
        return {
            "k": len(self.index),
            "method": self.options.method,
            "n_candidates": self.n_candidates,
            "criterion": f"greedy {self.options.criterion}-optimal on the whitened Jacobian of the identifiable "
            "geometry, instrument pose and lever arm, priors as the starting information",
            "edge_share": self.options.edge_share,
            "n_edge": int(self.edge.sum()),
            "learned_share": self.options.learned_share if bool(self.learned.any()) else 0.0,
            "n_learned": int(self.learned.sum()),
            "spread_share": self.options.spread_share,
            "spread_from": self.options.spread_from,
            "spread_length": self.options.spread_length,
            "n_spread": int(self.spread.sum()),
            "spread_toward": f"{self.n_work} work poses" if self.n_work else "the candidates",
            "stochastic_model": {
                "tracker_noise_um": self.options.sigma_tracker * 1e6,
                "joint_noise_deg": math.degrees(self.options.sigma_joint),
                "variance_factor": self.options.s0_sq,
            },
            "identifies": self.identifies,
            "n_identifiable": self.n_identifiable,
            "identifying_k": self.identifying_k,
            "predicted_holdout_rmse_mm": _mm(self.predicted_rmse),
            "random_predicted_holdout_rmse_mm": _mm(self.random_rmse),
            "log_det": self.log_det,
            "random_log_det": self.random_log_det,
            "curve": [{"k": k, "predicted_holdout_rmse_mm": _mm(v)} for k, v in self.curve],
            "parameters": [
                {"name": n, "unit": scale[u][1], "sigma": None if math.isnan(s) else float(s) * scale[u][0]}
                for n, u, s in zip(self.names, self.units, self.sigma.tolist())
            ],
            "held": [{"name": h["name"], "reason": h["reason"]} for h in self.held],
            "index": self.index.tolist(),
        }

    def markdown(self) -> str:
        d = self.to_dict()
        if d["method"] in KINEMATIC_METHODS:
            learned = (
                "A learned correction is not counted, and it needs poses where the robot works rather than these: "
                "for the default method, plan with --method auto"
            )
        else:
            learned = (
                f"For the {d['method']} method: after the first {d['spread_from']} picks every pick but the edges' "
                f"follows the density of {d['spread_toward']}, where the learned correction needs its poses; what it "
                "adds is not counted"
            )
        if self.identifies:
            random = d["random_predicted_holdout_rmse_mm"]
            random = "no more than these" if random is None else f"{random:.4f} mm"
            predicted = (
                f"- predicted held-out RMSE of a kinematic calibration over the candidates: "
                f"{d['predicted_holdout_rmse_mm']:.4f} mm ({d['k']} random candidates: {random}). {learned} "
                "(docs/real-data.md, *Planning the poses*)"
            )
        else:
            predicted = f"- **no accuracy predicted**: {self.degenerate_reason()}"
        lines = [
            f"# Planned poses: {d['k']} of {d['n_candidates']} candidates",
            "",
            f"{d['criterion']}; {d['n_edge']} at the edges of the region, {d['n_learned']} picked where the learned "
            f"correction is least certain, {d['n_spread']} following the density of {d['spread_toward']}.",
            "",
            predicted,
            f"- variance factor {d['stochastic_model']['variance_factor']:.3g}, tracker noise "
            f"{d['stochastic_model']['tracker_noise_um']:.3g} um",
            "",
            "| K | predicted held-out RMSE [mm] |",
            "|---:|---:|",
            *[f"| {c['k']} | {_cell(c['predicted_holdout_rmse_mm'])} |" for c in d["curve"]],
            "",
            "| parameter | predicted sigma |",
            "|---|---:|",
            *[
                f"| {p['name']} | {'none' if p['sigma'] is None else format(p['sigma'], '.3g')} {p['unit']} |"
                for p in d["parameters"]
            ],
            "",
        ]
        return "\n".join(lines)

    def degenerate_reason(self) -> str:
        """Why the planned poses predict nothing (where :attr:`identifies` is false)."""
        k = len(self.index)
        if self.identifying_k is None:
            fewer = f"no choice of up to {self.curve[-1][0]} of the {self.n_candidates} candidates does"
        else:
            fewer = f"the first {self.identifying_k} planned poses would"
        need = self.n_identifiable - weak_allowance(self.n_identifiable)
        return (
            f"the {k} planned poses cannot identify {need} of the {self.n_identifiable} parameters of the geometry, "
            f"instrument pose and lever arm that poses spread over the joint ranges identify ({fewer}); a "
            "calibration of them would be refused or would hold parameters it needs: give more distinct candidates or "
            "a larger n (--n)"
        )


def _mm(v: float) -> float | None:
    """[m] -> [mm]; None for NaN, a prediction not made."""
    return None if math.isnan(v) else v * 1e3


def _cell(v: float | None) -> str:
    return "none (not identified)" if v is None else f"{v:.4f}"


#: joint configurations spread over the joint ranges (seeded) that tell which parameters poses can identify at all
GENERIC_POSES = 200


def weak_allowance(n: int) -> int:
    """How many of ``n`` parameters a design may leave weak and still predict: one in ten, at least one. A few dozen
    well spread poses determine all but a parameter or two better than the analysis's strict independence test
    asks (a calibration holds those at their priors and says so), while a degenerate design (one pose, the same
    pose repeated) leaves most of them undetermined."""
    return max(1, n // 10)


def identifying(model: MeasurementModel, q: Tensor, opts: PlanOptions) -> int:
    """How many of the design's parameters the poses ``q (N, dof)`` [rad] identify (those
    :func:`~torchcal.estimate.design.design_problem` keeps: determined better than their priors, by the same
    identifiability analysis as a calibration's)."""
    problem = design_problem(
        model, q, sigma_tracker=opts.sigma_tracker, sigma_joint=opts.sigma_joint, priors=opts.priors
    )
    return len(problem.names)


def identifying_prefix(
    model: MeasurementModel, q: Tensor, order: Tensor, sizes: tuple[int, ...], opts: PlanOptions, need: int
) -> int | None:
    """The smallest of ``sizes`` whose first poses of ``order`` identify ``need`` parameters (None: not even the
    largest), by bisection: more poses never identify fewer."""
    sizes = sorted(sizes)
    if identifying(model, q[order[: sizes[-1]]], opts) < need:
        return None
    lo, hi = 0, len(sizes) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if identifying(model, q[order[: sizes[mid]]], opts) >= need:
            hi = mid
        else:
            lo = mid + 1
    return sizes[lo]


def distinct_poses(q: Tensor) -> Tensor:
    """The rows of ``q (N, dof)`` with joints no earlier row has, in their order."""
    return q[distinct_index(q).to(q.device)]


def distinct_index(q: Tensor) -> Tensor:
    """The indices ``(M,)`` of the rows of ``q (N, dof)`` with joints no earlier row has (:func:`distinct_poses`)."""
    first = S.first_alike(q.detach().cpu())
    return torch.nonzero(first == torch.arange(len(first))).flatten()


def plan_loads(k: int, levels) -> Tensor:
    """The payload ``(k,)`` [kg] of each of ``k`` planned poses over the loads ``levels``: the levels in turn, in the
    order the poses were picked, so that every load takes an equal share (within one row) of the criterion's early
    picks, of the spread picks and of the edge picks, and its rows cover the region the plan covers. One model fits
    such a campaign (rows cycling over 0, 5 and 10 kg on a simulated UR10: 0.84-0.98x the error of a model fitted per
    load, docs/reference.md, *Loads*); a description without link masses or measured torques needs rows at two loads or
    more to tell a joint's stiffness from its links' weight."""
    lv = [float(v) for v in levels]
    if not lv or any(not (0.0 <= v < 3000.0) for v in lv):
        raise OptionError(f"payload levels must be one or more masses in kg, 0 <= m < 3000, got {levels!r}")
    return torch.tensor(lv, dtype=torch.float64, device="cpu")[torch.arange(k, device="cpu") % len(lv)]


def loads_summary(payload: Tensor) -> dict:
    """The plan's ``loads`` block: which payloads [kg] and how many planned rows each."""
    levels = sorted({float(v) for v in payload})
    return {"levels_kg": levels, "rows": [int((payload == v).sum()) for v in levels]}


#: how many poses :func:`sample_candidates` draws at most, in multiples of the candidates asked for, before it settles
#: for the usable ones it has: a 7-axis arm in a tight scene sees one draw in a few hundred, and drawing on until the
#: pool is full took minutes where a few thousand usable candidates were there
SAMPLE_DRAWS = 40


def sample_candidates(
    model: MeasurementModel,
    n: int,
    seed: int,
    tracker_in_base: Tensor | None = None,
    lever: Tensor | None = None,
    *,
    need: int = 1,
    region: Tensor | None = None,
) -> Tensor:
    """Up to ``n`` random poses ``(M, dof)`` within the joint limits (and within ``region`` ``(2, dof)``, a run's
    calibrated joint ranges, where given) that a tracker at ``tracker_in_base`` ``(3,)`` [m] (default
    :data:`DEFAULT_TRACKER`) sees with the lever arm ``lever`` ``(3,)`` [m] (default :data:`DEFAULT_LEVER`), by
    rejection sampling of at most :data:`SAMPLE_DRAWS` times ``n`` draws (seeded: the same poses every time).

    Fewer than ``n`` where the draws run out: those, said on stderr, as long as there are at least ``need`` (the poses
    the plan picks); refused only below that."""
    robot = model.robot
    dt = robot.dtype
    tb = (
        torch.tensor(DEFAULT_TRACKER, dtype=dt, device=robot.device)
        if tracker_in_base is None
        else tracker_in_base.to(dt)
    )
    lv = torch.tensor(DEFAULT_LEVER, dtype=dt, device=robot.device) if lever is None else lever.to(dt)
    scene, g = Scene(robot, tb, lv), torch.Generator().manual_seed(seed)
    lo, hi = _sample_box(robot, region)
    got, count, drawn, batch = [], 0, 0, max(4 * n, 256)
    while count < n and drawn < SAMPLE_DRAWS * n:
        # a CPU generator: the same candidates on every device
        cand = lo + (hi - lo) * torch.rand(batch, robot.dof, generator=g, dtype=dt, device="cpu").to(robot.device)
        keep = cand[scene.visible(cand)]
        got.append(keep)
        count, drawn = count + len(keep), drawn + batch
    q = torch.cat(got)[:n]
    where = "within the run's calibrated region" if region is not None else "within the joint limits"
    if len(q) < max(need, 1):
        raise OptionError(
            f"only {len(q)} of {drawn} poses drawn {where} satisfy the line-of-sight rule, fewer than the {need} the "
            "plan needs; move the tracker (tracker, --tracker), or give candidates in a file"
        )
    if len(q) < n:
        _console.info(
            f"plan: {len(q)} of {drawn} poses drawn {where} satisfy the line-of-sight rule (asked for {n}): planning "
            "among them"
        )
    return q


def candidate_region(model: MeasurementModel) -> tuple[Tensor | None, list[int]]:
    """The box a plan with a run samples its candidates in: the run's calibrated region, with every joint the run's
    training rows barely moved (narrow: :func:`~torchcal.robot.ranges.narrow_joints`) opened to its limits; and
    those joints (1-based). Inside the region a plan adds what a new campaign there would tell; a narrow joint's
    geometry the run held near nominal by its prior, and only poses that move that joint tell it.

    Returns:
        ``(region (2, dof) or None where the run records none, the narrow joints)``."""
    from torchcal.robot.ranges import narrow_joints

    region = model.region
    if region is None:
        return None, []
    robot = model.robot
    narrow = [n.joint for n in narrow_joints(region, robot.limits, robot.joint_types)]
    if not narrow:
        return region, []
    out = region.clone()
    for j in narrow:
        out[0, j - 1], out[1, j - 1] = robot.limits[j - 1, 0], robot.limits[j - 1, 1]
    return out, narrow


def _sample_box(robot, region: Tensor | None) -> tuple[Tensor, Tensor]:
    """The joint box to draw from: the limits clipped to one turn, and to ``region`` where given (where a region
    lies outside the limits, the limits)."""
    lo, hi = robot.limits[:, 0].clamp(min=-math.pi), robot.limits[:, 1].clamp(max=math.pi)
    if region is not None:
        r = region.to(device=lo.device, dtype=lo.dtype)
        lo2, hi2 = torch.maximum(lo, r[0]), torch.minimum(hi, r[1])
        ok = lo2 <= hi2
        lo, hi = torch.where(ok, lo2, lo), torch.where(ok, hi2, hi)
    return lo, hi


def scene_of(model: MeasurementModel) -> tuple[Tensor, Tensor]:
    """The tracker's position in the base frame ``(3,)`` and the lever arm ``(3,)`` [m] of a calibrated model."""
    robot = model.robot
    with torch.no_grad():
        return tf.invert(robot.T_tracker_base())[:3, 3].clone(), robot.t_flange_probe().clone()


class LearnedTurns:
    """Every ``round(1 / share)``-th pick (offset from the edge picks) goes to the candidate with the largest
    variance ``score``, the learned correction's predictive variance, discounted near the poses planned so far (module
    docstring)."""

    def __init__(self, std: Tensor, where: Tensor, share: float, length: float = LEARNED_LENGTH):
        self.score = std.square().clone()  # (N,) predictive variance [m^2]
        self.where = where  # (N, d) joints scaled to [0, 1]
        self.every = max(1, round(1.0 / share))
        self.length = length
        self.seen: set[int] = set()  # picks already folded into the discount
        self.turns: list[int] = []

    def fold(self, taken: Tensor) -> None:
        """Discount the score near the picks not yet folded in."""
        for i in set(torch.nonzero(taken).flatten().tolist()) - self.seen:
            d2 = (self.where - self.where[i]).square().sum(-1)
            self.score = self.score * (1.0 - torch.exp(-0.5 * d2 / self.length**2))
            self.seen.add(i)

    def __call__(self, j: int, taken: Tensor) -> Tensor | None:
        self.fold(taken)
        if (j + 1 + self.every // 2) % self.every != 0 or not bool((self.score[~taken] > 0).any()):
            return None
        self.turns.append(j)
        return self.score


def _scaled(q: Tensor, of: Tensor | None = None) -> Tensor:
    """The joints ``of`` (default ``q``) scaled to the candidates' ``q`` range, ``[0, 1]`` per joint."""
    lo = q.min(0).values
    return ((q if of is None else of) - lo) / (q.max(0).values - lo).clamp(min=1e-12)


class Turns:
    """The other criteria's turns in order of precedence: the first that claims pick ``j`` makes it. A pick the edge
    rule claims (every ``edge_every``-th) stays the I or D criterion's among the edge candidates."""

    def __init__(self, turns: list[LearnedTurns | SpreadTurns], edge_every: int = 0):
        self.turns = turns
        self.edge_every = edge_every

    def __call__(self, j: int, taken: Tensor) -> Tensor | None:
        edge = self.edge_every > 0 and (j + 1) % self.edge_every == 0
        out = None
        for t in self.turns:
            if out is None and not edge:
                out = t(j, taken)
            else:  # every one keeps its discount current, whether it has the turn or not
                t.fold(taken)
        return out


def learned_turns(model: MeasurementModel, q: Tensor, share: float) -> LearnedTurns | None:
    """The learned correction's turns (:class:`LearnedTurns`), or None where ``share`` is 0 or the model's learned
    corrections have no predictive standard deviation."""
    if share <= 0:
        return None
    std = learned_std(model, Context(q=q))
    if std is None:
        return None
    return LearnedTurns(std.norm(dim=-1), _scaled(q), share)


class SpreadTurns:
    """A share of the picks (pick ``j >= start`` where ``floor((j + 1) share)`` steps up: any share; below a share
    of 1 the first pick is the criterion's) by kernel herding: the candidate that brings the planned poses' kernel
    mean closest to the candidates', ``mean_k K(x, x_k) - sum_p K(x, x_p) / (n + 1)`` over the ``n`` poses planned so
    far, with a squared-exponential kernel of length ``length`` in joints scaled to the candidates' range. These picks
    follow the candidates' density, as a random design does, without a random design's clumps and gaps; given
    ``toward``, the poses where the robot will work (scaled alike), they follow those instead (``x_k`` over them)."""

    def __init__(
        self,
        where: Tensor,
        share: float,
        length: float = SPREAD_LENGTH,
        chunk: int = 1024,
        start: int = 0,
        toward: Tensor | None = None,
    ):
        self.where = where  # (N, d) joints scaled to [0, 1]
        toward = where if toward is None else toward
        self.share = share
        self.start = start
        self.length = length
        self.mean = kernel_mean(where, toward, length, chunk)
        self.sum = torch.zeros_like(self.mean)
        self.seen: set[int] = set()
        self.turns: list[int] = []

    def fold(self, taken: Tensor) -> None:
        """Add the picks not yet counted to the planned poses' kernel sum."""
        for i in set(torch.nonzero(taken).flatten().tolist()) - self.seen:
            d2 = (self.where - self.where[i]).square().sum(-1)
            self.sum = self.sum + torch.exp(-0.5 * d2 / self.length**2)
            self.seen.add(i)

    def __call__(self, j: int, taken: Tensor) -> Tensor | None:
        self.fold(taken)
        if j < self.start or math.floor((j + 1) * self.share + 1e-9) <= math.floor(j * self.share + 1e-9):
            return None
        self.turns.append(j)
        return self.mean - self.sum / (len(self.seen) + 1)


#: the most poses the spread picks' kernel mean is taken over: beyond it a seeded random subset of this size (the
#: default pool of sampled candidates is taken whole), so that the mean costs at most ``N x SPREAD_REFERENCE``
#: kernel values and a pool of 100,000 candidates does not take ``10^10``
SPREAD_REFERENCE = 10_000


def kernel_mean(where: Tensor, toward: Tensor, length: float, chunk: int = 1024) -> Tensor:
    """``mean_k K(x, x_k) (N,)`` of a squared-exponential kernel of length ``length`` for each ``x`` of ``where
    (N, d)`` over ``toward (M, d)`` (at most :data:`SPREAD_REFERENCE` of them, a seeded subset beyond).

    The squared distances come from one matrix product per chunk of ``chunk`` rows (``|a|^2 + |b|^2 - 2 a.b``,
    clamped at 0) and the kernel is taken in place: the ``cdist``, square and exponential of ``(chunk, M)`` each as
    a new tensor cost several times more.
    """
    if len(toward) > SPREAD_REFERENCE:
        toward = toward[torch.randperm(len(toward), generator=torch.Generator().manual_seed(0))[:SPREAD_REFERENCE]]
    b2 = toward.square().sum(-1)
    mean = torch.empty(len(where), dtype=where.dtype, device=where.device)
    for lo in range(0, len(where), chunk):  # (chunk, M) at a time: memory stays bounded
        a = where[lo : lo + chunk]
        d2 = torch.addmm(a.square().sum(-1, keepdim=True) + b2, a, toward.T, alpha=-2.0).clamp_(min=0.0)
        mean[lo : lo + chunk] = d2.mul_(-0.5 / length**2).exp_().mean(-1)
    return mean


def spread_turns(
    q: Tensor, share: float, start: int = 0, length: float = SPREAD_LENGTH, work: Tensor | None = None
) -> SpreadTurns | None:
    """The turns that spread the design (:class:`SpreadTurns`) from pick ``start`` on, toward the candidates' density
    or the ``work`` poses'; None where ``share`` is 0."""
    if share <= 0:
        return None
    toward = None if work is None else _scaled(q, work)
    return SpreadTurns(_scaled(q), share, length=length, start=start, toward=toward)


def _random_index(n: int, k: int, seed: int) -> Tensor:
    return torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:k]


@torch_threads(1)  # greedy picks of 3 x 3 blocks per candidate: a second thread only waits
def plan_poses(model: MeasurementModel, q: Tensor, opts: PlanOptions, work: Tensor | None = None) -> Plan:
    """Pick ``opts.k`` of the candidates ``q (N, dof)`` [rad] for ``model``'s robot (module docstring); the spread
    picks follow the poses ``work (M, dof)`` [rad] where given (where the robot will work), else the candidates."""
    for name, top in (("edge_share", 0.5), ("learned_share", 0.5), ("spread_share", 1.0)):
        if not 0.0 <= getattr(opts, name) <= top:
            raise OptionError(f"{name} must lie in [0, {top}], got {getattr(opts, name)}")
    if opts.spread_from < 0 or not opts.spread_length > 0:
        raise OptionError(
            f"spread_from must be at least 0 and spread_length positive, got {opts.spread_from}, {opts.spread_length}"
        )
    if work is not None and (work.ndim != 2 or work.shape[1] != q.shape[1] or len(work) == 0):
        raise OptionError(f"the work poses must be (M, {q.shape[1]}) joints, got {tuple(work.shape)}")
    N = len(q)
    if not 1 <= opts.k <= N:
        raise OptionError(f"can plan 1 to {N} poses from {N} candidates, asked for {opts.k}")
    problem = design_problem(
        model, q, sigma_tracker=opts.sigma_tracker, sigma_joint=opts.sigma_joint, priors=opts.priors
    )
    edge = at_edges(q, q, HOLDOUT_EDGE)
    every = round(1.0 / opts.edge_share) if opts.edge_share > 0 else 0
    top = min(N, 2 * opts.k)
    grid = tuple(sorted({c for c in CURVE if c <= top} | {opts.k, top}))
    learned = learned_turns(model, q, opts.learned_share)
    spread = spread_turns(q, opts.spread_share, opts.spread_from, opts.spread_length, work)
    other = Turns([t for t in (learned, spread) if t is not None], every)
    design = greedy_design(
        problem, max(grid), criterion=opts.criterion, restrict=edge, every=every, checkpoints=grid, other=other
    )
    turns = set(learned.turns) if learned is not None else set()
    spread_picks = set(spread.turns) if spread is not None else set()
    # a prediction only where the poses identify what poses spread over the joint ranges do (the priors alone would
    # make one from a single pose, or from the same pose five times)
    generic = sample_joints(model.robot, GENERIC_POSES, torch.Generator().manual_seed(0))
    need = identifying(model, generic.to(q.device), opts)
    first = identifying_prefix(model, q, design.order, grid, opts, need - weak_allowance(need))
    curve = []
    for c in grid:
        S = covariance(design.information[c], opts.s0_sq)
        ok = first is not None and c >= first
        curve.append((c, predicted_rmse(problem.J, problem.noise, S, opts.s0_sq) if ok else math.nan))
    S_k = covariance(design.information[opts.k], opts.s0_sq)
    rnd = _random_index(N, opts.k, opts.seed)
    S_r = covariance(information(problem, rnd), opts.s0_sq)
    random_ok = identifying(model, q[rnd], opts) >= need - weak_allowance(need)
    index = design.order[: opts.k]
    return Plan(
        index=index,
        q=q[index],
        edge=edge[index],
        learned=torch.tensor([j in turns for j in range(opts.k)], dtype=torch.bool, device=q.device),
        spread=torch.tensor([j in spread_picks for j in range(opts.k)], dtype=torch.bool, device=q.device),
        names=problem.names,
        units=problem.units,
        sigma=S_k.diagonal().sqrt() if first is not None and opts.k >= first else torch.full_like(S_k[0], math.nan),
        held=problem.identifiability.fixed,
        predicted_rmse=dict(curve)[opts.k],
        random_rmse=predicted_rmse(problem.J, problem.noise, S_r, opts.s0_sq) if random_ok else math.nan,
        curve=curve,
        log_det=float(design.log_det[opts.k - 1]),
        random_log_det=log_det(problem, rnd),
        n_candidates=N,
        options=opts,
        n_work=0 if work is None else len(work),
        n_identifiable=need,
        identifying_k=first,
    )
