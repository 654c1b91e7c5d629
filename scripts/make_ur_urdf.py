#!/usr/bin/env python3
"""Generate ``robots/ur5.urdf`` and ``robots/ur10.urdf`` from the standard DH tables in ``robots/urX.yaml``
(torchcal.robot.ur_urdf says how).

    python scripts/make_ur_urdf.py           # write robots/ur5.urdf and robots/ur10.urdf
    python scripts/make_ur_urdf.py --check   # regenerate in memory, exit 1 if the files differ or
                                             # the URDF chain does not reproduce the DH table
"""

import argparse
import sys
from pathlib import Path

from torchcal.robot.ur_urdf import MODELS, TOLERANCE, check_numerics, load_table, render

ROOT = Path(__file__).resolve().parents[1]
ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
ap.add_argument("--check", action="store_true", help="exit 1 if a file differs or the URDF FK != the DH FK (1e-12)")


def main(argv=None) -> int:
    check, status = ap.parse_args(argv).check, 0
    for name in MODELS:
        source, path = f"robots/{name}.yaml", ROOT / "robots" / f"{name}.urdf"
        model = load_table(ROOT / source)
        text = render(model, source)
        if not check:
            path.write_text(text, encoding="utf-8")
            print(f"wrote robots/{name}.urdf")
        elif not path.is_file() or path.read_text(encoding="utf-8") != text:
            print(f"robots/{name}.urdf: out of date, run scripts/make_ur_urdf.py")
            status = 1
        else:
            worst = check_numerics(model, text, path)
            print(
                f"robots/{name}.urdf: up to date; max |T - Rz(pi) T_DH|:",
                ", ".join(f"{k} {v:.2e}" for k, v in worst.items()),
            )
            for key in (k for k, err in worst.items() if not err < TOLERANCE.get(k, 1e-12)):
                print(f"robots/{name}.urdf: {key} discrepancy {worst[key]:.3e} > {TOLERANCE.get(key, 1e-12):.0e}")
                status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
