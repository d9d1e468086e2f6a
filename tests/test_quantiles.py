"""The median and quantiles that spare ``numpy.ma`` are numpy's, bit for bit (numpy the oracle)."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest

from estimators.quantiles import median, percentile, quantile


def _samples(rng: np.random.Generator):
    """Arrays of 1-2 axes, odd and even lengths, scales from 1e-5 to 1e4, some whole numbers
    (ties), some with a NaN or an infinity."""
    for _ in range(400):
        shape = tuple(int(k) for k in rng.integers(1, 8, size=rng.integers(1, 3)))
        a = rng.normal(size=shape) * 10.0 ** rng.integers(-5, 5)
        if rng.random() < 0.3:
            a = np.round(a)
        if rng.random() < 0.15:
            a.flat[rng.integers(a.size)] = np.nan
        if rng.random() < 0.15:
            a.flat[rng.integers(a.size)] = np.inf
        yield a
    yield rng.normal(size=9_999)


def _same(ours, numpy_s) -> bool:
    return np.shape(ours) == np.shape(numpy_s) and np.array_equal(
        ours, np.asarray(numpy_s), equal_nan=True
    )


def test_median_is_numpy_s_on_every_axis():
    for a in _samples(np.random.default_rng(7)):
        for axis in (None, *range(a.ndim)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # inf - inf of numpy's own
                assert _same(median(a, axis=axis), np.median(a, axis=axis)), (a, axis)


def test_quantile_and_percentile_are_numpy_s_linear_ones():
    rng = np.random.default_rng(8)
    for a in _samples(rng):
        for q in (0.0, 1.0, 0.25, 0.995, float(rng.random()), [0.5, 0.995], rng.random(3)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                assert _same(quantile(a, q), np.quantile(a, q)), (a, q)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            assert _same(percentile(a, [50.0, 99.5]), np.percentile(a, [50.0, 99.5])), a


def test_a_q_outside_the_unit_interval_is_refused_as_numpy_refuses_it():
    with pytest.raises(ValueError, match="Quantiles must be in the range"):
        quantile([1.0, 2.0], 1.5)


def test_they_import_no_numpy_ma():
    probe = (
        "import sys; from estimators.quantiles import median, quantile, percentile; "
        "median([[1.0, 2.0], [3.0, 4.0]], axis=0); quantile([1.0, 2.0, 3.0], 0.3); "
        "percentile([1.0, 2.0], [50.0, 99.5]); print('numpy.ma' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_a_nan_among_the_values_is_returned_with_its_own_bits_as_numpy_returns_it():
    # numpy copies the NaN its partition puts last (sign and payload kept); inf - inf on x86
    # is such a NaN, with the sign bit set.
    nan = np.copysign(np.nan, -1.0)
    for a in ([1.0, nan, 2.0], [[nan, 1.0], [2.0, 3.0], [4.0, 5.0]], [3.0, nan]):
        a = np.asarray(a)
        for axis in (None, *range(a.ndim)):
            assert median(a, axis=axis).tobytes() == np.asarray(np.median(a, axis=axis)).tobytes()
        for q in (0.0, 0.3, 1.0, [0.5, 0.995]):
            assert quantile(a, q).tobytes() == np.asarray(np.quantile(a, q)).tobytes(), (a, q)
