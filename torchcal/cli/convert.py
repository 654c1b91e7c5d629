"""The ``convert`` command: measurements in other layouts in."""

from __future__ import annotations

from torchcal import _console
from torchcal._outdir import check_out_file
from torchcal.cli._args import _add_common, _add_force
from torchcal.errors import OptionError


def add_parser(sub) -> None:
    cv = sub.add_parser(
        "convert",
        help="import measurements in another layout (--map) or a third-party data set (--from)",
        description="Write a torchcal measurement file (CSV) from measurements in other layouts. --map MAP.yaml: "
        "joints and points in one file or several (text with any delimiter, header or not; YAML; MATLAB .mat), "
        "their units, joint order, signs and offsets, 4x4 or quaternion poses, several reflectors (probe) or "
        "placements (station), extra columns kept, as the MAP describes (docs/reference.md, 'Importing "
        "measurements'). --from ipa-robot-accuracy: the public UR10 data set.",
    )
    cv.add_argument("inputs", nargs="+", metavar="INPUT", help="the file(s) to convert; the MAP numbers them from 1")
    cv.add_argument("--map", default=None, metavar="MAP.yaml", help="the YAML file that describes the inputs' layout")
    cv.add_argument(
        "--from",
        dest="fmt",
        default=None,
        choices=["ipa-robot-accuracy"],
        help="ipa-robot-accuracy: Series_*/measurements_*.csv of the UR10 + Leica data set "
        "(Landgraf et al., IEEE CASE 2021, MIT licence)",
    )
    cv.add_argument("--out", required=True, help="measurement file to write")
    _add_force(cv)
    _add_common(cv)


def handle(args) -> int:
    from torchcal.data import convert_ipa
    from torchcal.data.mapped import convert_mapped

    if (args.map is None) == (args.fmt is None):
        raise OptionError("convert takes one of --map MAP.yaml (a layout you describe) and --from FORMAT")
    if args.fmt is not None and len(args.inputs) != 1:
        raise OptionError(f"--from {args.fmt} converts one file, got {len(args.inputs)}")
    out_file = check_out_file(args.out, inputs=[*args.inputs, args.map], force=args.force)
    if args.map is not None:
        m = convert_mapped(args.map, args.inputs, out_file, written_by="torchcal convert")
        kinds = [k for k in ("station", "probe") if getattr(m, k) is not None]
        what = "".join(f", {len(getattr(m, f'{k}_names'))} {k}s" for k in kinds)
        cols = [
            f"q1..q{m.dof}",
            *(["x, y, z"] if m.p is not None else []),
            *(["rx, ry, rz"] if m.r is not None else []),
        ]
        cols += [*(["t"] if m.t is not None else []), *(["temperature"] if m.temperature is not None else [])]
        cols += [*m.extra, *kinds]
        _console.info(f"wrote {m.n} rows of {m.dof} joints{what} to {args.out}: columns {', '.join(cols)}")
        if m.r is not None:
            from torchcal.data.mapped import orientation_note

            _console.info(f"convert: note: {orientation_note(args.map)}")
        return 0
    m = convert_ipa(args.inputs[0], out_file, written_by="torchcal convert")
    _console.info(f"wrote {m.n} poses to {args.out} (series {m.meta.get('series', '?')})")
    return 0
