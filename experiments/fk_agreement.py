"""Forward-kinematics agreement: torchcal against an independent numpy standard DH and against pytorch-kinematics.

For each built-in robot, seeded random joint vectors within the joint limits (clamped to +-pi); the largest
absolute difference of any element of ``T_base_flange`` (metres for the translation). The pk comparison also runs
with non-zero geometric corrections (sigma 1 mm / 1 mrad), since the pk chain is rebuilt from the calibrated
geometry. The numpy DH and UR's tables here are the one copy the tests use as well.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchcal.robot import load_robot

F64 = torch.float64
#: UR's published nominal DH tables, typed in here independently of robots/*.yaml: every UR shares the twists
#: alpha; a and d per robot [m]
_UR_ALPHA = (math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0)
_UR_A_D = {
    "ur5": ((0, -0.425, -0.39225, 0, 0, 0), (0.089159, 0, 0, 0.10915, 0.09465, 0.0823)),
    "ur10": ((0, -0.612, -0.5723, 0, 0, 0), (0.1273, 0, 0, 0.163941, 0.1157, 0.0922)),
}
#: rows (a, alpha, d) per joint
UR_DH = {name: list(zip(a, _UR_ALPHA, d)) for name, (a, d) in _UR_A_D.items()}


def numpy_standard_dh(table, q: np.ndarray) -> np.ndarray:
    """T_base_flange (N, 4, 4) of standard DH rows (a, alpha, d) [m, rad] at joints q (N, dof) [rad], in numpy."""
    out = []
    for qq in q:
        T = np.eye(4)
        for (a, al, d), th in zip(table, qq):
            ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
            T = T @ np.array(
                [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]]
            )
        out.append(T)
    return np.stack(out)


def random_q(robot, n: int, seed: int) -> torch.Tensor:
    """(n, dof) seeded uniform joints within the robot's limits, clamped to +-pi [rad]."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = robot.limits[:, 0].clamp(min=-math.pi), robot.limits[:, 1].clamp(max=math.pi)
    return lo + (hi - lo) * torch.rand(n, robot.dof, generator=g, dtype=F64)


def agreement(poses: int) -> dict:
    """The largest |difference| of T_base_flange per robot: against the numpy DH (UR5, UR10), against the
    pytorch-kinematics chain, and against that chain after non-zero geometric corrections."""
    out = {"poses": poses, "vs_numpy_dh": {}, "vs_pytorch_kinematics": {}, "vs_pk_calibrated": {}}
    for name, table in UR_DH.items():
        robot = load_robot(name)
        q = random_q(robot, poses, 0)
        with torch.no_grad():
            out["vs_numpy_dh"][name] = float(np.abs(robot(q).numpy() - numpy_standard_dh(table, q.numpy())).max())
    for spec in ("ur5", "ur10", "ur5.urdf", "ur10.urdf", "panda"):
        robot = load_robot(spec)
        q = random_q(robot, poses, 1)
        for key in ("vs_pytorch_kinematics", "vs_pk_calibrated"):
            if key == "vs_pk_calibrated":
                with torch.no_grad():
                    robot.geometry.delta.normal_(0.0, 1e-3, generator=torch.Generator().manual_seed(2))
            with torch.no_grad():
                T = robot(q)
            out[key][spec] = float((robot.chain.forward_kinematics(q).get_matrix() - T).abs().max())
    return out
