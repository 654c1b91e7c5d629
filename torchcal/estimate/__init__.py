"""Estimators: the least-squares machinery a calibration is built from.

- :mod:`~torchcal.estimate.rigid`: closed-form rigid fit (Kabsch / Horn) and its robust variant, the start of
  every calibration (tracker pose and lever arm);
- :mod:`~torchcal.estimate.problem`: a calibration as a whitened least-squares problem over selected parameters;
- :mod:`~torchcal.estimate.lm`: Levenberg-Marquardt with the adjustment statistics (variance factor, global test,
  standard deviations, correlations);
- :mod:`~torchcal.estimate.identifiability`: which parameters the data can separate;
- :mod:`~torchcal.estimate.fit`: fitting parameter groups of a measurement model, and per-pose errors;
- :mod:`~torchcal.estimate.covariance`: the parameter covariance and the standard deviation it gives a prediction;
- :mod:`~torchcal.estimate.robust`: gross-error screening (robust reweighting, data snooping);
- :mod:`~torchcal.estimate.netfit`: fitting a correction network by LM or L-BFGS;
- :mod:`~torchcal.estimate.check`: a Jacobian checker against central finite differences.

Only the rigid fit and the Jacobian checker are imported here; the rest are imported from their modules.
"""

from torchcal.estimate.check import check_jacobian, finite_difference_jacobian
from torchcal.estimate.rigid import fit_instrument_and_tool, rigid_fit

__all__ = ["check_jacobian", "finite_difference_jacobian", "fit_instrument_and_tool", "rigid_fit"]
