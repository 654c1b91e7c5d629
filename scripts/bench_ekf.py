"""Speed of one integrated ANN-EKF pass: the fast path against a per-step autograd baseline; prints JSON.

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

They must give the same estimates (the JSON reports the largest differences). No ANN re-iteration here: it is
the same for all and would hide the filter's own cost. ``--load`` also measures the fast path with the default
thread count while a competing busy process (a spinning Python loop) holds a core: ``loaded_pass_s`` and its
ratio to ``pass_s``.

    python scripts/bench_ekf.py [--samples 7342] [--device cpu|cuda] [--threads N] [--load] [--json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import torch
from torch import nn

from torchcal.filter import EKFConfig, EKFTrainer
from torchcal.sim import EffectSpec, SimConfig, simulate


class _Normalise(nn.Module):
    def __init__(self, offset, scale):
        super().__init__()
        self.register_buffer("offset", offset.clone())
        self.register_buffer("scale", scale.clone())

    def forward(self, q):
        return (q - self.offset) / self.scale


class _Scale(nn.Module):
    def __init__(self, s):
        super().__init__()
        self.register_buffer("s", s.clone())

    def forward(self, x):
        return x * self.s


def user_module(net) -> nn.Module:
    """The :class:`CorrectionNet` ``net`` rebuilt as a plain ``nn.Sequential`` (same weights, same order)."""
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


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=7342)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0, help="torch threads of the caller (0: leave the default)")
    ap.add_argument("--load", action="store_true", help="also time the fast path beside a busy competing process")
    ap.add_argument("--no-baseline", action="store_true", help="skip the (slow) baseline pass")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    default_threads = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    c = simulate(
        SimConfig(
            robot="ur5",
            trajectory=True,
            samples=args.samples,
            train_samples=args.samples - 1,
            seed=0,
            sigma_length=0.0,
            sigma_angle_deg=0.0,
            effects=[EffectSpec("field", size=2.5e-4)],
        )
    )
    robot = c.model.robot.to(args.device)
    net = c.model.effects[0].net.to(args.device)
    q = torch.cat([c.train.q, c.test.q]).to(args.device)
    y = torch.cat([c.train.p, c.test.p]).to(args.device)
    n = len(q)
    w0 = net.flat() * 1.05
    cfg = EKFConfig(reiterate_every=0)
    fast = EKFTrainer(robot, net, cfg).run(q, y, n, w0)
    user = EKFTrainer(robot, user_module(net), cfg).run(q, y, n, w0)
    out = {
        "pass_s": fast.seconds,
        "module_pass_s": user.seconds,
        "module_ratio": user.seconds / fast.seconds,
        "module_max_abs_diff_m": float((fast.prediction - user.prediction).abs().max()),
    }
    if not args.no_baseline:
        slow = EKFTrainer(robot, net, EKFConfig(reiterate_every=0, jacobian="autograd")).run(q, y, n, w0)
        out.update(
            {
                "baseline_pass_s": slow.seconds,
                "speedup": slow.seconds / fast.seconds,
                "max_abs_diff_m": float((fast.prediction - slow.prediction).abs().max()),
            }
        )
    out.update(
        {
            "samples": n,
            "state_dim": net.n_weights + 3,
            "device": args.device,
            "threads": torch.get_num_threads(),
            "status": fast.status[0],
        }
    )
    if args.load:
        spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        try:
            time.sleep(0.5)  # let it take its core
            torch.set_num_threads(default_threads)
            loaded = EKFTrainer(robot, net, cfg).run(q, y, n, w0)
        finally:
            spin.kill()
            spin.wait()
        out.update(
            {
                "loaded_pass_s": loaded.seconds,
                "loaded_ratio": loaded.seconds / fast.seconds,
                "loaded_threads": default_threads,
            }
        )
    print(", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in out.items()), file=sys.stderr)
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
