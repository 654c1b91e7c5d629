"""Poses a laser tracker can see: random static poses and continuous trajectories.

Line-of-sight rule (all conditions at every pose, with the nominal geometry):

1. *The probe faces the tracker*: the angle between the probe's outward direction (the
   lever arm ``t_flange_probe`` turned into the base frame; the flange z axis when the
   lever arm is shorter than 1 mm) and the direction from the probe to the tracker is at
   most ``max_incidence_deg`` (default 60 deg, a wide-angle reflector).
2. *Nothing of the arm in between*: the arm's skeleton (base, every joint frame origin
   and the flange, sampled every 2 cm along the segments between them) keeps at least
   ``clearance`` (default 5 cm) from the sight line, for every point of it that lies in
   front of the probe, i.e. between probe and tracker.
3. *Physically sensible*: every skeleton point and the probe stay above the mounting
   plane (``z > min_height``, default 2 cm below the base plane is the limit), and the
   probe is at least ``min_radius`` (default 0.25 m) from the base's z axis.

Self-collision of the links with each other is not checked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.errors import OptionError
from torchcal.robot import transforms as tf
from torchcal.robot.model import RobotModel

Tensor = torch.Tensor


@dataclass
class SightRule:
    max_incidence_deg: float = 60.0
    clearance: float = 0.05
    min_height: float = -0.02
    min_radius: float = 0.25
    skeleton_step: float = 0.02


#: poses per block of :func:`visible`: its skeleton test holds poses x skeleton points x 3 numbers at once
#: (a block of 2048 poses needs tens of MB; much larger blocks leave the processor's cache and run slower)
VISIBLE_BLOCK = 2048


def visible(
    robot: RobotModel, q: Tensor, tracker_in_base: Tensor, t_flange_probe: Tensor, rule: SightRule | None = None
) -> Tensor:
    """Which poses satisfy the line-of-sight rule (module docstring). ``q (N, dof)`` -> ``(N,)`` bool.

    The poses are taken in blocks of :data:`VISIBLE_BLOCK` (every test is per pose; the skeleton's sampling step
    is chosen once from all poses, as for a single block), so memory stays bounded for any ``N``.
    """
    rule = rule or SightRule()
    blocks = []
    with torch.no_grad():
        for lo in range(0, len(q), VISIBLE_BLOCK):
            qb = q[lo : lo + VISIBLE_BLOCK]
            F, T = robot.joint_frames(qb)
            probe = tf.transform_points(T, t_flange_probe)
            lever = T[:, :3, :3] @ t_flange_probe
            if float(t_flange_probe.norm()) < 1e-3:
                lever = T[:, :3, 2]
            out_dir = lever / lever.norm(dim=-1, keepdim=True)
            sight = tracker_in_base - probe
            dist = sight.norm(dim=-1, keepdim=True)
            u = sight / dist
            ok = (out_dir * u).sum(-1) >= math.cos(math.radians(rule.max_incidence_deg))
            base = torch.zeros(len(qb), 1, 3, dtype=q.dtype)
            nodes = torch.cat([base, F[:, :, :3, 3], T[:, None, :3, 3]], dim=1)  # (N, K, 3)
            blocks.append((probe, dist, u, ok, nodes))
        if not blocks:
            return torch.zeros(0, dtype=torch.bool, device=q.device)
        longest = max(float((b[4][:, 1:] - b[4][:, :-1]).norm(dim=-1).max()) for b in blocks)
        n_sub = max(2, int(math.ceil(longest / rule.skeleton_step)))
        s = torch.linspace(0.0, 1.0, n_sub, dtype=q.dtype)
        out = []
        for probe, dist, u, ok, nodes in blocks:
            ok &= (nodes[:, 1:, 2] > rule.min_height).all(-1) & (probe[:, 2] > rule.min_height)
            ok &= probe[:, :2].norm(dim=-1) >= rule.min_radius
            # the skeleton test, by far the costliest, only for the poses the cheap tests leave (per pose, so the
            # answer is the same as testing all)
            at = torch.nonzero(ok).flatten()
            if len(at):  # a block the cheap tests rule out whole leaves no skeleton to test
                ok[at] = _clear(nodes[at], probe[at], u[at], dist[at], s, rule.clearance)
            out.append(ok)
    return torch.cat(out)


def _clear(nodes: Tensor, probe: Tensor, u: Tensor, dist: Tensor, s: Tensor, clearance: float) -> Tensor:
    """Whether the line of sight of each pose passes its arm's skeleton at ``clearance`` [m] or more ``(N,)`` bool.

    Args:
        nodes: ``(N, K, 3)`` the skeleton's joints [m]; probe: ``(N, 3)`` [m]; u: ``(N, 3)`` the unit sight from the
            probe to the tracker; dist: ``(N, 1)`` the distance [m]; s: ``(S,)`` the sampling of each segment in
            ``[0, 1]``.
    """
    seg_a, seg_b = nodes[:, :-1], nodes[:, 1:]
    pts = seg_a[:, :, None] + (seg_b - seg_a)[:, :, None] * s[None, None, :, None]
    pts = pts.reshape(len(nodes), -1, 3)
    rel = pts - probe[:, None]
    along = (rel * u[:, None]).sum(-1)
    perp = (rel - along[..., None] * u[:, None]).norm(dim=-1)
    in_front = (along > 1e-3) & (along < dist)
    return ~((perp < clearance) & in_front).any(-1)


@dataclass(eq=False)
class Scene:
    """What decides whether the tracker sees a pose: the robot, where the tracker stands, the probe's lever arm
    and the line-of-sight rule. The poses and paths below are planned in a scene.

    Attributes:
        robot: the robot the poses are planned with (its nominal geometry, as a robot program would be).
        tracker_in_base: the tracker's position ``(3,)`` [m] in the robot's base frame.
        t_flange_probe: the probe's lever arm ``(3,)`` [m] in the flange frame.
        rule: the line-of-sight rule (``None``: the default :class:`SightRule`).
    """

    robot: RobotModel
    tracker_in_base: Tensor
    t_flange_probe: Tensor
    rule: SightRule | None = None

    def visible(self, q: Tensor) -> Tensor:
        """Which poses ``q (N, dof)`` the tracker sees ``(N,)`` bool (:func:`visible`)."""
        return visible(self.robot, q, self.tracker_in_base, self.t_flange_probe, self.rule)

    def visible_runs(self, q: Tensor) -> Tensor:
        """The samples of a planned path ``q (N, dof)`` the tracker sees: a laser tracker loses the beam where the
        line of sight breaks and picks it up again after, so the measured trajectory is the path with those
        samples missing."""
        ok = torch.zeros(len(q), dtype=torch.bool)
        for i in range(0, len(q), 4096):  # in blocks: the skeleton points of a long path fill memory at once
            ok[i : i + 4096] = self.visible(q[i : i + 4096])
        return q[ok]


def _joint_box(robot: RobotModel) -> tuple[Tensor, Tensor]:
    """The joint limits clipped to [-pi, pi] ``(dof,)`` each [rad]: a turn covers every posture."""
    lo = robot.limits[:, 0].clamp(min=-math.pi)
    hi = robot.limits[:, 1].clamp(max=math.pi)
    return lo, hi


def sample_joints(robot: RobotModel, n: int, generator: torch.Generator) -> Tensor:
    """Uniform joints ``(n, dof)`` within the limits, clipped to [-pi, pi] (a turn covers every posture)."""
    lo, hi = _joint_box(robot)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=generator, dtype=robot.dtype)


def random_poses(scene: Scene, n: int, generator: torch.Generator, max_tries: int = 200) -> Tensor:
    """``n`` random poses ``(n, dof)`` the tracker sees in ``scene``, by rejection sampling in batches."""
    q, count = first_visible(scene, n, lambda: sample_joints(scene.robot, max(4 * n, 256), generator), max_tries)
    if q is None:
        raise RuntimeError(
            f"only {count} of {n} poses satisfy the line-of-sight rule; move the tracker or relax the rule"
        )
    return q


def first_visible(scene: Scene, n: int, draw, tries: int) -> tuple[Tensor | None, int]:
    """The first ``n`` poses the tracker sees among up to ``tries`` batches ``draw()`` (rejection sampling), and how
    many it saw: ``(None, count)`` when the batches held fewer."""
    got: list[Tensor] = []
    count = 0
    for _ in range(tries):
        cand = draw()
        keep = cand[scene.visible(cand)]
        got.append(keep)
        count += len(keep)
        if count >= n:
            return torch.cat(got)[:n], count
    return None, count


def trajectory(
    scene: Scene,
    n_samples: int,
    generator: torch.Generator,
    step: float = 0.01,
    max_segment: float = 1.2,
    stop_after: int | None = None,
) -> Tensor:
    """A continuous visible trajectory ``(n_samples, dof)`` through random visible waypoints.

    Point-to-point motion as a robot program runs it: between consecutive waypoints every
    joint follows the same smooth cosine profile (zero velocity at the waypoints, C1), with
    the number of samples set by the largest joint move (``step`` rad per sample). A
    segment is accepted only if every sample on it is visible; waypoints are drawn among
    visible poses within ``max_segment`` rad (largest joint move) of the current one. ``stop_after``: end
    at that many waypoints instead (the path then has as many samples as the moves take).
    """
    current = random_poses(scene, 1, generator)[0]
    samples = [current[None]]
    total = 1
    reached = 0
    while total < n_samples and (stop_after is None or reached < stop_after):
        pool = random_poses(scene, 64, generator)
        moves = (pool - current).abs().max(dim=-1).values
        near = torch.nonzero(moves <= max_segment).flatten()
        if len(near) == 0:
            near = torch.argsort(moves)[:4]
        for idx in near[torch.randperm(len(near), generator=generator)][:16]:
            target = pool[idx]
            seg = trajectory_between(current, target, step)
            if bool(scene.visible(seg).all()):
                samples.append(seg)
                total += len(seg)
                current = target
                reached += 1
                break
    return torch.cat(samples)[:n_samples]


#: trajectory families (``SimConfig.path``, ``torchcal simulate --path``)
PATHS = ("p2p", "multisine", "randomwalk", "sweeps")


def multisine_path(
    scene: Scene, n_samples: int, generator: torch.Generator, dt: float = 0.1, span: float = 0.8
) -> Tensor:
    """A smooth multi-sine path through most of the joint range ``(n_samples, dof)``.

    Every joint is the sum of three sines of incommensurate periods (60-600 s at the sampling interval ``dt``)
    around the middle of a visible start pose, with amplitudes that together cover ``span`` of the half range
    (limits clipped to one turn). Unlike the point-to-point programs, the path never stops at waypoints and
    never repeats; samples without line of sight are left out, as the tracker would.
    """
    robot = scene.robot
    lo, hi = _joint_box(robot)
    centre = random_poses(scene, 1, generator)[0]
    half = 0.5 * (hi - lo)
    mid = 0.5 * (hi + lo)
    centre = mid + 0.5 * (centre - mid)  # halfway to the middle: room for the swing on both sides
    dof = robot.dof
    periods = 60.0 + 540.0 * torch.rand(dof, 3, generator=generator, dtype=robot.dtype)
    phases = 2 * math.pi * torch.rand(dof, 3, generator=generator, dtype=robot.dtype)
    weights = torch.rand(dof, 3, generator=generator, dtype=robot.dtype) + 0.2
    room = torch.minimum(hi - centre, centre - lo).clamp(min=0.0)
    amp = weights / weights.sum(-1, keepdim=True) * torch.minimum(span * half, room)[:, None]
    got, start = [], 0.0
    while sum(len(g) for g in got) < n_samples:
        t = start + torch.arange(8192, dtype=robot.dtype) * dt
        q = centre + (amp[None] * torch.sin(2 * math.pi * t[:, None, None] / periods[None] + phases[None])).sum(-1)
        got.append(scene.visible_runs(q))
        start = float(t[-1]) + dt
        if start > 1e3 * n_samples * dt:
            raise RuntimeError("the multi-sine path is almost never visible; move the tracker or relax the rule")
    return torch.cat(got)[:n_samples]


def random_walk_path(
    scene: Scene, n_samples: int, generator: torch.Generator, speed: float = 0.004, correlation: float = 0.995
) -> Tensor:
    """A slow random walk in joint space ``(n_samples, dof)``: each joint's velocity is a first-order
    autoregressive process (smooth, ``speed`` rad per sample RMS), reflected at the limits; a step that
    would lose the line of sight turns the velocity around instead."""
    robot = scene.robot
    lo, hi = _joint_box(robot)
    q = random_poses(scene, 1, generator)[0]
    v = torch.zeros_like(q)
    innov = speed * math.sqrt(1.0 - correlation**2)
    out = torch.empty(n_samples, robot.dof, dtype=robot.dtype)
    block = 256
    i = 0
    stuck = 0
    while i < n_samples:
        noise = torch.randn(block, robot.dof, generator=generator, dtype=robot.dtype) * innov
        seg = torch.empty(block, robot.dof, dtype=robot.dtype)
        qq, vv = q.clone(), v.clone()
        for k in range(block):
            vv = correlation * vv + noise[k]
            qq = qq + vv
            over, under = qq > hi, qq < lo
            qq = torch.where(over, 2 * hi - qq, torch.where(under, 2 * lo - qq, qq))
            vv = torch.where(over | under, -vv, vv)
            seg[k] = qq
        ok = scene.visible(seg)
        n_ok = int(ok.long().cumprod(0).sum())  # the visible run from the start of the block
        if n_ok == 0:
            v = -v
            stuck += 1
            if stuck > 200:
                raise RuntimeError("the random walk is stuck without line of sight; move the tracker")
            continue
        stuck = 0
        take = min(n_ok, n_samples - i)
        out[i : i + take] = seg[:take]
        i += take
        q = seg[take - 1].clone()
        v = -vv if n_ok < block else vv
    return out


def sweeps_path(scene: Scene, n_samples: int, generator: torch.Generator, waypoints: int = 6) -> Tensor:
    """Repeated sweeps ``(n_samples, dof)``: one closed point-to-point cycle through ``waypoints`` visible
    poses, run again and again as a production program does; the continuation revisits the same path."""
    cycle = trajectory(scene, 10**9, generator, stop_after=waypoints)
    back = scene.visible_runs(trajectory_between(cycle[-1], cycle[0]))
    loop = torch.cat([cycle, back])
    reps = -(-n_samples // len(loop))
    return loop.repeat(reps, 1)[:n_samples]


def trajectory_between(a: Tensor, b: Tensor, step: float = 0.01) -> Tensor:
    """The point-to-point move ``(m, dof)`` from ``a`` to ``b`` ``(dof,)`` [rad] (cosine profile, as
    :func:`trajectory`), ``b`` included."""
    m = max(20, int(math.ceil(float((b - a).abs().max()) / step)))
    s = torch.linspace(0.0, 1.0, m + 1, dtype=a.dtype)[1:]
    return a + (0.5 - 0.5 * torch.cos(math.pi * s))[:, None] * (b - a)


def path(kind: str, scene: Scene, n_samples: int, generator: torch.Generator) -> Tensor:
    """A trajectory ``(n_samples, dof)`` of the family ``kind`` (one of :data:`PATHS`) in ``scene``."""
    makers = {"p2p": trajectory, "multisine": multisine_path, "randomwalk": random_walk_path, "sweeps": sweeps_path}
    if kind not in makers:
        raise OptionError(f"trajectory path '{kind}' is not one of {', '.join(PATHS)}")
    return makers[kind](scene, n_samples, generator)


def fixed_axis_poses(
    scene: Scene, n: int, generator: torch.Generator, axis: Tensor, spread_deg: float, max_tries: int = 50
) -> Tensor:
    """``n`` poses ``(n, dof)`` the tracker sees whose flange z axis (the tool axis) points along ``axis`` within
    ``spread_deg``: a campaign whose tool hardly turns (a robot on a lifting column measured by a total station).

    Each pose starts from uniform random joints and is pulled onto its target axis (``axis`` tilted by a uniform
    angle in ``[0, spread_deg]`` about a random perpendicular direction) by Gauss-Newton steps on the joints
    (minimum-norm steps: the other joints move as little as possible); poses that miss their target by more than
    1e-9 rad or that the tracker does not see are drawn again.

    Args:
        axis: ``(3,)`` direction in the base frame (normalised here).
        spread_deg: the largest angle between a pose's tool axis and ``axis`` [deg].
    """
    robot = scene.robot
    a = torch.as_tensor(axis, dtype=robot.dtype)
    a = a / a.norm()

    eye = torch.eye(robot.dof, dtype=robot.dtype) * 1e-6

    def jac(q: Tensor) -> Tensor:  # d z / d q (m, 3, dof) by central differences (no autograd through the chain)
        zp = robot((q[:, None, :] + eye).reshape(-1, robot.dof))[:, :3, 2].reshape(len(q), robot.dof, 3)
        zm = robot((q[:, None, :] - eye).reshape(-1, robot.dof))[:, :3, 2].reshape(len(q), robot.dof, 3)
        return ((zp - zm) / 2e-6).transpose(1, 2)

    def draw() -> Tensor:
        m = max(2 * n, 64)
        q = sample_joints(robot, m, generator)
        # targets: the axis tilted by at most spread_deg about a random direction perpendicular to it
        u = torch.linalg.cross(a.expand(m, 3), torch.randn(m, 3, generator=generator, dtype=a.dtype))
        u = u / u.norm(dim=-1, keepdim=True)
        angle = torch.rand(m, generator=generator, dtype=a.dtype) * math.radians(spread_deg)
        target = a * torch.cos(angle)[:, None] + torch.linalg.cross(u, a.expand(m, 3)) * torch.sin(angle)[:, None]
        with torch.no_grad():
            for _ in range(20):
                r = robot(q)[:, :3, 2] - target
                J = jac(q)  # (m, 3, dof)
                # rank 2 (a unit vector turns in its tangent plane): the third singular value is difference noise, cut
                dq = torch.linalg.lstsq(J, -r.unsqueeze(-1), rcond=1e-6, driver="gelsd").solution.squeeze(-1)
                q = q + dq.clamp(-0.5, 0.5)
            miss = (robot(q)[:, :3, 2] - target).norm(dim=-1)
        lo, hi = robot.limits[:, 0], robot.limits[:, 1]
        return q[(miss < 1e-9) & ((q >= lo) & (q <= hi)).all(dim=-1)]

    q, count = first_visible(scene, n, draw, max_tries)
    if q is not None:
        return q
    raise RuntimeError(
        f"only {count} of {n} poses with a fixed tool axis satisfy the line-of-sight rule; move the tracker or "
        "relax the rule"
    )


def narrow_poses(
    scene: Scene, n: int, generator: torch.Generator, joints: tuple[int, ...], width: float, max_tries: int = 200
) -> Tensor:
    """``n`` poses ``(n, dof)`` the tracker sees whose revolute ``joints`` (0-based) stay within a band of ``width``
    [rad] centred on one visible pose, the other joints ranging over their limits: a campaign that
    moves only the joints that matter most (a grid over joints 2 and 3, the wrist held still).

    The centre is a random visible pose; its band is clipped to the joint limits. A centre whose band leaves too few
    visible poses (a wrist turned so that most other joints hide the probe) is drawn again.
    """
    lo, hi = _joint_box(scene.robot)
    idx = torch.tensor(joints, dtype=torch.long)
    for _ in range(20):
        centre = random_poses(scene, 1, generator, max_tries)[0]
        c_lo = torch.maximum(centre[idx] - width / 2, lo[idx])
        c_hi = torch.minimum(centre[idx] + width / 2, hi[idx])

        def draw(c_lo=c_lo, c_hi=c_hi) -> Tensor:
            cand = sample_joints(scene.robot, max(4 * n, 256), generator)
            cand[:, idx] = c_lo + (c_hi - c_lo) * torch.rand(len(cand), len(idx), generator=generator, dtype=cand.dtype)
            return cand

        q, _ = first_visible(scene, n, draw, max_tries // 4)
        if q is not None:
            return q
    raise RuntimeError(
        f"no centre of joints {[j + 1 for j in joints]} leaves {n} poses within {math.degrees(width):.3g} deg that "
        "satisfy the line-of-sight rule; widen the band or move the tracker"
    )
