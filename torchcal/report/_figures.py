"""Matplotlib for the report's figures: the headless backend, imported only when a figure is drawn, and saving."""

from __future__ import annotations

from pathlib import Path


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (no display needed; imported late: matplotlib is slow to load)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: Path, dpi: int = 110, *, tight: bool = True) -> None:
    """Write ``fig`` to ``path`` at ``dpi`` (after a tight layout unless ``tight`` is False) and close it."""
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
