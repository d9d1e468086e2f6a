"""Matplotlib for the commands' figures: the Agg backend (no display) and one way to write a PNG."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.figure import Figure


def save_figure(fig: Figure, path: Path, *, dpi: int) -> None:
    """Lay out, write ``path`` (PNG) and release the figure (pyplot keeps every open one)."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
