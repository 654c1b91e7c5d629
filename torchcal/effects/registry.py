"""The one table of effect kinds: their classes, where they act, whether least squares fits them.

``report.json`` names effects by kind (CONTRACT §4); ``model.json`` rebuilds them by class
(:func:`effect_from_config`). Both read this table, and so does the calibration when it decides which
effects' parameters to fit jointly with the geometry (:data:`NAMED_KINDS`).
"""

from __future__ import annotations

from dataclasses import dataclass

from torchcal.effects.base import Acts, Effect, read_renamed
from torchcal.effects.drift import Drift
from torchcal.effects.gp import GPCorrection
from torchcal.effects.grouped import GroupedCorrection
from torchcal.effects.instrument import TrackerError
from torchcal.effects.joint import (
    Backlash,
    Compliance,
    Coupling,
    Cyclic,
    LumpedCompliance,
    TorqueCompliance,
    Transmission,
)
from torchcal.effects.kernel import KernelCorrection
from torchcal.effects.learned import CorrectionNet, LearnedEffect
from torchcal.effects.region import RegionGate
from torchcal.errors import OptionError


@dataclass(frozen=True)
class EffectKind:
    """One kind of effect.

    Attributes:
        name: the kind as ``report.json`` writes it.
        classes: the effect classes of this kind (the first is the default one).
        acts: where its classes act (:class:`Acts`); a drift acts on the instrument or, as a scale, in Cartesian
            space, chosen per instance.
        named: a few physically meaningful parameters, fitted by least squares jointly with the geometry
            (False: a learned residual model with its own fit).
    """

    name: str
    classes: tuple[type[Effect], ...]
    acts: tuple[Acts, ...]
    named: bool


KIND_TABLE: tuple[EffectKind, ...] = (
    # the mass-based form where the robot description has masses, the lumped one (no link masses) elsewhere
    # and the one read from the measured joint torques (tau1..tauN columns)
    EffectKind("compliance", (Compliance, LumpedCompliance, TorqueCompliance), (Acts.JOINT,), True),
    EffectKind("backlash", (Backlash,), (Acts.JOINT,), True),
    EffectKind("cyclic", (Cyclic,), (Acts.JOINT,), True),
    EffectKind("drift", (Drift,), (Acts.INSTRUMENT, Acts.CARTESIAN), True),
    EffectKind(
        "learned",
        (LearnedEffect, KernelCorrection, GPCorrection, RegionGate, GroupedCorrection),
        (Acts.CARTESIAN,),
        False,
    ),
    # a joint-angle error polynomial in the joint's own angle (transmission ratio / scale, README)
    EffectKind("transmission", (Transmission,), (Acts.JOINT,), True),
    # one joint's reading error proportional to another joint's reading (an undeclared coupling, README)
    EffectKind("coupling", (Coupling,), (Acts.JOINT,), True),
    # the instrument's own errors in its spherical coordinates: encoder harmonics, range offset and scale (README)
    EffectKind("instrument", (TrackerError,), (Acts.TRACKER,), True),
)

#: effect kinds as named in report.json (CONTRACT §4)
KINDS: tuple[str, ...] = tuple(k.name for k in KIND_TABLE)
#: effect kinds whose parameters the least-squares fit estimates jointly with the geometry
NAMED_KINDS: tuple[str, ...] = tuple(k.name for k in KIND_TABLE if k.named)
#: effect classes by class name, for model.json
CLASSES: dict[str, type[Effect]] = {c.__name__: c for k in KIND_TABLE for c in k.classes}
#: class names model.json of earlier runs used, old -> new (their keys: :attr:`Effect.renamed`)
RENAMED_CLASSES = {"SupportGate": "RegionGate"}


def kind(name: str) -> EffectKind:
    """The table entry of kind ``name``."""
    for k in KIND_TABLE:
        if k.name == name:
            return k
    raise OptionError(f"unknown effect kind '{name}'; known: {', '.join(KINDS)}")


def effect_from_config(cfg: dict, robot=None) -> Effect:
    """Rebuild an effect from ``{"class": name, **config()}``; load its parameters with ``load_state_dict``.

    ``robot``: the run's robot, the skeleton of a :class:`RegionGate`'s fallback geometry (its values come with
    the state dict).
    """
    cfg = dict(cfg)
    name = cfg.pop("class")
    name = RENAMED_CLASSES.get(name, name)
    if name not in CLASSES:
        raise OptionError(f"unknown effect class '{name}'; known: {', '.join(CLASSES)}")
    read_renamed(cfg, CLASSES[name].renamed)  # a run written before a key's rename
    if name == "LearnedEffect":
        return LearnedEffect(CorrectionNet(cfg["dof"], cfg["hidden"]))
    if name == "GroupedCorrection":
        return GroupedCorrection(
            cfg["groups"], [effect_from_config(c, robot) for c in cfg["inner"]], cfg.get("regions")
        )
    if name == "RegionGate":
        if cfg.get("fallback") and robot is None:
            raise OptionError("a RegionGate with a fallback geometry needs the run's robot to be rebuilt")
        import copy

        import torch

        return RegionGate(
            effect_from_config(cfg["inner"], robot),
            torch.zeros(cfg["n_region"], cfg["dof"], dtype=torch.float64),
            cfg["length"],
            max_points=cfg["n_region"],
            fallback=copy.deepcopy(robot) if cfg.get("fallback") else None,
            predictive=cfg.get("predictive"),
            fallback_in_base=cfg.get("fallback_frame") == "base",
        )
    return CLASSES[name](**cfg)
