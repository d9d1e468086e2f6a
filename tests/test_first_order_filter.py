"""The first-order recursive filter (estimators.first_order_filter) against its oracle, scipy.signal.lfilter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from estimators.first_order_filter import first_order_filter


def _framed(b0, a1, x, zi, cuts):
    """The filter over ``x`` taken in the frames ``cuts`` gives, the state carried between them."""
    out = []
    for part in np.split(x, cuts):
        if part.shape[0]:
            y, zi = first_order_filter(b0, a1, part, zi)
            out.append(y)
    return np.concatenate(out), zi


@pytest.mark.parametrize("columns", [(), (3,)], ids=["one", "three"])
def test_the_outputs_and_final_state_are_lfilter_s_to_the_bit(columns):
    """Random low-passes (α from 1e-4 to 1, the gain of 1 included), inputs from 1e-8 to 1e8, signed
    and squared, a random state, one sample to thousands, cut into random frames: the outputs and the
    final state are lfilter's byte for byte (a rounding apart anywhere would show in most of them)."""
    rng = np.random.default_rng(33)
    for trial in range(200):
        n = int(rng.integers(1, 3000))
        alpha = 1.0 if trial == 0 else float(rng.uniform(1e-4, 1.0))
        b0, a1 = alpha, alpha - 1.0
        x = rng.standard_normal((n, *columns)) * 10.0 ** rng.uniform(-8.0, 8.0)
        if trial % 2:
            x = x**2
        zi = rng.standard_normal((1, *columns)) * np.abs(x).max()
        cuts = np.sort(rng.integers(0, n, int(rng.integers(0, 8))))
        want, want_zf = lfilter([b0], [1.0, a1], x, axis=0, zi=zi)
        got, zf = _framed(b0, a1, x, zi, cuts)
        assert got.shape == want.shape and zf.shape == want_zf.shape
        assert got.tobytes() == want.tobytes(), trial
        assert zf.tobytes() == want_zf.tobytes(), trial


def test_zeros_keep_lfilter_s_signs_but_where_a_negative_output_follows():
    """Exact zeros in and out (a settled filter on a constant 0 or -0): the same bytes, but for the
    sign the back-substitution's ``0·y[n+1]`` gives a zero followed by a negative output (documented)."""
    x = np.array([0.0, -0.0, 0.0, -0.0, -0.0, 0.0])
    for zi in (np.zeros(1), -np.zeros(1)):
        want, want_zf = lfilter([0.25], [1.0, -0.75], x, axis=0, zi=zi)
        got, zf = first_order_filter(0.25, -0.75, x, zi)
        assert got.tobytes() == want.tobytes() and zf.tobytes() == want_zf.tobytes()
    x = np.array([-0.0, -1.0])
    want, _ = lfilter([0.25], [1.0, -0.75], x, axis=0, zi=-np.zeros(1))
    got, _ = first_order_filter(0.25, -0.75, x, -np.zeros(1))
    np.testing.assert_array_equal(got, want)
    assert np.signbit(want[0]) and not np.signbit(got[0])


def test_outputs_that_are_not_finite_and_filters_it_cannot_solve_are_refused():
    """lfilter carries an overflow forward only; the back-substitution would carry it back through
    ``0·inf``: such outputs are refused, as are an empty input and ``|a1| > 1`` (a pivoting solve)."""
    # An integrator (a1 = -1) overflows on the second sample: lfilter gives 1e308, inf, inf.
    with pytest.raises(ValueError, match="not finite"):
        first_order_filter(1.0, -1.0, np.array([1e308, 1e308, 1.0]), np.zeros(1))
    with pytest.raises(ValueError, match="not finite"):
        first_order_filter(0.5, -0.5, np.array([1.0, np.nan, 1.0]), np.zeros(1))
    with pytest.raises(ValueError, match="one sample"):
        first_order_filter(0.5, -0.5, np.zeros(0), np.zeros(1))
    with pytest.raises(ValueError, match=r"\|a1\|"):
        first_order_filter(0.5, -1.5, np.ones(4), np.zeros(1))
