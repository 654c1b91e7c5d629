#!/usr/bin/env python3
"""The command line of :mod:`torchcal.experiments.table4`: reproduce (and beat) Table 4 and Figs. 9, 11, 12 of
Horvath & Neuner (2024): the integrated ANN-EKF.

The experiment and its outputs are described there; this script parses the arguments, runs it and prints.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from torchcal.effects import CorrectionNet
from torchcal.experiments import table4
from torchcal.experiments.table4 import PAPER, campaign, metrics, plot, plot_ann
from torchcal.filter import EKFConfig, EKFTrainer


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=table4.__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--samples", type=int, default=7342)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="2 draws and 3000 samples")
    ap.add_argument("--paper-mode", action="store_true", help="also run the paper's re-iteration (slow)")
    ap.add_argument("--out", default="runs/paper")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.draws, args.samples = 2, 3000
    t_start = time.perf_counter()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    c = campaign(args.samples, args.seed)
    robot, net_true = c.model.robot, c.model.effects[0].net
    q = torch.cat([c.train.q, c.test.q])
    y = torch.cat([c.train.p, c.test.p])
    n_tr = c.train.n
    R = robot.T_tracker_base()[:3, :3]
    with torch.no_grad():
        G_true = robot.probe_position(c.q_true)
        NG_true = net_true(c.q_true) @ R.T
        t_kin = robot.probe_position(q[:1])[0]
    w_nom = net_true.flat()
    plain = EKFTrainer(robot, net_true, EKFConfig(reiterate_every=0))
    pinned = EKFTrainer(robot, net_true, EKFConfig(reiterate_every=0, sigma_t0=2e-5, q_t=1e-9, sigma_w0=0.01))
    paper = EKFTrainer(robot, net_true, EKFConfig())
    results = {}
    res_a = plain.run(q, y, n_tr, w_nom, t0=y[0])
    results["scenario_a"] = metrics(res_a, G_true, NG_true, n_tr)
    plot(res_a, G_true, NG_true, n_tr, out_dir / "fig9_scenario_a.png", "scenario a: nominal ANN weights")
    g = torch.Generator().manual_seed(args.seed + 100)
    for level in ("5", "10", "15", "random"):
        if level == "random":
            w1 = torch.stack([CorrectionNet(seed=args.seed + 1000 + d).flat() for d in range(args.draws)])
        else:
            p = int(level) / 100.0
            w1 = w_nom * (1 + p * torch.randn(args.draws, len(w_nom), generator=g, dtype=w_nom.dtype))
        w_pcm = torch.stack([pinned.pcm_weights(c.train.q, c.train.p, w1[d], seed=d) for d in range(args.draws)])
        res = pinned.run(q, y, n_tr, w_pcm, t0=t_kin)
        entry = metrics(res, G_true, NG_true, n_tr)
        entry["plain"] = metrics(plain.run(q, y, n_tr, w1, t0=y[0]), G_true, NG_true, n_tr)
        if args.paper_mode:
            entry["paper_mode"] = metrics(paper.run(q, y, n_tr, w1, t0=y[0]), G_true, NG_true, n_tr)
        if level in PAPER:
            entry["paper"] = dict(zip(("rmse_ng_test_mm", "rmse_g_test_mm", "rmse_all_test_mm"), PAPER[level]))
        results[level] = entry
        if level == "5":
            plot(res, G_true, NG_true, n_tr, out_dir / "fig11_scenario_b5.png", "scenario b, 5 %: torchcal mode")
            plot_ann(res, NG_true, n_tr, out_dir / "fig12_ann_b5.png")
        print(
            f"{level:>6}: torchcal NG {entry['rmse_ng_test_mm']:.3f} G {entry['rmse_g_test_mm']:.3f} All "
            f"{entry['rmse_all_test_mm']:.3f} mm (learned {entry['learned']:.0%}); plain All "
            f"{entry['plain']['rmse_all_test_mm']:.3f} mm",
            file=sys.stderr,
        )
    results["setup"] = {
        "samples": len(q),
        "train": n_tr,
        "draws": args.draws,
        "seed": args.seed,
        "field_variation_mm": c.truth["effects"][0]["variation_m"] * 1e3,
        "seconds": time.perf_counter() - t_start,
    }
    (out_dir / "table4.json").write_text(json.dumps(results, indent=1) + "\n")
    lines = [
        "| w_1 | mode | RMSE(NG) test | RMSE(G) test | RMSE(All) test | learned |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for level in ("5", "10", "15", "random"):
        e = results[level]
        rows = [("torchcal", e), ("plain EKF", e["plain"])]
        rows += [("paper re-iteration", e["paper_mode"])] if "paper_mode" in e else []
        for name, m in rows:
            lines.append(
                f"| {level} | {name} | {m['rmse_ng_test_mm']:.3f} | {m['rmse_g_test_mm']:.3f} | "
                f"{m['rmse_all_test_mm']:.3f} | {m['learned']:.0%} |"
            )
        if "paper" in e:
            pp = e["paper"]
            lines.append(
                f"| {level} | paper (Table 4) | {pp['rmse_ng_test_mm']:.2f} | {pp['rmse_g_test_mm']:.2f} | "
                f"{pp['rmse_all_test_mm']:.2f} | |"
            )
    (out_dir / "table4.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines), file=sys.stderr)
    print(json.dumps(results) if args.json else json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
