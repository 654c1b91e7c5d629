#!/usr/bin/env python3
"""Generate ``robots/ur5.urdf`` and ``robots/ur10.urdf`` from the standard DH tables in ``robots/urX.yaml``
(torchcal.robot.ur_urdf says how).

    python scripts/make_ur_urdf.py           # write robots/ur5.urdf and robots/ur10.urdf
    python scripts/make_ur_urdf.py --check   # regenerate in memory, exit 1 if the files differ or
                                             # the URDF chain does not reproduce the DH table
"""

import sys
from pathlib import Path

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from torchcal.robot.ur_urdf import MODELS, TOLERANCE, check_numerics, load_table, render

ROOT = Path(__file__).resolve().parents[1]
ap = common.parser(__doc__)
ap.add_argument("--check", action="store_true", help="exit 1 if a file differs or the URDF FK != the DH FK (1e-12)")


def regenerate(args) -> dict:
    """Per robot: written, out of date, or the largest FK differences of the check and whether they pass."""
    result = {}
    for name in MODELS:
        source, path = f"robots/{name}.yaml", ROOT / "robots" / f"{name}.urdf"
        model = load_table(ROOT / source)
        text = render(model, source)
        if not args.check:
            path.write_text(text, encoding="utf-8")
            result[name] = {"written": True}
        elif not path.is_file() or path.read_text(encoding="utf-8") != text:
            result[name] = {"up_to_date": False, "ok": False}
        else:
            worst = check_numerics(model, text, path)
            ok = all(err < TOLERANCE.get(k, 1e-12) for k, err in worst.items())
            result[name] = {"up_to_date": True, "max_abs_difference": worst, "ok": ok}
    return result


if __name__ == "__main__":
    args, result = common.run(ap, regenerate)
    for name, r in result.items():
        if r.get("written"):
            print(f"wrote robots/{name}.urdf")
        elif not r["up_to_date"]:
            print(f"robots/{name}.urdf: out of date, run scripts/make_ur_urdf.py")
        else:
            worst = ", ".join(f"{k} {v:.2e}" for k, v in r["max_abs_difference"].items())
            print(f"robots/{name}.urdf: up to date; max |T - Rz(pi) T_DH|: {worst}; {'ok' if r['ok'] else 'FAILED'}")
    common.emit(result, args)
    sys.exit(0 if all(r.get("ok", True) for r in result.values()) else 1)
