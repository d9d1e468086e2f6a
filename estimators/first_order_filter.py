"""A first-order recursive filter, scipy.signal.lfilter's numbers without scipy.signal's import.

``lfilter([b0], [1, a1], x, axis=0, zi=zi)`` computes, column by column, the difference
equations its documentation states (direct form II transposed, ``b`` padded to ``[b0, 0]``)::

    y[0] = zi + b0·x[0]
    y[n] = z[n−1] + b0·x[n],    z[n] = 0·x[n] − a1·y[n]

i.e. ``y[n] + a1·y[n−1] = u[n]``, ``u[n] = b0·x[n]`` and ``zi`` added to ``u[0]``: a lower
bidiagonal system with a unit diagonal. LAPACK's ``dgtsv`` (:mod:`scipy.linalg.lapack`) solves
it by elimination without interchanges (``|1| ≥ |a1|``) and then a back-substitution by the unit
diagonal; its elimination step ``y[n] = u[n] − a1·y[n−1]`` rounds as lfilter's does, so the
outputs are lfilter's to the bit (``tests/test_first_order_filter.py`` checks it, lfilter the
oracle). The back-substitution subtracts ``0·y[n+1]``: it changes no finite value, but turns a
zero output ``−0.0`` followed by a negative one into ``+0.0``; and an overflow would reach back
through ``0·inf``, so outputs that are not all finite are refused.

Why: importing scipy.signal costs 0.46 s of CPU at every start (0.05 s where scipy.stats and
scipy.linalg are already loaded, as replay's pipeline had them through filterpy); scipy.linalg costs
0.11 s alone, imported at the first call. The solve takes about twice lfilter's time (9 ns a
sample and column against 5). Applies to ``|a1| ≤ 1`` (every low-pass ``y = α·x + (1 − α)·y₋₁``).
Used by the log health figures (:mod:`estimators.log_health`) and the thrust-axis check's
averages (:mod:`estimators.thrust_gnss`).
"""

from __future__ import annotations

import numpy as np

from estimators._typing import FloatArray


def first_order_filter(
    b0: float, a1: float, x: FloatArray, zi: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``lfilter([b0], [1.0, a1], x, axis=0, zi=zi)``: ``x`` (N, ...) with N ≥ 1, ``zi`` of shape
    (1, ...) (the state, lfilter's); returns the output (N, ...) and the final state, for the
    next call's ``zi``. Raises ``ValueError`` for ``|a1| > 1`` or an output that is not finite."""
    if not abs(a1) <= 1.0:
        raise ValueError(f"first_order_filter needs |a1| ≤ 1 (no interchanges), got {a1!r}")
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[0]
    if n == 0:
        raise ValueError("first_order_filter needs one sample at least, got none")
    u = (b0 * x).reshape(n, -1)
    u[0] += np.asarray(zi, dtype=np.float64).reshape(-1)
    y: FloatArray = u
    info = 0
    if n > 1:  # one sample is its first right-hand side (LAPACK takes no empty diagonal)
        # Imported where it is used: a module importing this one does not pay for scipy.linalg.
        from scipy.linalg.lapack import dgtsv

        _, _, _, y, info = dgtsv(
            np.full(n - 1, a1), np.ones(n), np.zeros(n - 1), u, overwrite_b=True
        )
    if info != 0 or not np.isfinite(y).all():
        raise ValueError(
            "first_order_filter: an output is not finite (an input is not, or is so large that "
            "the recursion overflowed)"
        )
    out: FloatArray = y.reshape(x.shape)
    # lfilter's last delay, z = b1·x − a1·y with its b padded to [b0, 0].
    return out, (0.0 * x[-1] - out[-1] * a1)[None]
