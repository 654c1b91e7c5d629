"""The integrated method on outside-style trajectories (a multi-sine path and a formula field that the project's
simulator does not share), judged on the continuation of each path (JSON).

python scripts/trajectory_outside.py --seeds 0 1 --fields tanh fourier
python scripts/trajectory_outside.py --seeds 3 --fields product --size 0.15mm --out /tmp/campaigns
"""

import _checkout  # noqa: F401  (puts the checkout's experiments/ on the path)

from experiments import common
from experiments.trajectory_outside import markdown, summary, table
from torchcal.errors import OptionError
from torchcal.sim import EffectSpec
from torchcal.sim.outside import FIELD_KINDS

ap = common.parser(__doc__)
ap.add_argument("--seeds", nargs="+", type=int, default=[0])
ap.add_argument("--fields", nargs="+", default=["tanh"], choices=(*FIELD_KINDS, "none"))
ap.add_argument("--size", default="0.1mm", help="RMS of the field at the probe, with a unit (m, mm, um)")
ap.add_argument("--width", type=int, default=29, help="tanh hidden units, Fourier features, product pairs")
ap.add_argument("--samples", type=int, default=7342, help="samples of the whole path; the first 80 %% train")
ap.add_argument(
    "--periods",
    nargs=2,
    type=float,
    default=None,
    help="shortest and longest sine period [samples] (default n/8, 1.5 n)",
)
ap.add_argument("--auto", action="store_true", help="also the default method (auto) on each continuation")
ap.add_argument("--out", default=None, help="write each campaign's train.csv, test.csv, truth.json under this folder")


def _size(text: str) -> float:
    try:
        return EffectSpec.parse(f"field={text}").size
    except OptionError:
        ap.error(f"--size '{text}' is not a positive number with a unit (m, mm, um), e.g. 0.1mm")


def experiment(a):
    rows = table(
        a.seeds,
        a.fields,
        size=_size(a.size),
        width=a.width,
        samples=a.samples,
        periods=a.periods,
        out=a.out,
        default_method=a.auto,
    )
    return {"rows": rows, "summary": summary(rows)}, markdown(rows)


if __name__ == "__main__":
    common.run_markdown(ap, experiment)
