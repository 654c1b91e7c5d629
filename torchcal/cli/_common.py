"""What several commands' handlers do alike: the calibration module, a robot file as an input, reading a file in the
command's units, warning about rows beyond the calibrated region, one torch thread for commands that use a run, the
simulator with its failure in the command's words, a found effect in one line."""

from __future__ import annotations

import functools
import json
from pathlib import Path

from torchcal import _console
from torchcal._outdir import check_out_file
from torchcal._threads import torch_threads
from torchcal.errors import OptionError


def calibration_module():
    """The module with ``calibrate``, ``Options``, ``min_poses``, ``DEFAULT_METHOD`` (one place to change)."""
    from torchcal import pipeline as C

    return C


def _robot_input(spec: str) -> list[str]:
    """The robot description as an input file when ``spec`` is a path (built-in names are not inputs)."""
    return [spec] if Path(spec).is_file() else []


def _reading(args, robot) -> dict:
    """The keywords of :func:`~torchcal.data.read_measurements` for a file of ``robot``'s joints in the units of
    ``--length-unit`` / ``--angle-unit``."""
    return dict(
        dof=robot.dof,
        joint_limits=robot.limits,
        length_unit=args.length_unit,
        angle_unit=args.angle_unit,
        robot_name=robot.name,
        joint_types=robot.joint_types,
    )


#: how many rows outside the calibrated region predict and compensate name on stderr before counting the rest
MAX_OUTSIDE_LINES = 20


def warn_outside(path, lines, model, q, what: str) -> None:
    """Warn on stderr (not under ``--quiet``), one line per row (the first ``MAX_OUTSIDE_LINES``, then a count), for
    the rows of :func:`outside_rows`."""
    from torchcal.use.outside import outside_rows

    rows = outside_rows(model, q)
    for i, why in rows[:MAX_OUTSIDE_LINES]:
        line = lines[i] if lines is not None and i < len(lines) else i + 1
        _console.info(f"torchcal: warning: {path}: line {line}: {why}" + (f"; {what}" if what else ""))
    if len(rows) > MAX_OUTSIDE_LINES:
        _console.info(
            f"torchcal: warning: {path}: {len(rows) - MAX_OUTSIDE_LINES} more rows outside the calibrated region "
            "(the extrapolation column names them)"
        )


def _one_torch_thread(command):
    """Run a command that uses a run (``predict``, ``compensate``, ``plan``) with one torch thread.

    Their work is a long series of small kernels (a model evaluated per parameter step, row blocks of a few hundred
    rows, 3 x 3 factors per candidate): a second thread shortens none of them, and where other work shares the cores,
    each kernel waits for the slowest member of torch's thread team, spinning meanwhile (docs/benchmarks.md, *Speed of
    predict, compensate and plan*). The results are the same to rounding (a thread count may change the order of a
    sum).
    """

    @functools.wraps(command)
    def run(args) -> int:
        with torch_threads(1):
            return command(args)

    return run


def _has_load(data, meta: dict) -> bool:
    """Whether predict's rows carry load columns or the run was fitted with them."""
    load = meta.get("load") if isinstance(meta.get("load"), dict) else {}
    return (
        data.payload is not None or data.tau is not None or bool(load.get("payload_column")) or bool(load.get("tau_Nm"))
    )


def _simulate(cfg):
    """``simulate(cfg)``, with the line-of-sight failure told in terms of the command's options."""
    from torchcal.sim import simulate

    try:
        return simulate(cfg)
    except RuntimeError as e:
        if "line-of-sight" not in str(e):
            raise
        raise OptionError(
            f"robot '{cfg.robot}': {e.args[0].split(';')[0]}: the simulated tracker cannot see the "
            "probe in enough poses. Check --robot, --base-link and --tip-link (the chain must end "
            "at the tool flange of an upright arm), or ask for fewer --poses/--samples"
        ) from None


def json_out_file(path: str, inputs: list, force: bool, written_by: str) -> Path:
    """A JSON file to write: one an earlier ``written_by`` wrote (``"written_by": ...``; JSON has no comment line for
    the usual mark) is replaced like a marked file; anything else as :func:`~torchcal._outdir.check_out_file` says."""
    p = Path(path)
    if p.is_file() and not p.is_symlink():
        try:
            earlier = json.loads(p.read_text(encoding="utf-8")).get("written_by") == written_by
        except (ValueError, OSError, AttributeError):
            earlier = False
        if earlier:
            return check_out_file(path, inputs=inputs, force=True)
    return check_out_file(path, inputs=inputs, force=force)
