"""Session validation: unusable samples are counted and removed, never silently."""

import numpy as np
import pytest

from estimators.session import (
    ACCEL_IMPLAUSIBLE_MPS2,
    GYRO_IMPLAUSIBLE_RPS,
    ImuSession,
    SessionError,
    all_usable,
    finite_rows,
    plausible_rows,
    validate_session,
)


def _session(n=10):
    t = np.arange(n) * 0.01
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    gyr = np.zeros((n, 3))
    return ImuSession(t, acc, gyr, np.full(n, 20.0))


def test_clean_session_passes_unchanged():
    s = _session()
    out, rej = validate_session(s)
    assert rej.total == 0
    np.testing.assert_array_equal(out.t_s, s.t_s)


def test_each_reason_is_counted():
    s = _session(10)
    s.accel_mps2[2, 1] = np.nan
    s.gyro_rps[3, 0] = np.inf
    s.t_s[5] = s.t_s[4]  # duplicate stamp
    s.t_s[7] = s.t_s[1]  # step back
    s.accel_mps2[8, 2] = 160.0  # at full scale
    out, rej = validate_session(s, accel_limit_mps2=156.0)
    assert rej.counts == {"non_finite": 2, "non_monotonic_time": 2, "saturated_accel": 1}
    assert out.n_samples == 5
    assert np.all(np.diff(out.t_s) > 0)


def test_wrong_shape_is_an_error_naming_the_array():
    s = _session()
    bad = ImuSession(s.t_s, s.accel_mps2[:, :2], s.gyro_rps)
    with pytest.raises(SessionError, match=r"accel_mps2 must have shape \(10, 3\)"):
        validate_session(bad)


def test_empty_or_all_bad_session_is_an_error():
    with pytest.raises(SessionError, match="non-empty"):
        validate_session(ImuSession(np.array([]), np.zeros((0, 3)), None))
    s = _session(3)
    s.accel_mps2[:] = np.nan
    with pytest.raises(SessionError, match="no usable samples"):
        validate_session(s)


def test_a_session_needs_a_triad():
    with pytest.raises(SessionError, match="neither"):
        validate_session(ImuSession(np.arange(3.0), None, None))


@pytest.mark.parametrize(
    ("field", "value", "usable"),
    [
        (None, None, True),
        ("t", np.nan, False),
        ("accel", np.nan, False),
        ("accel", -np.inf, False),
        ("accel", ACCEL_IMPLAUSIBLE_MPS2, True),
        ("accel", -np.nextafter(ACCEL_IMPLAUSIBLE_MPS2, np.inf), False),
        ("gyro", np.nan, False),
        ("gyro", -GYRO_IMPLAUSIBLE_RPS, True),
        ("gyro", np.nextafter(GYRO_IMPLAUSIBLE_RPS, np.inf), False),
        ("gyro", 1e300, False),
        ("temp", np.inf, False),
    ],
)
def test_all_usable_is_every_row_finite_and_plausible(field, value, usable):
    """A frame joins a replay's group on one reduction per array: it must say what the rows'
    finite and plausible tests say of the frame, a value at the bound kept, one past it or not
    finite in any field refused."""
    s = _session(6)
    temp = np.full(6, 25.0)
    arrays = {"t": s.t_s, "accel": s.accel_mps2, "gyro": s.gyro_rps, "temp": temp}
    if field is not None:
        arrays[field].flat[4] = value
    plausible = plausible_rows(s.accel_mps2, s.gyro_rps)
    for t_c in (temp, None):
        rows = finite_rows(s.t_s, s.accel_mps2, s.gyro_rps, t_c) & plausible
        assert all_usable(s.t_s, s.accel_mps2, s.gyro_rps, t_c) == bool(rows.all())
    assert all_usable(s.t_s, s.accel_mps2, s.gyro_rps, temp) == usable
