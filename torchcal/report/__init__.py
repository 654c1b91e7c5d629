"""Writing a run: report.json, report.md with plots, the calibrated URDF (reloading it: :mod:`torchcal.use`)."""

from torchcal.report.rundir import build_report, write_run, write_run_files

__all__ = ["build_report", "write_run", "write_run_files"]
