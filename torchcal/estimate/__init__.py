"""Estimators: closed-form rigid fit (more to come: LM, identifiability, global test)."""

from torchcal.estimate.check import check_jacobian, finite_difference_jacobian
from torchcal.estimate.rigid import fit_instrument_and_tool, rigid_fit

__all__ = ["check_jacobian", "finite_difference_jacobian", "fit_instrument_and_tool", "rigid_fit"]
