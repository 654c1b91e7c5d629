"""One exception hierarchy for everything torchcal reports to its users.

Every error says what was expected and what came; file errors also name the file,
the 1-based line (as an editor shows it) and the column.
"""

from __future__ import annotations


class TorchcalError(Exception):
    """Base class of all torchcal errors."""


class RobotSpecError(TorchcalError, ValueError):
    """A robot description (built-in name, URDF, DH YAML) is missing or malformed."""


class ShapeError(TorchcalError, ValueError):
    """A tensor has the wrong shape, dtype or device."""


class MeasurementFileError(TorchcalError, ValueError):
    """A measurement file is malformed.

    Attributes:
        path: the file.
        line: 1-based line number in the file, or None when the whole file is concerned.
        column: the column name, or None.
    """

    def __init__(
        self, path, message: str, *, line: int | None = None, column: str | None = None, hint: str | None = None
    ):
        self.path = str(path)
        self.line = line
        self.column = column
        self.hint = hint
        where = self.path
        if line is not None:
            where += f", line {line}"
        if column is not None:
            where += f", column '{column}'"
        text = f"{where}: {message}"
        if hint:
            text += f" (hint: {hint})"
        super().__init__(text)


class EstimationError(TorchcalError, RuntimeError):
    """Numerical trouble in an estimator: rank deficiency, divergence, a failed solve."""


class OptionError(TorchcalError, ValueError):
    """An unknown option; the message lists the valid ones."""
