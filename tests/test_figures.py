"""service.figures: figures laid out in fixed margins keep their labels on the canvas."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from service.figures import Margins, save_figure, subplots


@pytest.mark.parametrize("top", [0.02, -0.025, 3.0, 700.0, 1.2345e-4, -9e5])
def test_a_linear_axis_labels_stay_on_the_canvas_at_any_scale(tmp_path, top):
    """The margins hold tick labels of six characters (the report's plots): a gyro
    difference of 1e-4 rad/s was labelled 0.000125 and a CUSUM of -9e5 σ −800000, and their axis
    labels were cut at the figure's left edge."""
    fig, axes = subplots(2, 1, figsize=(8, 5), sharex=True)
    for ax in axes:
        ax.plot(np.linspace(0.0, 2000.0, 50), np.linspace(0.0, top, 50))
        ax.set_ylabel("|Δω|, rad/s")
    axes[1].set_xlabel("time from the log's start, s")
    save_figure(fig, tmp_path / "f.png", dpi=90, margins=Margins())
    renderer = FigureCanvasAgg(fig).get_renderer()
    boxes = [ax.get_tightbbox(renderer) for ax in axes]
    assert min(b.x0 for b in boxes) >= 0.0 and max(b.y1 for b in boxes) <= fig.bbox.height, boxes
