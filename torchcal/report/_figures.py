"""Matplotlib for the report's figures: imported only when a figure is drawn, drawn on the Agg canvas, and saving."""

from __future__ import annotations

import sys
from pathlib import Path

#: the axes titles' height (axes fraction), given so that matplotlib does not place them itself: the automatic
#: placement measures the extent of every tick label above the axes at each draw, a sixth of a report's time, for
#: axes that have none there (where this puts the title anyway)
TITLE_Y = 1.0


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (no display needed; imported late: matplotlib is slow to load)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def subplots(nrows: int = 1, ncols: int = 1, *, figsize=None, layout=None, **kw):
    """A figure and its axes, as ``pyplot.subplots`` returns them, without pyplot.

    The figure belongs to no figure manager (nothing to close, no global state) and is saved through the
    Agg canvas, whatever backend pyplot would pick; pyplot's own import is not paid.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout=layout)
    return fig, fig.subplots(nrows, ncols, **kw)


def save(fig, path: Path, dpi: int = 110, *, tight: bool = True, margins: dict | None = None) -> None:
    """Write ``fig`` to ``path`` at ``dpi`` and release it.

    ``margins``: the subplot parameters (``left``, ``right``, ``bottom``, ``top``, ``wspace``, ``hspace``; figure
    fractions) for a figure whose size and labels are fixed; a tight layout measures every label's extent first and
    cost a quarter of a report's time. Without them, a tight layout unless ``tight`` is False.
    """
    if margins is not None:
        fig.subplots_adjust(**margins)
    elif tight:
        fig.tight_layout()
    # the lowest zlib level: lossless all the same, a quarter of a figure's time, files 10-15 % larger
    fig.savefig(path, dpi=dpi, pil_kwargs={"compress_level": 1})
    if "matplotlib.pyplot" in sys.modules:  # a figure of pyplot's (ours are not, then this does nothing)
        sys.modules["matplotlib.pyplot"].close(fig)
