"""The conventions contract: normal gravity and the exact triad error model."""

import numpy as np
import pytest

from estimators.conventions import (
    EARTH_RATE_RPS,
    PARAM_AXIS,
    PARAM_CAUSE,
    PARAM_NAMES,
    Cause,
    Triad,
    nine_params,
    normal_gravity_mps2,
    reference_magnitude,
    sensor_axes,
    triad_matrix,
)


@pytest.mark.parametrize(
    ("lat_deg", "expected_mps2"),
    # Equator and pole are WGS-84's defining γe and γp; at 45° GRS80 tables give
    # 9.8061992, and WGS-84's γe is 1.44e-6 m/s² lower, so 9.8061978.
    [(0.0, 9.7803253359), (90.0, 9.8321849379), (45.0, 9.8061978)],
)
def test_normal_gravity_on_the_ellipsoid_matches_wgs84(lat_deg, expected_mps2):
    assert normal_gravity_mps2(lat_deg, 0.0) == pytest.approx(expected_mps2, abs=2e-7)


def test_free_air_gradient_is_about_3_086e_6_per_metre():
    g0 = normal_gravity_mps2(45.0, 0.0)
    g1 = normal_gravity_mps2(45.0, 1000.0)
    assert (g0 - g1) / 1000.0 == pytest.approx(3.086e-6, rel=2e-3)


def test_guangzhou_gravity_is_the_value_m4_used():
    # methods.md M4: the tests used 9.788 m/s² at Guangzhou (23.13° N, ~20 m).
    assert normal_gravity_mps2(23.13, 20.0) == pytest.approx(9.788, abs=1e-3)


@pytest.mark.parametrize(("lat", "h"), [(91.0, 0.0), (np.nan, 0.0), (0.0, 2e5)])
def test_normal_gravity_rejects_impossible_places(lat, h):
    with pytest.raises(ValueError, match="must be within"):
        normal_gravity_mps2(lat, h)


def test_reference_is_g_for_accelerometers_and_earth_rate_for_gyros():
    assert reference_magnitude(Triad.ACCEL, 9.81) == 9.81
    assert reference_magnitude(Triad.GYRO, 9.81) == EARTH_RATE_RPS


def test_parameter_tables_name_axis_and_cause_of_each_predicate():
    assert len(PARAM_NAMES) == len(PARAM_AXIS) == len(PARAM_CAUSE) == 9
    assert PARAM_CAUSE[0] is Cause.ZERO_SIGNAL and PARAM_CAUSE[4] is Cause.SCALE_FACTOR
    assert PARAM_AXIS[6:] == ("xy", "xz", "yz")


def test_nonorthogonality_cosines_are_the_papers_differences_to_first_order():
    rng = np.random.default_rng(1)
    angles = rng.normal(0.0, 1e-3, 6)  # δ_xy, δ_xz, δ_yx, δ_yz, δ_zx, δ_zy
    d_xy, d_xz, d_yx, d_yz, d_zx, d_zy = angles
    d = nine_params(np.zeros(3), np.zeros(3), sensor_axes(angles))[6:]
    first_order = np.array([d_xz - d_yz, d_zy - d_xy, d_yx - d_zx])
    # The neglected terms are products of two angles: ~1e-6 here.
    np.testing.assert_allclose(d, first_order, atol=5e-6)


def test_scalar_equation_is_the_first_order_expansion_of_the_exact_model():
    rng = np.random.default_rng(2)
    b = rng.normal(0, 1e-3, 3)
    e = rng.normal(0, 1e-3, 3)
    axes = sensor_axes(rng.normal(0, 1e-3, 6))
    theta = nine_params(b, e, axes)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a = u @ triad_matrix(e, axes).T + b
    lhs = 0.5 * (np.sum(a * a, axis=1) - 1.0)
    h = np.column_stack([u, u**2, u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2]])
    # Second-order terms in parameters of size 1e-3: residual of order 1e-5.
    np.testing.assert_allclose(lhs, h @ theta, atol=3e-5)
