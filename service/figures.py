"""Matplotlib for the commands' figures, without pyplot: one way to make a figure and one to write a PNG.

A :class:`~matplotlib.figure.Figure` made directly is drawn by the Agg canvas when saved as PNG
(no display, no backend to choose) and freed with its last reference: pyplot's registry of open
figures, which had to be closed, and its import are not needed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatter, NullLocator, ScalarFormatter


def subplots(
    nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float], **kwargs: Any
) -> tuple[Figure, Any]:
    """A figure of ``figsize`` inches and its axes, as ``pyplot.subplots`` gives them (``kwargs``
    to :meth:`Figure.subplots`: ``sharex``, ``squeeze``, ...)."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(nrows, ncols, **kwargs)


@dataclass(frozen=True)
class Margins:
    """Space around and between a figure's rows of axes, inches: set where the labels are known, in
    place of ``tight_layout``'s measuring every tick label's text (0.05 s of CPU a figure)."""

    left: float = 0.9
    right: float = 0.3
    bottom: float = 0.6
    top: float = 0.25
    between: float = 0.3


def save_figure(fig: Figure, path: Path, *, dpi: int, margins: Margins | None = None) -> None:
    """Lay the axes out in ``margins`` (None: by ``tight_layout``) and write ``path`` (PNG)."""
    if margins is None:
        fig.tight_layout()
    else:
        width, height = fig.get_size_inches()
        grid = fig.axes[0].get_gridspec()
        if grid is None:
            raise ValueError("save_figure: margins need axes on a grid, as subplots makes them")
        rows = grid.nrows
        for ax in fig.axes:
            if isinstance(ax.yaxis.get_major_formatter(), ScalarFormatter):
                # Six characters at most (the margins are set for them): 1.25 and ×1e−4 above the
                # axis, not 0.000125; −8 and ×1e5, not −800000 (matplotlib's default keeps 1e−5
                # to 1e6 written out).
                ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 5))
        tall = height - margins.top - margins.bottom
        each = (tall - (rows - 1) * margins.between) / rows
        fig.subplots_adjust(
            left=margins.left / width,
            right=1.0 - margins.right / width,
            bottom=margins.bottom / height,
            top=1.0 - margins.top / height,
            hspace=margins.between / each,
        )
    fig.savefig(path, dpi=dpi)


def plain_log_labels(ax: Axes) -> None:
    """The log y axis of ``ax`` labelled in plain text (``1e−05``), at the ticks the default labels:
    its ``10⁻⁵`` is mathtext, whose parser is built at the first label (0.07 s of CPU). An axis of
    two decades or more is read from its labelled decades and has no minor ticks (some 40 on a
    spectrum, 0.04 s of CPU to draw); a narrower one keeps them, as they carry its labels. Call it
    after the last ``semilogy``, which sets the defaults again."""
    ax.yaxis.set_major_formatter(LogFormatter())
    low, high = ax.get_ylim()
    if high >= 100.0 * low:
        ax.yaxis.set_minor_locator(NullLocator())
    else:
        ax.yaxis.set_minor_formatter(LogFormatter())
