"""Reloading a calibration's run directory (its files are an outside contract; :mod:`torchcal.report.rundir`
writes them): the model, its covariance and trust, a run as a prior, each row's station and probe, and predicting.
The layout of the directory is :mod:`torchcal.report.rundir`'s.
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
import pickle
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torchcal._inputs import load_json, read_bounded
from torchcal._method import CANDIDATES
from torchcal._threads import torch_threads
from torchcal.data import Measurements
from torchcal.effects import Context, MeasurementModel, effect_from_config
from torchcal.errors import MeasurementFileError, OptionError, TorchcalError
from torchcal.estimate.covariance import ParameterCovariance
from torchcal.estimate.trust import MIN_ROWS, FewRows, Trust
from torchcal.robot import load_robot

if TYPE_CHECKING:  # the pipeline is imported by load_prior alone: predict, compensate and plan do not load it
    from torchcal.pipeline import Prior

F64 = torch.float64
Tensor = torch.Tensor


def _set_region(model: MeasurementModel, cfg, run_dir: Path) -> None:
    """Set a loaded model's region from model.json's ``region`` (absent in runs written before it: no region)."""
    if cfg is None:
        return
    dof = model.robot.dof
    try:
        lo = [float(v) for v in cfg["joint_min"]]
        hi = [float(v) for v in cfg["joint_max"]]
        fade = cfg.get("fade", False)
    except (KeyError, TypeError, ValueError, AttributeError):
        raise _run_error(run_dir, "model.json: region must hold joint_min and joint_max lists of numbers") from None
    ok = len(lo) == len(hi) == dof and all(math.isfinite(a) and math.isfinite(b) and a <= b for a, b in zip(lo, hi))
    if not ok or not isinstance(fade, bool):
        raise _run_error(
            run_dir, f"model.json: region must give {dof} finite joint ranges (joint_min <= joint_max) and a fade flag"
        )
    model.set_region(torch.tensor([lo, hi], dtype=torch.float64, device=model.robot.device), fade=fade)


#: a cone of tool axes wider than this half-angle [rad] says nothing: the training rows turned the tool every way
MAX_CONE = 0.9 * math.pi


def tool_axis_cone(robot, q: Tensor) -> dict | None:
    """The cone ``{"axis": (3,), "max_angle": rad}`` of the tool axes (the flange's z in the base frame) of poses
    ``q (N, dof)``: their normalised mean direction and the largest angle of one from it; None where the mean is
    near zero or the cone wider than :data:`MAX_CONE`."""
    with torch.no_grad():
        z = robot(q)[:, :3, 2].to("cpu", torch.float64)
    m = z.mean(0)
    if float(m.norm()) < 1e-6:
        return None
    m = m / m.norm()
    cap = float(torch.arccos((z @ m).clamp(-1.0, 1.0)).max())
    return None if cap > MAX_CONE else {"axis": m.tolist(), "max_angle": cap}


def _tool_cone(cfg, run_dir: Path) -> tuple[Tensor, float] | None:
    """model.json's ``tool_axis`` as ``(axis (3,), max_angle)``, checked (absent in runs written before it: None)."""
    if cfg is None:
        return None
    try:
        axis = torch.tensor([float(v) for v in cfg["axis"]], dtype=torch.float64, device="cpu")  # beside CPU axes
        cap = float(cfg["max_angle"])
    except (KeyError, TypeError, ValueError):
        raise _run_error(run_dir, "model.json: tool_axis must hold an axis (3 numbers) and a max_angle") from None
    if axis.shape != (3,) or not bool(torch.isfinite(axis).all()) or abs(float(axis.norm()) - 1) > 1e-6:
        raise _run_error(run_dir, "model.json: tool_axis.axis must be a unit vector")
    if not (math.isfinite(cap) and 0 <= cap <= math.pi):
        raise _run_error(run_dir, "model.json: tool_axis.max_angle must be an angle in 0..pi")
    return axis, cap


def tool_axis_beyond(model: MeasurementModel, q: Tensor) -> Tensor:
    """How far ``(N,)`` [rad] the tool axis of each pose ``q (N, dof)`` lies beyond the cone the run's training rows
    covered (``model.tool_cone``, set by :func:`load_model`); 0 inside it and where the run recorded none."""
    cone = getattr(model, "tool_cone", None)
    if cone is None:
        return torch.zeros(len(q), dtype=torch.float64, device="cpu")  # as the CPU angles below
    axis, cap = cone
    with torch.no_grad():
        z = model.robot(q)[:, :3, 2].to("cpu", torch.float64)
    return (torch.arccos((z @ axis).clamp(-1.0, 1.0)) - cap).clamp(min=0)


def _run_error(run_dir: Path, what: str) -> OptionError:
    return OptionError(f"{run_dir}: {what}; expected a run directory written by 'torchcal calibrate'")


#: Integer sizes an effect's config in model.json may carry, and the largest accepted: each becomes the size of
#: tensors allocated when the effect is rebuilt, before model.pt is loaded into them. Any other integer in a
#: config is bounded by :data:`MAX_CONFIG_INT`; ``joint`` must name a joint of the run's robot (1-based).
#: (``n_support``: a kernel correction's points, and a region gate's in runs written before ``n_region``)
SIZE_LIMITS = {
    "hidden": 100_000,
    "n_support": 200_000,
    "n_region": 200_000,
    "n_inducing": 100_000,
    "n_weights": 10_000_000,
    "dof": 256,
}
MAX_CONFIG_INT = 100_000
#: Most effects (and effects nested in one another) a run may hold.
MAX_EFFECTS = 1000


def check_effect_configs(configs: list, robot, n_stored: int, run_dir: Path) -> None:
    """Refuse effect configs (``model.json``) whose numbers cannot come from a run before anything is built.

    Every number must be finite; every integer (not a bool) at least 0 (``hidden`` at least 1) and at most its
    :data:`SIZE_LIMITS` entry (other keys: :data:`MAX_CONFIG_INT`); and no size may exceed ``n_stored``, the number of
    values model.pt holds: each size counts values stored there (a network of ``hidden`` units stores at least
    ``hidden`` weights), so a larger one cannot agree with the state (which ``load_state_dict`` checks exactly).
    A ``joint`` must be a joint of ``robot``: 1..dof.
    """
    count = 0

    def bad(where: str, what: str) -> OptionError:
        return _run_error(run_dir, f"model.json: {where}: {what}")

    def walk(value, where: str, key: str | None) -> None:
        nonlocal count
        if isinstance(value, dict):
            if "class" in value:
                count += 1
                if count > MAX_EFFECTS:
                    raise bad(where, f"more than {MAX_EFFECTS} effects")
            for k, v in value.items():
                walk(v, f"{where}.{k}", str(k))
        elif isinstance(value, list):
            for i, v in enumerate(value):
                walk(v, f"{where}[{i}]", key)
        elif isinstance(value, bool) or value is None or isinstance(value, str):
            return
        elif isinstance(value, float):
            if not math.isfinite(value):
                raise bad(where, f"{value} is not a finite number")
            if key in SIZE_LIMITS or key == "joint":
                raise bad(where, f"must be a whole number, got {value!r}")
        elif isinstance(value, int):
            if key == "joint":
                if not 1 <= value <= robot.dof:
                    raise bad(where, f"joint {value} is not a joint of robot '{robot.name}' (1..{robot.dof})")
                return
            cap, low = SIZE_LIMITS.get(key, MAX_CONFIG_INT), 1 if key == "hidden" else 0
            if not low <= value <= cap:
                raise bad(where, f"{value} is outside {low}..{cap}")
            if key in SIZE_LIMITS and value > max(n_stored, 1):
                raise bad(where, f"{value} is larger than the {n_stored} values model.pt holds; they cannot agree")
        else:
            raise bad(where, f"unexpected value {value!r}")

    for i, c in enumerate(configs):
        walk(c, f"effects[{i}]", None)


def _load_torch_file(run_dir: Path, name: str):
    """A run directory's tensor file ``name`` (read bounded, ``weights_only``: no pickled object runs), or the run
    error that names it."""
    raw = read_bounded(run_dir / name, name, lambda m: _run_error(run_dir, f"{name} {m}"))
    try:
        return torch.load(io.BytesIO(raw), weights_only=True, map_location="cpu")
    except pickle.UnpicklingError:
        raise _run_error(run_dir, f"{name} holds more than tensors (a pickled object); refused to load it") from None
    except (RuntimeError, EOFError, OSError, ValueError) as e:
        raise _run_error(run_dir, f"{name} cannot be read (truncated or not a torch file: {e})") from None


def load_model(run_dir: str | os.PathLike) -> tuple[MeasurementModel, dict]:
    """Rebuild the calibrated measurement model of a run directory.

    Raises:
        OptionError: not a run directory, or one whose ``model.json``/``model.pt`` is missing, malformed,
            truncated, not a plain tensor file, or names a robot file outside the run directory.
    """
    run_dir = Path(run_dir)
    meta_path = run_dir / "model.json"
    if not run_dir.is_dir():
        raise _run_error(run_dir, "not a directory")
    if not meta_path.exists():
        raise _run_error(run_dir, "not a torchcal run directory (no model.json)")
    meta = load_json(meta_path, "model.json", lambda m: _run_error(run_dir, f"model.json {m}"))
    if not isinstance(meta, dict):
        raise _run_error(run_dir, "model.json is not a JSON object")
    missing = [k for k in ("robot_file", "effects") if k not in meta]
    if missing:
        raise _run_error(run_dir, f"model.json lacks {', '.join(missing)}")
    rf = meta["robot_file"]
    if not isinstance(rf, str) or not rf:
        raise _run_error(run_dir, f"model.json: robot_file must be a relative path, got {rf!r}")
    robot_path = Path(os.path.realpath(run_dir / rf))
    if Path(rf).is_absolute() or Path(os.path.realpath(run_dir)) not in robot_path.parents:
        raise _run_error(run_dir, f"model.json: robot_file {rf!r} points outside the run directory; refused")
    for key in ("base_link", "tip_link"):
        if meta.get(key) is not None and not isinstance(meta[key], str):
            raise _run_error(run_dir, f"model.json: {key} must be a link name, got {meta[key]!r}")
    if not isinstance(meta["effects"], list) or not all(isinstance(c, dict) for c in meta["effects"]):
        raise _run_error(run_dir, "model.json: effects must be a list of objects")
    robot = load_robot(robot_path, base_link=meta.get("base_link"), tip_link=meta.get("tip_link"))
    for key in ("stations", "probes"):  # one instrument pose per station, one lever arm per probe
        names = meta.get(key)
        if names is None:
            continue
        ok = isinstance(names, list) and 1 < len(names) <= MAX_LABELS and all(isinstance(v, str) for v in names)
        if not ok or len(set(names)) != len(names):
            raise _run_error(run_dir, f"model.json: {key} must be a list of 2..{MAX_LABELS} distinct names")
        (robot.set_stations if key == "stations" else robot.set_probes)(names)
    pt = run_dir / "model.pt"
    if not pt.exists():
        raise _run_error(run_dir, "model.pt is missing")
    state = _load_torch_file(run_dir, "model.pt")
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise _run_error(run_dir, "model.pt does not hold a state dict of tensors")
    # every size in model.json is rebuilt as tensors before the state is loaded into them: bound them first
    check_effect_configs(meta["effects"], robot, sum(v.numel() for v in state.values()), run_dir)
    try:
        effects = [effect_from_config(c, robot) for c in meta["effects"]]
    except TorchcalError:
        raise
    except (KeyError, TypeError, ValueError) as e:
        raise _run_error(run_dir, f"model.json: an effect cannot be rebuilt ({type(e).__name__}: {e})") from None
    if "robot.tool_rotation.delta" in state:  # a run on a 6-D probe's data: the probe frame's rotation in the flange
        robot.enable_orientation()
    model = MeasurementModel(robot, effects)
    if "robot.readings.delta" not in state and robot.readings.is_identity:  # written before readings maps existed
        state["robot.readings.delta"] = robot.readings.delta.detach().clone()
    try:
        model.load_state_dict(state)
    except (RuntimeError, TypeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise _run_error(run_dir, f"model.pt does not match model.json ({first})") from None
    _check_state(run_dir, model)
    _set_region(model, meta.get("region"), run_dir)
    model.tool_cone = _tool_cone(meta.get("tool_axis"), run_dir)
    return model, meta


def load_covariance(run_dir: str | os.PathLike, model: MeasurementModel) -> ParameterCovariance | None:
    """The run's parameter covariance (``covariance.pt``) checked against its loaded ``model``; None when the run has
    none (a fit whose normal matrix was singular, or a run written before it was kept)."""
    run_dir = Path(run_dir)
    path = run_dir / "covariance.pt"
    if not path.exists():
        return None
    state = _load_torch_file(run_dir, "covariance.pt")
    try:
        return ParameterCovariance.from_state(state, model)
    except ValueError as e:
        raise _run_error(run_dir, f"covariance.pt does not fit model.pt: it {e}") from None


def load_prior(run_dir: str | os.PathLike) -> Prior:
    """A run directory as the prior of a new calibration (:func:`torchcal.pipeline.prior.prior_from_run`): its
    model, its parameter covariance and the variance factor of the fit that covariance is of (report.json's
    ``global_test.statistic``; 1 where the report lacks it)."""
    run_dir = Path(run_dir)
    model, meta = load_model(run_dir)
    if meta.get("method") == "pcm":
        # the pcm method keeps the nominal geometry and its network corrects that geometry's residual: an update of
        # the geometry from a few rows would leave the network correcting a geometry it was not fitted with
        raise OptionError(
            f"{run_dir}: a run of the pcm method cannot be the prior of an update (its correction network was "
            "fitted to the nominal geometry, which an update moves); calibrate the new rows with --method pcm, or "
            "use a kinematic or default-method run as the prior"
        )
    s0_sq, effects = 1.0, ()
    if (run_dir / "report.json").exists():
        rep = load_json(run_dir / "report.json", "report.json", lambda m: _run_error(run_dir, f"report.json {m}"))
        stat = rep.get("global_test", {}).get("statistic") if isinstance(rep, dict) else None
        if isinstance(stat, (int, float)) and math.isfinite(stat) and stat > 0:
            s0_sq = float(stat)
        found = rep.get("effects") if isinstance(rep, dict) else None
        if isinstance(found, list) and meta["effects"]:
            effects = tuple(e for e in found if isinstance(e, dict))
    from torchcal.pipeline import prior_from_run

    prior = prior_from_run(model, load_covariance(run_dir, model), str(run_dir), s0_sq)
    return dataclasses.replace(prior, effects=effects)


def check_prior_robot(run_dir: str | os.PathLike, robot, given: str) -> None:
    """Refuse ``--robot`` (``given``, loaded as ``robot``) where it is not the robot the prior run calibrated: an
    update starts from the prior run's robot and its corrections, so another description would be ignored while
    the report named it. Compared by joints and by the nominal forward kinematics at seeded joint angles inside the
    limits (to 1 um)."""
    run_dir = Path(run_dir)
    meta = load_json(run_dir / "model.json", "model.json", lambda m: _run_error(run_dir, f"model.json {m}"))
    theirs = load_robot(run_dir / meta["robot_file"], base_link=meta.get("base_link"), tip_link=meta.get("tip_link"))
    why = None
    if theirs.dof != robot.dof:
        why = f"it has {robot.dof} joints, the prior run's robot {theirs.dof}"
    else:
        lo = theirs.limits[:, 0]
        hi = torch.minimum(theirs.limits[:, 1], lo + 2 * math.pi)  # a +-10 m track or an unlimited joint: one span
        u = torch.rand(64, theirs.dof, generator=torch.Generator().manual_seed(0), dtype=lo.dtype, device=lo.device)
        q = lo + u * (hi - lo)
        with torch.no_grad():
            gap = float((robot.to(q.device)(q) - theirs(q)).norm(dim=-1).max())
        if gap > 1e-6:
            why = f"its flange is up to {gap * 1e3:.3f} mm from the prior run's robot's at the same joint angles"
    if why is not None:
        raise OptionError(
            f"robot {given} (--robot) is not the robot of the prior run {run_dir} ({meta['robot_file']}): {why}. An "
            "update starts from the prior run's robot and its corrections; give that robot, or calibrate from scratch "
            "without the prior (--prior)"
        )


def load_trust(run_dir: str | os.PathLike, meta: dict, key: str = "trust") -> Trust | None:
    """model.json's predictive-sigma entry ``key`` (:class:`~torchcal.estimate.trust.Trust`); None where the run was
    written before it existed or measured it on too few held-out rows."""
    d = meta.get(key) if key == "trust" else (meta.get("geometric") or {}).get("trust")
    if d is None:
        return None
    try:
        return Trust.from_dict(d)
    except ValueError as e:
        raise _run_error(Path(run_dir), f"model.json: {key}: {e}") from None


def load_few_rows(run_dir: str | os.PathLike, meta: dict) -> FewRows | None:
    """model.json's bounds on the sigma's scale from too few held-out rows (:class:`~torchcal.estimate.trust.FewRows`);
    None where the run measured a level, held out no row or was written before the bounds existed."""
    d = meta.get("trust_few_rows")
    if d is None:
        return None
    try:
        return FewRows.from_dict(d)
    except ValueError as e:
        raise _run_error(Path(run_dir), f"model.json: trust_few_rows: {e}") from None


def _unmeasured_sigma(run_dir: Path, model: MeasurementModel, meta: dict, ctx: Context) -> tuple[Tensor | None, str]:
    """The sigma and its note of a run without a measured level: bounded by its few held-out rows where it kept them
    (:func:`load_few_rows`), else :func:`_old_run_sigma`."""
    few = load_few_rows(run_dir, meta)
    if few is None:
        return _old_run_sigma(run_dir, model, ctx, measured="trust" in meta)
    return few.std(model, ctx, load_covariance(run_dir, model)), f"{run_dir}: the run's sigma {few.note()}"


def load_geometric(
    run_dir: str | os.PathLike, model: MeasurementModel, meta: dict
) -> tuple[MeasurementModel, ParameterCovariance | None, Trust] | None:
    """The kinematic calibration a run keeps beside a final model that is not it (``geometric.pt``), with its
    covariance and :class:`~torchcal.estimate.trust.Trust`; None where the run keeps none."""
    run_dir = Path(run_dir)
    geo_trust = load_trust(run_dir, meta, "geometric")
    if geo_trust is None or not (run_dir / "geometric.pt").exists():
        return None
    geo, cov = _side_model(run_dir, model, "geometric")
    return geo, cov, geo_trust


def _side_model(
    run_dir: Path, model: MeasurementModel, name: str
) -> tuple[MeasurementModel, ParameterCovariance | None]:
    """A model the run keeps beside its own (``NAME.pt``, no effects, on ``model``'s robot and region, not fading)
    and its covariance (``covariance_NAME.pt``, None where absent); a file that does not fit is a damaged run."""
    import copy

    side = MeasurementModel(copy.deepcopy(model.robot))
    try:
        side.load_state_dict(_load_torch_file(run_dir, f"{name}.pt"))
    except (RuntimeError, TypeError, AttributeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise _run_error(run_dir, f"{name}.pt does not match model.json ({first})") from None
    _check_state(run_dir, side)
    side.set_region(model.region, fade=False)
    if not (run_dir / f"covariance_{name}.pt").exists():
        return side, None
    try:
        return side, ParameterCovariance.from_state(_load_torch_file(run_dir, f"covariance_{name}.pt"), side)
    except ValueError as e:
        raise _run_error(run_dir, f"covariance_{name}.pt does not fit {name}.pt: it {e}") from None


def load_standalone(run_dir: str | os.PathLike, model: MeasurementModel) -> MeasurementModel | None:
    """The geometry a run with effects exports (``standalone.pt``, :mod:`torchcal.pipeline.standalone`): ``model``'s
    robot with that state, no effects; None where the run keeps none (no effects, or written before it)."""
    import copy

    run_dir = Path(run_dir)
    if not (run_dir / "standalone.pt").exists():
        return None
    alone = MeasurementModel(copy.deepcopy(model.robot))
    try:
        alone.load_state_dict(_load_torch_file(run_dir, "standalone.pt"))
    except (RuntimeError, TypeError, AttributeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise _run_error(run_dir, f"standalone.pt does not match model.json ({first})") from None
    _check_state(run_dir, alone)
    return alone


def load_holdout(run_dir: str | os.PathLike, dof: int) -> dict[str, Tensor] | None:
    """The held-out rows a run keeps (``holdout.pt``: ``q (N, dof)``, ``p (N, 3)`` and where the run has several
    stations or probes their ``station``, ``probe`` indices), checked; None where the run keeps none."""
    run_dir = Path(run_dir)
    if not (run_dir / "holdout.pt").exists():
        return None
    rows = _load_torch_file(run_dir, "holdout.pt")
    ok = isinstance(rows, dict) and all(isinstance(rows.get(k), Tensor) for k in ("q", "p"))
    n = rows["q"].shape[0] if ok and rows["q"].dim() == 2 else -1
    ok = ok and n > 0 and tuple(rows["q"].shape) == (n, dof) and tuple(rows["p"].shape) == (n, 3)
    ok = ok and all(
        k not in rows or (isinstance(rows[k], Tensor) and tuple(rows[k].shape) == (n,)) for k in ("station", "probe")
    )
    if not ok or not all(bool(torch.isfinite(rows[k]).all()) for k in ("q", "p")):
        raise _run_error(run_dir, f"holdout.pt must hold finite q (N, {dof}) and p (N, 3) tensors")
    return rows


#: the column predict and compensate write to say which model gave each row (RowTrust.which): the run's model, its
#: kinematic calibration, its geometry and physical effects alone, or the nominal geometry with the fitted instrument
#: pose and lever arm (:mod:`torchcal.pipeline.beyond`)
MODEL_NAMES = CANDIDATES
#: beyond the region, in a run that could not choose on held-out rows (:mod:`torchcal.pipeline.beyond`), the kinematic
#: calibration predicts a row only where the run's model's sigma is more than this many times its own: within it the
#: richer model's error stays the smaller though its sigma is not (it knows more of what it is unsure of), far above
#: it the richer model is guessing
SWITCH_RATIO = 2.0


def load_nominal(
    run_dir: str | os.PathLike, model: MeasurementModel, meta: dict
) -> tuple[MeasurementModel, ParameterCovariance | None, Trust] | None:
    """The nominal geometry with the fitted instrument pose and lever arm a run keeps (``nominal.pt``), with its
    covariance and :class:`~torchcal.estimate.trust.Trust`; None where the run keeps none (written before it, or
    re-stationed: its instrument pose is the old placement's)."""
    run_dir = Path(run_dir)
    d = meta.get("nominal")
    if not isinstance(d, dict) or d.get("trust") is None or not (run_dir / "nominal.pt").exists():
        return None
    try:
        tr = Trust.from_dict(d["trust"])
    except ValueError as e:
        raise _run_error(run_dir, f"model.json: nominal: trust: {e}") from None
    nom, cov = _side_model(run_dir, model, "nominal")
    return nom, cov, tr


def load_physical(
    run_dir: str | os.PathLike, model: MeasurementModel, meta: dict
) -> tuple[MeasurementModel, ParameterCovariance | None, Trust] | None:
    """The run's model without the parts that fade beyond the region, with the part of the run's covariance that is
    about it and its :class:`~torchcal.estimate.trust.Trust`; None where the run measured none."""
    from torchcal.estimate.trust import without_fading

    d = meta.get("physical")
    if not isinstance(d, dict) or d.get("trust") is None:
        return None
    try:
        tr = Trust.from_dict(d["trust"])
    except ValueError as e:
        raise _run_error(Path(run_dir), f"model.json: physical: trust: {e}") from None
    phys = without_fading(model)
    try:
        cov = load_covariance(run_dir, phys)
    except OptionError:  # the covariance is also about the learned parts: the calibration measured it without one
        cov = None
    return phys, cov, tr


def beyond_choice(meta: dict) -> str | None:
    """The candidate a run chose for its rows beyond the region (model.json's ``beyond``), None where it chose none
    (too few held-out rows beyond, or a run written before the choice)."""
    d = meta.get("beyond")
    name = d.get("model") if isinstance(d, dict) else None
    return name if name in MODEL_NAMES else None


@dataclass
class RowTrust:
    """How far to trust each row (:func:`row_trust`).

    Attributes:
        sigma: the predictive standard deviation ``(N, 3)`` [m] of the model each row uses; None where the run has
            neither a covariance nor a measured level.
        extrapolation: ``(N,)`` how far each pose lies outside the calibrated region [rad or m].
        which: ``(N,)`` which model predicts each row, an index into :data:`MODEL_NAMES`: 0 (the run's model) inside
            the region; beyond it the candidate the run chose on its held-out rows (:mod:`torchcal.pipeline.beyond`),
            or in a run that chose none its kinematic calibration (1) where the model's sigma is more than
            :data:`SWITCH_RATIO` times that one's.
        geometric: the model that predicts the rows whose ``which`` is not 0 (the kinematic calibration, or the
            candidate the run chose; None where there is none).
        note: what the sigma lacks, for the user (a run written before the measured level), else None.
    """

    sigma: Tensor | None
    extrapolation: Tensor
    which: Tensor
    geometric: MeasurementModel | None = None
    note: str | None = None
    geometric_sigma: Callable[[Context], Tensor] | None = None  # that model's sigma at other rows


def _old_run_sigma(
    run_dir: Path, model: MeasurementModel, ctx: Context, measured: bool = False
) -> tuple[Tensor | None, str]:
    """The sigma of a run without a measured level (written before it, or ``measured`` but on too few held-out
    rows): parameters, learned posterior and the report's tracker noise, and the note that says so."""
    from torchcal.estimate.covariance import combined_std

    s = combined_std(model, ctx, load_covariance(run_dir, model))
    noise = None
    if (run_dir / "report.json").exists():
        rep = load_json(run_dir / "report.json", "report.json", lambda m: _run_error(run_dir, f"report.json {m}"))
        v = rep.get("stochastic_model", {}).get("tracker_sigma_m") if isinstance(rep, dict) else None
        noise = float(v) if isinstance(v, int | float) and math.isfinite(v) and v >= 0 else None
    why = (
        f"had fewer than {MIN_ROWS} held-out rows to measure what its model leaves unexplained on"
        if measured
        else "was written before torchcal measured what its model leaves unexplained"
    )
    note = (
        f"{run_dir}: the run {why}: sx, sy, sz hold the parameters' and the learned model's uncertainty"
        + (" and the instrument's noise" if noise is not None else "")
        + " only, and understate the error; "
        + (f"hold out {MIN_ROWS} rows or more" if measured else "calibrate again")
        + " for a sigma that covers it"
    )
    if s is None or noise is None:
        return s, note
    return (s.square() + noise**2).sqrt(), note


@torch_threads(1)  # per-row sigmas from many small products: a second thread only waits
def row_trust(run_dir: str | os.PathLike, model: MeasurementModel, meta: dict, ctx: Context) -> RowTrust:
    """How far to trust the predictions of a run's loaded ``model`` at the rows ``ctx`` (CONTRACT §3): the standard
    deviation of a new measurement minus the prediction (:class:`~torchcal.estimate.trust.Trust`) of the model that
    predicts each row. Beyond the calibrated region that is the candidate the run chose on its held-out rows beyond
    it (:mod:`torchcal.pipeline.beyond`), with its own sigma; in a run that chose none, the kinematic calibration the
    run keeps beside its model where the model's sigma is far above that one's (:data:`SWITCH_RATIO`)."""
    run_dir = Path(run_dir)
    ext = torch.maximum(model.extrapolation(ctx.q).cpu(), tool_axis_beyond(model, ctx.q).to(ctx.q.dtype))
    which = torch.zeros(len(ext), dtype=torch.long, device=ext.device)
    tr = load_trust(run_dir, meta)
    if tr is None:
        sigma, note = _unmeasured_sigma(run_dir, model, meta, ctx)
        return RowTrust(None if sigma is None else sigma.cpu(), ext, which, note=note)
    sigma = tr.std(model, ctx, load_covariance(run_dir, model)).cpu()
    chosen = beyond_choice(meta)
    loader = {"geometric": load_geometric, "physical": load_physical, "nominal": load_nominal}.get(chosen or "")
    alt = loader(run_dir, model, meta) if loader is not None else None
    if chosen == "full":
        return RowTrust(_sigma_beyond(run_dir, model, meta, ctx, ext, sigma), ext, which)
    if chosen is not None and alt is None:  # a candidate not kept here (a re-stationed run: the old placement's)
        return RowTrust(sigma, ext, which)
    if alt is None:
        alt = load_geometric(run_dir, model, meta)
    elif chosen == "physical":  # its sigma beyond: its covariance bounded by the tolerance priors
        alt = _bounded(run_dir, meta, *alt)
    out = ext > 0
    if alt is None or not bool(out.any()):
        return RowTrust(sigma, ext, which, None if alt is None else alt[0])
    m, cov, alt_trust = alt
    rows = torch.nonzero(out).flatten()
    s_alt = alt_trust.std(m, ctx.subset(rows.to(ctx.q.device)), cov).cpu()
    # a chosen candidate predicts every row beyond; else the kinematic calibration where the model's sigma is far above
    take = (
        torch.ones(len(rows), dtype=torch.bool, device=rows.device)
        if chosen is not None
        else SWITCH_RATIO * s_alt.norm(dim=1) < (sigma[rows].norm(dim=1))
    )
    sigma[rows[take]] = s_alt[take]
    which[rows[take]] = MODEL_NAMES.index(chosen or "geometric")
    return RowTrust(sigma, ext, which, m, geometric_sigma=lambda c: alt_trust.std(m, c, cov).cpu())


def _beyond_trust(
    run_dir: Path, meta: dict, model: MeasurementModel
) -> tuple[ParameterCovariance | None, Trust] | None:
    """The covariance bounded by the tolerance priors (``covariance_beyond.pt``) and the trust measured with it of
    the run's chosen model (full or physical) beyond the region; None where the run keeps none (a re-stationed run)."""
    d = meta.get("beyond")
    if not isinstance(d, dict) or d.get("trust") is None or not (run_dir / "covariance_beyond.pt").exists():
        return None
    try:
        tr = Trust.from_dict(d["trust"])
    except ValueError as e:
        raise _run_error(run_dir, f"model.json: beyond: trust: {e}") from None
    try:
        cov = ParameterCovariance.from_state(_load_torch_file(run_dir, "covariance_beyond.pt"), model)
    except ValueError as e:
        raise _run_error(run_dir, f"covariance_beyond.pt does not fit the model: it {e}") from None
    return cov, tr


def _bounded(run_dir: Path, meta: dict, model: MeasurementModel, cov, tr):
    """``(model, cov, trust)`` with the covariance and trust of the rows beyond where the run keeps them."""
    got = _beyond_trust(run_dir, meta, model)
    return (model, cov, tr) if got is None else (model, *got)


def _sigma_beyond(run_dir: Path, model: MeasurementModel, meta: dict, ctx: Context, ext: Tensor, sigma: Tensor):
    """``sigma`` with the rows beyond the region given the run's model's sigma beyond (:func:`_beyond_trust`)."""
    got = _beyond_trust(run_dir, meta, model)
    rows = torch.nonzero(ext > 0).flatten()
    if got is None or not len(rows):
        return sigma
    cov, tr = got
    sigma[rows] = tr.std(model, ctx.subset(rows.to(ctx.q.device)), cov).cpu()
    return sigma


def trust(run_dir: str | os.PathLike, model: MeasurementModel, ctx: Context) -> tuple[Tensor | None, Tensor]:
    """The run's model's own predictive standard deviation ``(N, 3)`` [m] at ``ctx`` (:func:`row_trust` without the
    choice of model; None where the run has none) and the extrapolation ``(N,)``."""
    run_dir = Path(run_dir)
    meta = load_json(run_dir / "model.json", "model.json", lambda m: _run_error(run_dir, f"model.json {m}"))
    meta = meta if isinstance(meta, dict) else {}
    tr = load_trust(run_dir, meta)
    if tr is None:
        sigma = _unmeasured_sigma(run_dir, model, meta, ctx)[0]
    else:
        sigma = tr.std(model, ctx, load_covariance(run_dir, model))
    ext = torch.maximum(model.extrapolation(ctx.q).cpu(), tool_axis_beyond(model, ctx.q).to(ctx.q.dtype))
    return (None if sigma is None else sigma.cpu()), ext


def _check_state(run_dir: Path, model: MeasurementModel) -> None:
    """Refuse a loaded model that cannot predict: a NaN anywhere, an infinite fitted value or nominal geometry
    (joint limits alone may be infinite: a continuous joint), or joint limits whose lower is above the upper.
    Blamed on ``model.pt``, before any data file is read against the limits."""
    params = {name for name, _ in model.named_parameters()}
    for name, value in model.state_dict().items():
        if not value.is_floating_point():
            continue
        if bool(torch.isnan(value).any()) or (
            not name.endswith("limits")
            and (name in params or name.endswith("nominal"))
            and not bool(torch.isfinite(value).all())
        ):
            raise _run_error(
                run_dir, f"model.pt: {name} holds non-finite values; the run directory is damaged or the fit diverged"
            )
    limits = model.robot.limits
    inverted = (limits[:, 0] > limits[:, 1]).nonzero().flatten().tolist()
    if inverted:
        k = inverted[0]
        raise _run_error(
            run_dir,
            f"model.pt: the limits of joint {k + 1} ({model.robot.joint_names[k]}) are inverted, lower "
            f"{float(limits[k, 0])!r} > upper {float(limits[k, 1])!r}; the run directory is damaged",
        )


#: stations or probes a run directory may name (each is a 6- or 3-element group of model.pt)
MAX_LABELS = 10000


def rows_of(model: MeasurementModel, data: Measurements) -> Measurements:
    """``data`` with its station and probe indices in the model's order (by name); rows of a file without a
    ``station`` (``probe``) column take the model's first station (probe). A name the model does not know is an error
    naming it and the model's names; a model of one station (probe) ignores the column."""
    out = {}
    for key, known in (("station", model.robot.stations), ("probe", model.robot.probes)):
        index, names = getattr(data, key), getattr(data, f"{key}_names")
        if not known:
            out[key], out[f"{key}_names"] = None, ()
            continue
        if index is None:
            index = torch.zeros(data.n, dtype=torch.long, device=data.q.device)
        else:
            unknown = [n for n in names if n not in known]
            if unknown:
                raise _label_error(data, key, unknown[0], f"is not one of the run's {key}s ({', '.join(known)})")
            lut = torch.tensor([known.index(n) for n in names], dtype=torch.long, device=index.device)
            index = lut[index]
        out[key], out[f"{key}_names"] = index, tuple(known)
    return dataclasses.replace(data, meta=dict(data.meta), **out)


def _label_error(data: Measurements, key: str, name: str, why: str) -> MeasurementFileError:
    """The refusal of the first row of ``data`` whose ``key`` column names ``name``: file, line and column."""
    index, names = getattr(data, key), getattr(data, f"{key}_names")
    row = int(torch.nonzero(index.cpu() == names.index(name))[0])
    line = data.lines[row] if data.lines else None
    return MeasurementFileError(data.source or "the data", f"{key} {name!r} {why}", line=line, column=key)


def check_placement(meta: dict, data: Measurements, keys: tuple[str, ...] = ("station", "probe")) -> None:
    """Refuse rows that name another station or probe than the one a run of a single instrument pose (lever arm)
    was fitted for: a re-stationed run's placement (``model.json``'s ``station`` ``label``: the station its points
    named), or the one name of a calibration's rows (``labels``). Without them the model would predict those rows
    in its own frame, with its own lever arm, metres off and without a word. A run without such a label leaves the
    columns to :func:`rows_of`. ``keys``: the columns to check."""
    for key, label, why in _run_labels(meta):
        index = getattr(data, key)
        if index is None or key not in keys:
            continue
        names = getattr(data, f"{key}_names")
        used = {names[int(i)] for i in torch.unique(index.cpu())}
        other = [n for n in names if n != label and n in used]
        if other:
            raise _label_error(data, key, other[0], why)


def _run_labels(meta: dict) -> list[tuple[str, str, str]]:
    """``(key, label, why another is refused)`` for the station and probe a run holds a single name of."""
    placed = meta.get("station") if isinstance(meta.get("station"), dict) else {}
    labels = meta.get("labels") if isinstance(meta.get("labels"), dict) else {}
    out = []
    if isinstance(placed.get("label"), str):
        why = f"is not the run's placement: it was re-stationed on points of {placed['label']!r}"
        out.append(("station", placed["label"], why))
    elif isinstance(labels.get("station"), str):
        why = f"is not the run's placement: it was calibrated on rows of station {labels['station']!r} only"
        out.append(("station", labels["station"], why + " (re-station it for this one: torchcal station)"))
    if isinstance(labels.get("probe"), str):
        why = f"is not the run's probe: it was calibrated on rows of probe {labels['probe']!r} only"
        out.append(("probe", labels["probe"], why + ", whose lever arm another probe does not share"))
    return out


def own_names(meta: dict, station: str | None, probe: str | None) -> tuple[str | None, str | None]:
    """``--station`` / ``--probe`` of a command on the run, None where they name the one station (probe) the run
    holds (:func:`_run_labels`): that name is the run's own, not one of several to choose from; another name is
    refused with the run's."""
    own = {key: (label, why) for key, label, why in _run_labels(meta)}
    out = []
    for key, name in (("station", station), ("probe", probe)):
        if key in own and name is not None and name != own[key][0]:
            raise OptionError(f"{key} {name!r} (--{key}) {own[key][1]}")
        out.append(None if key in own and name == own[key][0] else name)
    return out[0], out[1]


def at_station(
    model: MeasurementModel, station: str | None = None, probe: str | None = None, *, groups: bool = True
) -> tuple[MeasurementModel, int, int]:
    """A copy of ``model`` with one instrument pose and one lever arm, those of ``station`` and ``probe`` (names;
    None: the first), for what works in one frame (``compensate``); with their indices in ``model``. A learned
    correction per station and probe becomes that pair's (none where the pair has none; none at all without
    ``groups``: at a new placement no station's applies). A model of one station and one probe comes back as it is
    (a name given for it must then be absent)."""
    import copy

    from torchcal.effects.grouped import GroupedCorrection
    from torchcal.robot.model import Instrument, Tool

    robot = model.robot
    picked = []
    for key, name, known in (("station", station, robot.stations), ("probe", probe, robot.probes)):
        if name is not None and name not in known:
            have = f"the run's {key}s are {', '.join(known)}" if known else f"the run has a single {key}"
            raise OptionError(f"{key} {name!r} is not one of the run's: {have}")
        picked.append(known.index(name) if name is not None else 0)
    if not robot.stations and not robot.probes:
        return model, 0, 0
    out = copy.deepcopy(model)
    r = out.robot
    with torch.no_grad():
        r.instrument = Instrument(robot.T_tracker_base(picked[0]).detach(), dtype=r.dtype, device=r.device)
        r.tool = Tool(robot.t_flange_probe(picked[1]).detach(), dtype=r.dtype, device=r.device)
    for i, e in reversed(list(enumerate(out.effects))):
        if isinstance(e, GroupedCorrection):
            key = (picked[0], picked[1])
            if groups and key in e.groups:
                out.effects[i] = e.inner[e.groups.index(key)]
            else:
                del out.effects[i]
    return out, picked[0], picked[1]


def predict(run_dir: str | os.PathLike, data: Measurements, device: torch.device | str = "cpu") -> torch.Tensor:
    """Predicted probe positions in the tracker frame ``(N, 3)`` [m] with everything the run learned, computed
    on ``device`` and returned on the CPU."""
    model, meta = load_model(run_dir)
    return predict_with(model, meta, data, device)


@torch_threads(1)  # a series of small kernels: a second thread only waits (docs/benchmarks.md)
def predict_with(
    model: MeasurementModel, meta: dict, data: Measurements, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """:func:`predict` with a model already loaded (:func:`load_model`); the model is moved to ``device``."""
    model, data = model.to(device), data.to(device)
    if data.dof != model.robot.dof:
        raise OptionError(f"data have {data.dof} joints but the run's robot '{model.robot.name}' has {model.robot.dof}")
    check_placement(meta, data)
    data = rows_of(model, data)
    with torch.no_grad():
        return model(
            Context.from_measurements(data, trajectory=bool(meta.get("trajectory")) and data.t is not None)
        ).cpu()


def predict_orientation(model: MeasurementModel, meta: dict, data: Measurements) -> torch.Tensor | None:
    """Predicted probe orientations in the tracker frame as rotation vectors ``(N, 3)`` [rad] where the run fitted a
    6-D probe's orientation (its model has the probe frame's rotation), else None. Joint effects turn the probe;
    Cartesian corrections (the learned ones) do not."""
    if not model.robot.has_orientation:
        return None
    from torchcal.data.ipa import matrix_to_rotvec

    data = data.to(model.robot.device)
    with torch.no_grad():
        ctx = Context.from_measurements(data, trajectory=bool(meta.get("trajectory")) and data.t is not None)
        return matrix_to_rotvec(model.orientation(ctx)).cpu()
