"""Speed of one integrated ANN-EKF pass: the fast path against a per-step autograd baseline; prints JSON.

The paper's setting (Horvath & Neuner 2024, Sec. 3): a continuous UR5 trajectory of 7342 samples, the
correction network 6-29-3 (293 weights) plus the probe position: a 296-dimensional state, every sample an
update. Both paths run in the same process on the same data:

* baseline: ``torch.func.jacrev`` of the network per step, dense ``H`` and the textbook Joseph form
  ``(I - K H) P (I - K H)^T + K R K^T`` (O(n^3) per step);
* fast path: the network's analytic Jacobian and the Joseph form as one rank-6 update (O(n^2) per step).

They must give the same estimates (the JSON reports the largest difference). No ANN re-iteration here:
it is the same for both and would hide the filter's own cost.

    python scripts/bench_ekf.py [--samples 7342] [--device cpu|cuda] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys

import torch

from torchcal.filter import EKFConfig, EKFTrainer
from torchcal.sim import EffectSpec, SimConfig, simulate


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=7342)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave the default)")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    c = simulate(SimConfig(robot="ur5", trajectory=True, samples=args.samples,
                           train_samples=args.samples - 1, seed=0, sigma_length=0.0, sigma_angle_deg=0.0,
                           effects=[EffectSpec("field", size=2.5e-4)]))
    robot = c.model.robot.to(args.device)
    net = c.model.effects[0].net.to(args.device)
    q = torch.cat([c.train.q, c.test.q]).to(args.device)
    y = torch.cat([c.train.p, c.test.p]).to(args.device)
    n = len(q)
    w0 = net.flat() * 1.05
    fast = EKFTrainer(robot, net, EKFConfig(reiterate_every=0)).run(q, y, n, w0)
    slow = EKFTrainer(robot, net, EKFConfig(reiterate_every=0, jacobian="autograd")).run(q, y, n, w0)
    diff = float((fast.prediction - slow.prediction).abs().max())
    out = {"pass_s": fast.seconds, "baseline_pass_s": slow.seconds, "speedup": slow.seconds / fast.seconds,
           "samples": n, "state_dim": net.n_weights + 3, "max_abs_diff_m": diff, "device": args.device,
           "threads": torch.get_num_threads(), "status": fast.status[0]}
    print(f"fast {fast.seconds:.2f} s, baseline {slow.seconds:.2f} s, speedup {out['speedup']:.1f}, "
          f"largest difference {diff:.1e} m", file=sys.stderr)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
