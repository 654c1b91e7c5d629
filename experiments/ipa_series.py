"""The UR10 series of Landgraf et al. (IPA) as the real-data experiments read them."""

from __future__ import annotations

from pathlib import Path

import torch

from torchcal.data import Measurements
from torchcal.errors import MeasurementFileError


def series_file(data_dir: Path, name: str) -> Path:
    """The one ``Series_<name>/measurements_*.csv`` under ``data_dir``."""
    files = sorted((Path(data_dir) / f"Series_{name}").glob("measurements_*.csv"))
    if len(files) != 1:
        raise MeasurementFileError(
            f"expected one Series_{name}/measurements_*.csv under {data_dir}, found {len(files)}"
        )
    return files[0]


def subsample_idx(n: int, rows: int, seed: int) -> torch.Tensor:
    """A seeded random ``rows`` of ``n`` row indices in file order (all of them when ``rows`` is 0 or not smaller)."""
    if rows <= 0 or rows >= n:
        return torch.arange(n)
    return torch.sort(torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:rows]).values


def subsample(m: Measurements, rows: int, seed: int) -> tuple[Measurements, dict | None]:
    """:func:`subsample_idx` applied to ``m``, with a note of what was kept (None when all)."""
    if rows <= 0 or rows >= m.n:
        return m, None
    return m.subset(subsample_idx(m.n, rows, seed)), {"rows": rows, "of": m.n, "seed": seed}
