"""Constant-level segments of one channel: tilt-table angles (M2), rate-table steps (M4).

The static detector finds intervals where the whole unit is at rest; a bench
test needs something else: the intervals where *one* channel holds a level
(the tilted axis between two settings of the table, a gyro while the rate
table turns at a constant rate). A sample belongs to a plateau when the means
of the ``window_s`` before it and after it differ by less than half of
``min_step``, the smallest level change the protocol makes; a plateau is a run
of such samples lasting at least ``min_duration_s``, trimmed by ``trim_s`` at
both ends so the averages exclude the settling of the table. Where the noise
allows, the test is tighter than half a step: six standard deviations of the
difference of two window means (but not under a tenth of a step, for
quantized channels with little noise), with the noise taken from the median
absolute first difference (robust to the steps themselves), so the slow start
of a turn is not averaged into the level.
"""

from __future__ import annotations

import numpy as np

from estimators._typing import FloatArray


def find_plateaus(
    t_s: FloatArray,
    x: FloatArray,
    *,
    min_step: float,
    window_s: float = 1.0,
    min_duration_s: float = 5.0,
    trim_s: float = 0.5,
) -> list[slice]:
    """Index slices of the constant-level segments of ``x``, in time order.

    Parameters
    ----------
    t_s : (N,) sample times, s, increasing.
    x : (N,) the channel, any unit.
    min_step : smallest level change between two consecutive plateaus, unit of ``x``.
    window_s : length of the means compared on either side of a sample, s.
    min_duration_s : shortest plateau kept, s (after trimming).
    trim_s : time dropped at each end of a plateau, s.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(x, dtype=float)
    if t.ndim != 1 or v.shape != t.shape or t.size < 2:
        raise ValueError(
            f"need matching (N,) times and values with N >= 2, got {t.shape} and {v.shape}"
        )
    if not min_step > 0:
        raise ValueError(f"min_step must be positive, got {min_step!r}")
    dt = float(np.median(np.diff(t)))
    w = max(1, round(window_s / dt))
    if t.size < 2 * w:
        return []
    c = np.concatenate([[0.0], np.cumsum(v)])
    # before[k]: mean of x[k-w:k]; after[k]: mean of x[k:k+w], for k = w … N−w.
    k = np.arange(w, t.size - w + 1)
    before = (c[k] - c[k - w]) / w
    after = (c[k + w] - c[k]) / w
    d1 = np.diff(v)
    sigma = 1.4826 * float(np.median(np.abs(d1 - np.median(d1)))) / np.sqrt(2.0)
    threshold = min(0.5 * min_step, max(6.0 * sigma * np.sqrt(2.0 / w), 0.1 * min_step))
    steady = np.zeros(t.size, dtype=bool)
    steady[k] = np.abs(after - before) <= threshold
    edges = np.diff(np.concatenate([[0], steady.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    out = []
    for a, b in zip(starts, stops, strict=True):
        t_lo, t_hi = t[a] + trim_s, t[b - 1] - trim_s
        if t_hi - t_lo < min_duration_s:
            continue
        lo2 = int(np.searchsorted(t, t_lo, side="left"))
        hi2 = int(np.searchsorted(t, t_hi, side="right"))
        out.append(slice(lo2, hi2))
    return out
