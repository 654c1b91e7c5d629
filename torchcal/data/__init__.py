"""Measurement data: the CSV file format, validation and units, and real-data importers."""

from torchcal.data.ipa import convert_ipa, read_ipa
from torchcal.data.measurements import (
    ANGLE_UNITS,
    LENGTH_UNITS,
    Measurements,
    read_measurements,
    write_measurements,
)

__all__ = [
    "ANGLE_UNITS",
    "LENGTH_UNITS",
    "Measurements",
    "convert_ipa",
    "read_ipa",
    "read_measurements",
    "write_measurements",
]
