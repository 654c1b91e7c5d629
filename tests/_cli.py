"""What several test files share about the command line: ``simulate`` into a folder, and the fields CONTRACT §4
requires of the ``report.json`` that ``calibrate`` writes."""

from pathlib import Path

from torchcal.cli import main

#: the fields every report.json holds at least (CONTRACT §4)
REPORT_FIELDS = (
    "robot",
    "method",
    "n_train",
    "n_holdout",
    "rmse_before_mm",
    "rmse_geometric_mm",
    "rmse_after_mm",
    "max_after_mm",
    "global_test",
    "effects",
    "parameters",
)


def cli_simulate(out: Path | str, *options: str, robot: str = "ur5") -> int:
    """``torchcal simulate --robot ROBOT --out OUT OPTIONS... --quiet`` through :func:`torchcal.cli.main`.

    Returns:
        The command's exit status.
    """
    return main(["simulate", "--robot", robot, "--out", str(out), *options, "--quiet"])
