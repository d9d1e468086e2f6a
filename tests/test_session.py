"""Session validation: unusable samples are counted and removed, never silently."""

import numpy as np
import pytest

from estimators.session import ImuSession, SessionError, validate_session


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
