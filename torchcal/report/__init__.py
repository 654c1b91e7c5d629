"""Run directories: report.json, report.md with plots, the calibrated URDF, and reloading for predict."""

from torchcal.report.rundir import build_report, load_covariance, load_model, predict, write_run, write_run_files

__all__ = ["build_report", "load_covariance", "load_model", "predict", "write_run", "write_run_files"]
