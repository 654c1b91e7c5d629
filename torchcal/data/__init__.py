"""Measurement data: the CSV file format, validation and units."""

from torchcal.data.measurements import (
    ANGLE_UNITS,
    LENGTH_UNITS,
    Measurements,
    read_measurements,
    write_measurements,
)

__all__ = ["ANGLE_UNITS", "LENGTH_UNITS", "Measurements", "read_measurements", "write_measurements"]
