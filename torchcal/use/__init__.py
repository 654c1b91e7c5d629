"""The use of a finished run: load it, predict with how far to trust each row, re-station it after the instrument
moved, command the joints that reach targets (``compensate``), plan the poses of the next campaign, export the
calibrated robot to the files other software reads (``export``).

A layer above the pipeline (a run is what the pipeline made) and below the report (which writes what this reads)
and the command line (which calls into it).
"""

from torchcal.use.rundir import load_covariance, load_model, load_prior, predict

__all__ = ["load_covariance", "load_model", "load_prior", "predict"]
