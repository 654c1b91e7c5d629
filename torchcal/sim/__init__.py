"""Simulated laser-tracker campaigns (poses, trajectories, biased geometry, noise, effects)."""

from torchcal.sim.campaign import (
    DEFAULT_SIZES,
    EFFECT_NAMES,
    Campaign,
    EffectSpec,
    SimConfig,
    simulate,
    write_campaign,
)
from torchcal.sim.poses import PATHS, Scene, SightRule, path, random_poses, trajectory, visible

__all__ = [
    "DEFAULT_SIZES",
    "EFFECT_NAMES",
    "PATHS",
    "path",
    "Campaign",
    "EffectSpec",
    "Scene",
    "SightRule",
    "SimConfig",
    "random_poses",
    "simulate",
    "trajectory",
    "visible",
    "write_campaign",
]
