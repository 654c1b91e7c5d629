"""Controller readings -> model joints: the linear map of a parallelogram, reversed directions, a cable differential
or URDF mimic joints, as a calibration parameter group.

The measurement file's ``q1..qN`` are the controller's readings ``r``; the kinematic chain turns by the model's joint
angles ``q``::

    q = A r + b,    A = A_nominal + delta    (n_joints x n_readings)

A FANUC-style parallelogram has the elbow's model angle ``q3 = -(J2 + J3)``: row 3 of ``A`` is ``[0, -1, -1, 0, ...]``.
A URDF mimic joint is a model joint without a reading of its own: its row is ``multiplier`` at its source's reading
and its ``b`` the mimic ``offset``. The declared non-zero coupling entries of a description's ``readings:`` block are
transmission or differential ratios and may be calibrated (``delta``'s ``mask``); the entries a description did not
declare, an identity map and mimic rows stay fixed (a mimic multiplier is a gear the URDF states exactly, and its
error would move the same link as the source joint's own ratio row, which a readings block can declare).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from torchcal.errors import ShapeError

Tensor = torch.Tensor

#: the sizes a reading's largest entry in a readings map (a ratio, or a URDF mimic multiplier) may have, and every
#: entry at most the larger: a gear's or a track's ratio between joint values in rad or m and the model's (a track
#: read in mm: 0.001); beyond them the reading noise carried through the map swamps the fit ("observation covariance
#: not positive definite" at 1e12)
MIN_RATIO, MAX_RATIO = 1e-4, 1e4

#: the header comment line of a URDF torchcal wrote (:mod:`torchcal.robot.export`) that carries a DH robot's readings
#: map as JSON (reading names, coupling, offset, reading limits), read back by :mod:`torchcal.robot.load`
READINGS_MAP_TAG = "torchcal readings map (JSON):"


class Readings(nn.Module):
    """The map ``q = (A_nominal + delta) r + b`` from controller readings ``r (..., n_readings)`` to model joints.

    The same interface as the robot's other parameter groups (:class:`~torchcal.robot.model._Group`: a zero-initialised
    ``delta``, a boolean ``mask`` of the free elements, ``names``); kept out of ``model.py`` so that the chain's module
    does not grow with it. Parameter names are ``readings.c<i>_<k>`` (model joint ``i``, reading ``k``, 1-based),
    unit 1 (a ratio).

    Args:
        coupling: nominal ``A (n_joints, n_readings)``.
        offset: ``b (n_joints,)`` [rad].
        free: boolean ``(n_joints, n_readings)``, the ratios that may be calibrated (default none).
    """

    def __init__(self, coupling, offset=None, free=None, *, dtype=torch.float64, device="cpu"):
        super().__init__()
        if dtype != torch.float64:
            raise ShapeError(f"the calibration path is float64, got dtype {dtype}")
        A = torch.as_tensor(coupling, dtype=dtype)
        if A.ndim != 2:
            raise ShapeError(f"coupling must be a matrix (n_joints, n_readings), got shape {tuple(A.shape)}")
        n, r = A.shape
        b = torch.zeros(n, dtype=dtype) if offset is None else torch.as_tensor(offset, dtype=dtype)
        if b.shape != (n,):
            raise ShapeError(f"offset must have shape ({n},), got {tuple(b.shape)}")
        mask = torch.zeros(n, r, dtype=torch.bool) if free is None else torch.as_tensor(free, dtype=torch.bool)
        # the description's (every reload reads it again): only the correction is in the state, so that run
        # directories written before readings existed load unchanged
        self.register_buffer("nominal", A.to(device).clone(), persistent=False)
        self.register_buffer("offset", b.to(device).clone(), persistent=False)
        self.register_buffer("mask", mask.reshape(n, r).to(device).clone(), persistent=False)
        self.delta = nn.Parameter(torch.zeros(n, r, dtype=dtype, device=device))
        self.names = [f"readings.c{i + 1}_{k + 1}" for i in range(n) for k in range(r)]
        self._identity = self._check_identity()
        # whether any ratio may be calibrated, as a Python bool: the description fixes it, and a robot moved to the
        # meta device (shape checks) must still list its parameter groups
        self.has_free = bool(self.mask.any())
        self.register_load_state_dict_post_hook(lambda module, _keys: module._refresh())

    @classmethod
    def identity(cls, n: int, *, dtype=torch.float64, device="cpu") -> Readings:
        """Every reading is its model joint: the map every description without readings gets."""
        return cls(torch.eye(n, dtype=dtype, device=device), dtype=dtype, device=device)

    def _check_identity(self) -> bool:
        A = self.nominal
        return (
            A.shape[0] == A.shape[1]
            and bool(torch.equal(A, torch.eye(A.shape[0], dtype=A.dtype, device=A.device)))
            and not bool(self.offset.any())
            and not bool(self.mask.any())
            and not bool(self.delta.detach().any())
        )

    def _refresh(self) -> None:
        self._identity = self._check_identity()

    @property
    def is_identity(self) -> bool:
        """True when the readings are the model joints exactly: the robot then skips the map (bit-identical FK)."""
        return self._identity

    @property
    def n_joints(self) -> int:
        return self.nominal.shape[0]

    @property
    def n_readings(self) -> int:
        return self.nominal.shape[1]

    def reset(self) -> None:
        with torch.no_grad():
            self.delta.zero_()

    def matrix(self, delta: Tensor | None = None) -> Tensor:
        """``A (n_joints, n_readings)``; ``delta`` replaces the module's correction."""
        return self.nominal + (self.delta if delta is None else delta)

    def joints(self, r: Tensor, delta: Tensor | None = None) -> Tensor:
        """Model joints ``q (..., n_joints)`` [rad] of readings ``r (..., n_readings)``."""
        return r @ self.matrix(delta).transpose(-1, -2) + self.offset

    def readings_of(self, q: Tensor) -> Tensor:
        """Readings ``r (..., n_readings)`` that give model joints ``q (..., n_joints)``: least squares when ``A`` is
        tall (mimic joints: exact when ``q`` honours them), exact for a square ``A`` of full rank."""
        A = self.matrix().detach()
        rhs = (q - self.offset).reshape(-1, self.n_joints).T
        r = torch.linalg.lstsq(A, rhs).solution.T
        return r.reshape(*q.shape[:-1], self.n_readings)

    def reading_limits(self, joint_limits: Tensor) -> Tensor:
        """Per-reading limits ``(n_readings, 2)`` implied by the model joints' ``joint_limits (n_joints, 2)``.

        Reading ``k`` takes the limits of the first model joint that follows it alone (``q_i = s r_k + b_i``, the
        interval mapped back through ``s``); a reading that every joint shares with another (a parallelogram's J3)
        gets ``[-2 pi, 2 pi]``, the default of a DH table without limits.
        """
        A, b = self.nominal, self.offset
        out = torch.tensor([[-2 * torch.pi, 2 * torch.pi]] * self.n_readings, dtype=A.dtype, device=A.device)
        for k in range(self.n_readings):
            for i in range(self.n_joints):
                row = A[i]
                if row[k] != 0 and int((row != 0).sum()) == 1:
                    lo, hi = (joint_limits[i] - b[i]) / row[k]
                    out[k] = torch.stack([torch.minimum(lo, hi), torch.maximum(lo, hi)])
                    break
        return out


def check_coupling(A: Sequence[Sequence[float]], n_joints: int, where: str) -> str | None:
    """Why ``A`` cannot map readings to ``n_joints`` model joints, or None: the shape, finite entries and full column
    rank (every reading must move the arm, or the data cannot tell it from the others)."""
    t = torch.as_tensor(A, dtype=torch.float64)
    if t.ndim != 2 or t.shape[0] != n_joints:
        return f"{where} must have {n_joints} rows (one per model joint), got shape {tuple(t.shape)}"
    if t.shape[1] == 0 or t.shape[1] > n_joints:
        return f"{where} must have 1 to {n_joints} columns (one per reading), got {t.shape[1]}"
    if not bool(torch.isfinite(t).all()):
        return f"{where} has non-finite entries"
    # each reading's scale is its largest entry: a cross-term far below it is a coupling (an exported run's folded
    # dq_j = c q_k, |c| anywhere up to 1 %, the smaller the more so), not a reading in encoder counts
    big = t.abs().max(dim=0).values
    big = big[big > 0]
    if len(big) and not (float(big.min()) >= MIN_RATIO and float(t.abs().max()) <= MAX_RATIO):
        worst = float(t.abs().max()) if float(t.abs().max()) > MAX_RATIO else float(big.min())
        return (
            f"{where} has a ratio of size {worst:.3g}, outside {MIN_RATIO:g} to {MAX_RATIO:g}: a reading that moves "
            "its joint that much (or that little) per unit makes the joint's reading noise swamp the fit (readings "
            "are the controller's joint values in rad or m, not encoder counts)"
        )
    rank = int(torch.linalg.matrix_rank(t))
    if rank < t.shape[1]:
        return (
            f"{where} has rank {rank} for {t.shape[1]} readings: some reading moves no joint, or two move the same "
            "joints in the same proportion"
        )
    return None
