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


def visible(robot: RobotModel, q: Tensor, tracker_in_base: Tensor, t_flange_probe: Tensor,
            rule: SightRule | None = None) -> Tensor:
    """Which poses satisfy the line-of-sight rule (module docstring). ``q (N, dof)`` -> ``(N,)`` bool."""
    rule = rule or SightRule()
    with torch.no_grad():
        F, T = robot.joint_frames(q)
        probe = tf.transform_points(T, t_flange_probe)
        lever = T[:, :3, :3] @ t_flange_probe
        if float(t_flange_probe.norm()) < 1e-3:
            lever = T[:, :3, 2]
        out_dir = lever / lever.norm(dim=-1, keepdim=True)
        sight = tracker_in_base - probe
        dist = sight.norm(dim=-1, keepdim=True)
        u = sight / dist
        ok = (out_dir * u).sum(-1) >= math.cos(math.radians(rule.max_incidence_deg))

        base = torch.zeros(len(q), 1, 3, dtype=q.dtype)
        nodes = torch.cat([base, F[:, :, :3, 3], T[:, None, :3, 3]], dim=1)  # (N, K, 3)
        seg_a, seg_b = nodes[:, :-1], nodes[:, 1:]
        n_sub = max(2, int(math.ceil(float((seg_b - seg_a).norm(dim=-1).max()) / rule.skeleton_step)))
        s = torch.linspace(0.0, 1.0, n_sub, dtype=q.dtype)
        pts = seg_a[:, :, None] + (seg_b - seg_a)[:, :, None] * s[None, None, :, None]
        pts = pts.reshape(len(q), -1, 3)
        rel = pts - probe[:, None]
        along = (rel * u[:, None]).sum(-1)
        perp = (rel - along[..., None] * u[:, None]).norm(dim=-1)
        in_front = (along > 1e-3) & (along < dist)
        ok &= ~((perp < rule.clearance) & in_front).any(-1)

        ok &= (nodes[:, 1:, 2] > rule.min_height).all(-1) & (probe[:, 2] > rule.min_height)
        ok &= probe[:, :2].norm(dim=-1) >= rule.min_radius
    return ok


def sample_joints(robot: RobotModel, n: int, generator: torch.Generator) -> Tensor:
    """Uniform joints within the limits, clipped to [-pi, pi] (a turn covers every posture)."""
    lo = robot.limits[:, 0].clamp(min=-math.pi)
    hi = robot.limits[:, 1].clamp(max=math.pi)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=generator, dtype=robot.dtype)


def random_poses(robot: RobotModel, n: int, tracker_in_base: Tensor, t_flange_probe: Tensor,
                 generator: torch.Generator, rule: SightRule | None = None, max_tries: int = 200) -> Tensor:
    """``n`` random visible poses ``(n, dof)``, by rejection sampling in batches."""
    got: list[Tensor] = []
    count = 0
    for _ in range(max_tries):
        cand = sample_joints(robot, max(4 * n, 256), generator)
        keep = cand[visible(robot, cand, tracker_in_base, t_flange_probe, rule)]
        got.append(keep)
        count += len(keep)
        if count >= n:
            return torch.cat(got)[:n]
    raise RuntimeError(f"only {count} of {n} poses satisfy the line-of-sight rule; move the tracker or relax the rule")


def trajectory(robot: RobotModel, n_samples: int, tracker_in_base: Tensor, t_flange_probe: Tensor,
               generator: torch.Generator, rule: SightRule | None = None, step: float = 0.01,
               max_segment: float = 1.2) -> Tensor:
    """A continuous visible trajectory ``(n_samples, dof)`` through random visible waypoints.

    Point-to-point motion as a robot program runs it: between consecutive waypoints every
    joint follows the same smooth cosine profile (zero velocity at the waypoints, C1), with
    the number of samples set by the largest joint move (``step`` rad per sample). A
    segment is accepted only if every sample on it is visible; waypoints are drawn among
    visible poses within ``max_segment`` rad (largest joint move) of the current one.
    """
    current = random_poses(robot, 1, tracker_in_base, t_flange_probe, generator, rule)[0]
    samples = [current[None]]
    total = 1
    while total < n_samples:
        pool = random_poses(robot, 64, tracker_in_base, t_flange_probe, generator, rule)
        moves = (pool - current).abs().max(dim=-1).values
        near = torch.nonzero(moves <= max_segment).flatten()
        if len(near) == 0:
            near = torch.argsort(moves)[:4]
        for idx in near[torch.randperm(len(near), generator=generator)][:16]:
            target = pool[idx]
            m = max(20, int(math.ceil(float(moves[idx]) / step)))
            s = torch.linspace(0.0, 1.0, m + 1, dtype=current.dtype)[1:]
            seg = current + (0.5 - 0.5 * torch.cos(math.pi * s))[:, None] * (target - current)
            if bool(visible(robot, seg, tracker_in_base, t_flange_probe, rule).all()):
                samples.append(seg)
                total += len(seg)
                current = target
                break
    return torch.cat(samples)[:n_samples]
