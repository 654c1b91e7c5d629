"""Speed of one integrated ANN-EKF pass: the fast path against a per-step autograd baseline
(``scripts/bench_ekf.py``).

The paper's setting (Horvath & Neuner 2024, Sec. 3): a continuous UR5 trajectory of 7342 samples, the
correction network 6-29-3 (293 weights) plus the probe position: a 296-dimensional state, every sample an
update. All paths run in the same process, on the same data, with the same thread count (the filter pins its
own inner loop to one thread and restores the caller's):

* baseline: ``torch.func.jacrev`` of the network per step, dense ``H`` and the textbook Joseph form
  ``(I - K H) P (I - K H)^T + K R K^T`` (O(n^3) per step);
* fast path (``pass_s``): the network's hand-derived Jacobian and the Joseph form as one rank-6 update
  (O(n^2) per step);
* user module (``module_pass_s``): the same network as a plain ``nn.Sequential`` through the path for any
  ``nn.Module`` (reverse-mode autodiff per step), the ratio to the fast path as ``module_ratio``.

They must give the same estimates (the result reports the largest differences). No ANN re-iteration here: it is
the same for all and would hide the filter's own cost. With ``load`` the fast path is also timed with the
process's default thread count while a competing busy process holds a core: ``loaded_pass_s`` and its ratio to
``pass_s``.
"""

from __future__ import annotations

import time

import torch
from torch import nn

from experiments.bench_calibration import busy_process
from torchcal.filter import EKFConfig, EKFTrainer
from torchcal.sim import EffectSpec, SimConfig, simulate

#: the simulated UR5 (SimConfig's robot and seed) keeps its nominal geometry: the filter's cost does not depend on
#: geometric biases, and without them the passes are compared on the field alone
TRUE_GEOMETRY = {"sigma_length": 0.0, "sigma_angle_deg": 0.0}


class _Normalise(nn.Module):
    """``(q - offset) / scale``: the network's input normalisation as a module."""

    def __init__(self, offset: torch.Tensor, scale: torch.Tensor):
        super().__init__()
        self.register_buffer("offset", offset.clone())
        self.register_buffer("scale", scale.clone())

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return (q - self.offset) / self.scale


class _Scale(nn.Module):
    """``x * s``: the network's output scale as a module."""

    def __init__(self, s: torch.Tensor):
        super().__init__()
        self.register_buffer("s", s.clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.s


def user_module(net) -> nn.Module:
    """The :class:`~torchcal.effects.CorrectionNet` ``net`` rebuilt as a plain ``nn.Sequential`` (same weights,
    same order), so that the filter takes its path for any ``nn.Module``."""
    seq = nn.Sequential(
        _Normalise(net.q_offset, net.q_scale),
        nn.Linear(net.dof, net.hidden, dtype=torch.float64),
        nn.Tanh(),
        nn.Linear(net.hidden, 3, dtype=torch.float64),
        _Scale(net.out_scale),
    )
    seq.load_state_dict(
        {
            "0.offset": net.q_offset,
            "0.scale": net.q_scale,
            "1.weight": net.fc1.weight,
            "1.bias": net.fc1.bias,
            "3.weight": net.fc2.weight,
            "3.bias": net.fc2.bias,
            "4.s": net.out_scale,
        }
    )
    return seq.to(net.q_offset.device)


def run(
    samples: int = 7342,
    device: str = "cpu",
    baseline: bool = True,
    load: bool = False,
    load_threads: int = 1,
    repeat: int = 3,
) -> dict:
    """Time the passes (module docstring) on a simulated trajectory of ``samples`` samples.

    Args:
        samples: trajectory length; all but the last are filtered.
        device: torch device of the robot, network and data.
        baseline: also run the (slow) per-step autograd baseline.
        load: also time the fast path beside a busy competing process, with ``load_threads`` torch threads
            (the process's default count: what a user who sets nothing gets).
        repeat: the fast and the module pass run this many times, alternating; each reports its shortest
            (the least disturbed by other processes on a shared machine), with its CPU time beside it.

    Returns:
        Seconds per pass, their ratios, the largest differences of the predictions [m], the problem's size,
        the thread count and the filter's status (keys as in the module docstring).
    """
    field = [EffectSpec("field", size=2.5e-4)]
    c = simulate(SimConfig(trajectory=True, samples=samples, train_samples=samples - 1, effects=field, **TRUE_GEOMETRY))
    robot = c.model.robot.to(device)
    net = c.model.effects[0].net.to(device)
    q = torch.cat([c.train.q, c.test.q]).to(device)
    y = torch.cat([c.train.p, c.test.p]).to(device)
    n = len(q)
    w0 = net.flat() * 1.05
    cfg = EKFConfig(reiterate_every=0)
    module = user_module(net)
    fast_t, user_t = [], []
    for _ in range(max(1, repeat)):
        fast, fast_cpu = _timed(EKFTrainer(robot, net, cfg), q, y, w0)
        user, user_cpu = _timed(EKFTrainer(robot, module, cfg), q, y, w0)
        fast_t.append((fast.seconds, fast_cpu))
        user_t.append((user.seconds, user_cpu))
    (fast_s, fast_cpu), (user_s, user_cpu) = min(fast_t), min(user_t)
    out = {
        "pass_s": fast_s,
        "module_pass_s": user_s,
        "module_ratio": user_s / fast_s,
        "module_max_abs_diff_m": float((fast.prediction - user.prediction).abs().max()),
        "pass_cpu_s": fast_cpu,
        "module_pass_cpu_s": user_cpu,
        "repeat": max(1, repeat),
    }
    if baseline:
        slow = EKFTrainer(robot, net, EKFConfig(reiterate_every=0, jacobian="autograd")).run(q, y, n, w0)
        out.update(
            {
                "baseline_pass_s": slow.seconds,
                "speedup": slow.seconds / fast_s,
                "max_abs_diff_m": float((fast.prediction - slow.prediction).abs().max()),
            }
        )
    out.update(
        {
            "samples": n,
            "state_dim": net.n_weights + 3,
            "device": device,
            "threads": torch.get_num_threads(),
            "status": fast.status[0],
        }
    )
    if load:
        out.update(_loaded(robot, net, cfg, q, y, w0, load_threads, fast_s, max(1, repeat)))
    return out


def _timed(trainer: EKFTrainer, q, y, w0):
    """One pass over all but the last sample; the result (``seconds`` its wall time) and its CPU time [s]."""
    c0 = time.process_time()
    res = trainer.run(q, y, len(q), w0)
    return res, time.process_time() - c0


def _loaded(robot, net, cfg: EKFConfig, q, y, w0, threads: int, quiet_s: float, repeat: int) -> dict:
    """The fast pass again (the shortest of ``repeat``) with ``threads`` torch threads while a busy process holds
    a core."""
    spin = busy_process()
    before = torch.get_num_threads()
    try:
        time.sleep(0.5)  # let it take its core
        torch.set_num_threads(threads)
        loaded_s = min(EKFTrainer(robot, net, cfg).run(q, y, len(q), w0).seconds for _ in range(repeat))
    finally:
        torch.set_num_threads(before)
        spin.kill()
        spin.wait()
    return {"loaded_pass_s": loaded_s, "loaded_ratio": loaded_s / quiet_s, "loaded_threads": threads}
