"""Estimators: closed-form rigid fit (more to come: LM, identifiability, global test)."""

from torchcal.estimate.rigid import fit_instrument_and_tool, rigid_fit

__all__ = ["fit_instrument_and_tool", "rigid_fit"]
