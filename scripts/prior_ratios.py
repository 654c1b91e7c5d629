#!/usr/bin/env python3
"""The largest geometric correction of a kinematic calibration in prior standard deviations, per unit (lengths,
angles), on legitimate data and on data of another robot: the measurement behind
``torchcal.pipeline.checks.MAX_PRIOR_RATIO`` (docs/prior_ratios.md).

    python scripts/prior_ratios.py sim                  # simulated UR5, UR10, Panda campaigns
    python scripts/prior_ratios.py outside DIR          # every DIR/*/train.csv (UR5 campaigns)
    python scripts/prior_ratios.py real DIR             # the ipa-robot-accuracy UR10 series A-D
    python scripts/prior_ratios.py wrong DIR/none-s808  # UR5 data calibrated as a UR10 and the reverse

One line per data set: its name and, per unit, the largest ratio and the parameter that has it.
"""

import argparse
import dataclasses
from pathlib import Path

from torchcal.data import read_measurements
from torchcal.estimate.fit import prior_ratios
from torchcal.pipeline import Options, calibrate
from torchcal.pipeline import checks as P
from torchcal.pipeline.options import PLAUSIBLE_ANGLE, PLAUSIBLE_LENGTH
from torchcal.sim import EffectSpec, SimConfig, simulate


def largest(robot: str, m, **options) -> dict:
    """Per unit ('m', 'rad'): (largest ratio, its parameter) after the geometric fit of ``robot`` to ``m``."""
    limits, P.MAX_PRIOR_RATIO = P.MAX_PRIOR_RATIO, {"m": float("inf"), "rad": float("inf")}  # measure, do not stop
    try:
        run = calibrate(robot, m, Options.of(method="kinematic", **options))
    finally:
        P.MAX_PRIOR_RATIO = limits
    fit = next(f for f in run.fits if f.stage == "geometric")
    scale = dataclasses.replace(run.options.fit, prior_length=PLAUSIBLE_LENGTH, prior_angle=PLAUSIBLE_ANGLE)
    ratios = prior_ratios(fit, run.model, scale)  # in the stop's units, not the fit's tolerance prior
    units = {i.name: i.unit for i in run.model.robot.parameter_info() if i.group == "geometry"}
    out = {}
    for u in ("m", "rad"):
        r, n = max(((r, n) for n, r in ratios.items() if units[n] == u), default=(0.0, None))
        out["lengths" if u == "m" else "angles"] = f"{r:.2f} ({n})"
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("sim", "outside", "real", "wrong"))
    ap.add_argument("data", nargs="?", type=Path, help="the data folder (outside, real, wrong)")
    a = ap.parse_args()
    if a.what == "sim":
        for robot in ("ur5", "ur10", "panda"):
            for seed in range(3):
                for effects in ([], ["compliance:2=50um"], ["field=0.6mm"]):
                    for bias_mm, bias_deg in ((0.1, 0.01), (1.0, 0.1)):
                        cfg = SimConfig(
                            robot=robot,
                            poses=200,
                            test_poses=10,
                            seed=seed,
                            effects=[EffectSpec.parse(e) for e in effects],
                            sigma_length=bias_mm * 1e-3,
                            sigma_angle_deg=bias_deg,
                        )
                        name = f"{robot} seed {seed} {'+'.join(effects) or 'geometry'} bias {bias_mm} mm {bias_deg} deg"
                        print(name, largest(robot, simulate(cfg).train), flush=True)
    elif a.what == "outside":
        for f in sorted(a.data.glob("*/train.csv")):
            print(f.parent.name, largest("ur5", read_measurements(f, dof=6)), flush=True)
    elif a.what == "real":
        from experiments.ur10_real import load_series

        data, _ = load_series(a.data, ("A", "B", "C", "D"), 0)
        for s, m in data.items():
            print(f"Series {s} ({m.n} rows)", largest("ur10", m, trajectory=False), flush=True)
    else:
        print("UR5 data as ur10", largest("ur10", read_measurements(a.data / "train.csv", dof=6)))
        print(
            "UR10 data as ur5",
            largest("ur5", simulate(SimConfig(robot="ur10", poses=200, test_poses=10, seed=1)).train),
        )


if __name__ == "__main__":
    main()
