"""Medians and quantiles as numpy computes them, without the import of ``numpy.ma`` they cost.

``np.median`` of floats looks for a NaN through ``np.ma.isMaskedArray``, and ``np.quantile``
and ``np.percentile`` choose their partition's indices with ``np.unique``, which asks
``np.ma.is_masked``: the first call imports ``numpy.ma`` (about 5 ms of CPU, a twentieth of
``ins-health calibrate``'s own work on a six-position session:
``benchmarks/bench_sixpos_calibrate.py``). These are numpy's own definitions
(``numpy.lib._function_base_impl``: ``_median``; ``_quantile`` with its default ``linear``
method, Hyndman & Fan's 7th, and ``_lerp``): the order statistics found by ``np.partition``,
their mean or their linear interpolation formed as numpy forms it, the values' own NaN where
one is among them. They give numpy's values bit for bit (``tests/test_quantiles.py``, numpy as the
oracle) for float64 values, as every caller has: others are cast to float64 first, where
numpy works in float32's, float16's or long double's own arithmetic or keeps a mask.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import FloatArray


def median(values: ArrayLike, axis: int | None = None) -> FloatArray:
    """``np.median(values, axis=axis)`` (a 0-d array for ``axis=None``)."""
    a = np.asarray(values, dtype=float)
    if axis is None:
        a, axis = a.ravel(), 0
    n = a.shape[axis]
    if n == 0:
        # numpy's NaN and its "Mean of empty slice" warning.
        return np.asarray(np.median(a, axis=axis))
    half = n // 2
    kth = [half - 1, half] if n % 2 == 0 else [half]
    # numpy's partition, the last place among its kth: a NaN sorts there, and numpy returns
    # that NaN itself (its sign and payload), not a NaN of its own.
    part = np.partition(a, [*kth, -1], axis=axis)
    # The mean of one or two values as np.mean forms it: their sum over their count.
    mean = np.add.reduce(np.take(part, kth, axis=axis), axis=axis) / len(kth)
    last: FloatArray = np.take(part, -1, axis=axis)
    return np.where(np.isnan(last), last, mean)


def quantile(values: ArrayLike, q: ArrayLike) -> FloatArray:
    """``np.quantile(values, q)`` of all the values, ``q`` in [0, 1] (a 0-d array for a scalar ``q``)."""
    a = np.asarray(values, dtype=float).ravel()
    qs = np.asarray(q, dtype=float)
    n = a.size
    if n == 0 or not np.all((qs >= 0.0) & (qs <= 1.0)):
        # numpy's answer to no values, and its error for a q outside [0, 1].
        return np.asarray(np.quantile(a, qs))
    virtual = (n - 1) * qs
    # At the top the largest value alone, as numpy takes it (index -1 for both neighbours).
    top = virtual >= n - 1
    previous = np.where(top, -1.0, np.floor(virtual))
    following = np.where(top, -1.0, previous + 1.0)
    lo, hi = previous.astype(np.intp), following.astype(np.intp)
    # numpy's kth (np.unique of 0, -1 and the neighbours): the same partition, whose last
    # place holds the NaN numpy returns.
    part = np.partition(a, sorted({0, -1, *lo.ravel().tolist(), *hi.ravel().tolist()}))
    below, above = part[lo], part[hi]
    gamma = virtual - previous
    step = above - below
    # From the nearer neighbour, as numpy's _lerp forms it.
    between = np.where(gamma >= 0.5, above - step * (1.0 - gamma), below + step * gamma)
    return np.where(np.isnan(part[-1]), part[-1], between)


def percentile(values: ArrayLike, q: ArrayLike) -> FloatArray:
    """``np.percentile(values, q)`` of all the values, ``q`` in [0, 100]: :func:`quantile` of ``q / 100``."""
    return quantile(values, np.true_divide(q, 100))
