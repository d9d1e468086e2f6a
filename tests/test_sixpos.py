"""M4: six-position accelerometer calibration, g-dependent gyro bias, rate-table scale factor, local gravity."""

import numpy as np
import pytest

from estimators.conventions import STANDARD_GRAVITY_MPS2, normal_gravity_mps2
from estimators.sim import simulate
from estimators.sim.session import earth_rate_n_rps
from estimators.sixpos import (
    GUANGZHOU_HEIGHT_M,
    GUANGZHOU_LATITUDE_DEG,
    SIX_FACES_UP_B,
    accel_truth,
    adis_like_model,
    face_directions,
    find_rate_steps,
    gyro_g_sensitivity,
    gyro_truth,
    paper_rate_profile_rps,
    rate_table_fit,
    rate_table_truth,
    session_positions,
    simulate_rate_table,
    six_position_accel,
    six_position_accel_fitter,
    six_position_spec,
    six_position_test,
)

G_LOCAL = normal_gravity_mps2(GUANGZHOU_LATITUDE_DEG, GUANGZHOU_HEIGHT_M)


def _model_means(values, g, up=SIX_FACES_UP_B):
    """Noise-free means of the paper's eq. 7 for per-axis terms ``values`` (3, 5)."""
    a = g * up
    out = np.zeros_like(a)
    for i in range(3):
        j, k = [m for m in range(3) if m != i]
        b, s, mj, mk, q = values[i]
        out[:, i] = b + (1 + s) * a[:, i] + mj * a[:, j] + mk * a[:, k] + q * a[:, i] ** 2
    return out


TERMS = np.array(
    [
        [0.03, 3e-3, -1e-3, 8e-4, 1.2e-4],
        [-0.05, -4e-3, 6e-4, 1.3e-3, -8e-5],
        [0.08, 5e-3, -9e-4, 7e-4, 1.5e-4],
    ]
)


@pytest.mark.parametrize("quadratic", [False, True])
@pytest.mark.parametrize("with_cov", [True, False])
def test_the_fitter_factored_once_gives_each_fit_bit_for_bit(quadratic, with_cov):
    # calibrate's covariance of the six-position fit is a Jacobian by central differences: the
    # means perturbed dozens of times, faces and covariances fixed, the designs factored once.
    # Each fit must be exactly the one six_position_accel makes of those means (the passport's
    # bytes rest on it).
    rng = np.random.default_rng(5)
    up = np.vstack([SIX_FACES_UP_B, SIX_FACES_UP_B[:2]])
    base = _model_means(TERMS, G_LOCAL, up) + 1e-3 * rng.standard_normal(up.shape)
    cov = (
        np.einsum("k,ij->kij", 1e-6 * (1.0 + rng.random(len(up))), np.eye(3)) if with_cov else None
    )
    fit = six_position_accel_fitter(
        up, gravity_mps2=G_LOCAL, accel_cov_mps2=cov, quadratic=quadratic
    )
    for _ in range(6):
        means = base + 1e-4 * rng.standard_normal(base.shape)
        once = six_position_accel(
            means, gravity_mps2=G_LOCAL, accel_cov_mps2=cov, up_b=up, quadratic=quadratic
        )
        factored = fit(means)
        for name in ("bias_mps2", "scale_error", "misalignment", "quad_per_mps2", "cov"):
            assert np.array_equal(getattr(factored, name), getattr(once, name)), name
        assert np.array_equal(factored.residuals_mps2, once.residuals_mps2)


def test_six_exact_positions_give_back_the_terms():
    est = six_position_accel(
        _model_means(TERMS, G_LOCAL),
        gravity_mps2=G_LOCAL,
        accel_cov_mps2=np.tile(np.eye(3) * 1e-10, (6, 1, 1)),
    )
    np.testing.assert_allclose(est.values, TERMS, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(est.residuals_mps2, 0.0, atol=1e-12)


def test_gyro_g_sensitivity_is_the_papers_sum_and_difference():
    # Gyro x reads m1 with the x axis up and m2 with it down: Bf = (m1 + m2)/2, Bgx = (m1 − m2)/(2g).
    bf, bg = (
        np.array([0.01, -0.02, 0.005]),
        np.array([[1e-4, 2e-5, -3e-5], [-2e-5, 3e-4, 1e-5], [4e-5, -1e-5, 2e-4]]),
    )
    w = bf + (G_LOCAL * SIX_FACES_UP_B) @ bg.T
    est = gyro_g_sensitivity(
        w, SIX_FACES_UP_B, gravity_mps2=G_LOCAL, gyro_cov_rps=np.tile(np.eye(3) * 1e-12, (6, 1, 1))
    )
    m1, m2 = w[0, 0], w[1, 0]
    assert est.bias_rps[0] == pytest.approx((m1 + m2) / 2, abs=1e-15)
    assert est.g_sensitivity[0, 0] == pytest.approx((m1 - m2) / (2 * G_LOCAL), rel=1e-12)
    np.testing.assert_allclose(est.g_sensitivity, bg, rtol=1e-9)


def test_stated_uncertainty_holds_in_a_monte_carlo_of_position_means():
    # 400 six-position tests with known noise of the means: normalized errors are N(0, 1).
    rng = np.random.default_rng(1)
    sigma = np.array([2e-4, 3e-4, 1.5e-4])
    clean = _model_means(TERMS, G_LOCAL)
    cov = np.tile(np.diag(sigma**2), (6, 1, 1))
    std = six_position_accel(clean, gravity_mps2=G_LOCAL, accel_cov_mps2=cov).std
    z = np.array(
        [
            (
                six_position_accel(
                    clean + sigma * rng.standard_normal((6, 3)),
                    gravity_mps2=G_LOCAL,
                    accel_cov_mps2=cov,
                ).values
                - TERMS
            )
            / std
            for _ in range(400)
        ]
    )
    # Variance of N(0,1) from 400 draws: sd sqrt(2/399) ≈ 0.07; 95 % coverage: binomial sd 1.1 %.
    assert np.all(np.abs(z.var(axis=0) - 1.0) < 5 * np.sqrt(2 / 399))
    coverage = (np.abs(z) <= 1.96).mean(axis=0)
    assert np.all(np.abs(coverage - 0.95) < 5 * np.sqrt(0.95 * 0.05 / 400))


@pytest.fixture(scope="module")
def simulated_tests():
    """Eight simulated six-position sessions of an ADIS16355-like unit at Guangzhou, through the static detector."""
    model = adis_like_model()
    out = []
    for seed in range(8):
        res = simulate(six_position_spec(model, static_s=20.0), seed)
        positions = session_positions(res.session)
        # The Earth rate each position saw, from the simulated attitudes (the fixture's headings are known).
        er = np.array(
            [
                res.truth.mat_nb[p.index_start].T @ earth_rate_n_rps(GUANGZHOU_LATITUDE_DEG)
                for p in positions
            ]
        )
        out.append((positions, er))
    return model, out


def test_simulated_sessions_recover_every_term_within_the_stated_uncertainty(simulated_tests):
    model, tests = simulated_tests
    acc_true = accel_truth(model)
    bf_true, bg_true = gyro_truth(model)
    z_acc, z_gyr = [], []
    for positions, er in tests:
        assert len(positions) == 6
        res = six_position_test(positions, gravity_mps2=G_LOCAL)
        z_acc.append((res.accel.values - acc_true) / res.accel.std)
        up = face_directions(np.array([p.accel_mean_mps2 for p in positions]))
        gyr = gyro_g_sensitivity(
            np.array([p.gyro_mean_rps for p in positions]),
            up,
            gravity_mps2=G_LOCAL,
            gyro_cov_rps=np.array([p.gyro_cov_rps for p in positions]),
            earth_rate_b_rps=er,
        )
        z_gyr.append(
            (
                np.column_stack([gyr.bias_rps, gyr.g_sensitivity])
                - np.column_stack([bf_true, bg_true])
            )
            / gyr.std
        )
    z = np.concatenate([np.ravel(z_acc), np.ravel(z_gyr)])
    # 216 normalized errors: none beyond 4.5 σ (chance of one: 0.15 %), spread about 1.
    assert np.max(np.abs(z)) < 4.5
    assert 0.75 < z.std() < 1.25


def test_assuming_standard_gravity_shows_up_as_the_scale_error_it_should(simulated_tests):
    _, tests = simulated_tests
    positions, _ = tests[0]
    mean = np.array([p.accel_mean_mps2 for p in positions])
    cov = np.array([p.accel_cov_mps2 for p in positions])
    local = six_position_accel(mean, gravity_mps2=G_LOCAL, accel_cov_mps2=cov)
    standard = six_position_accel(mean, gravity_mps2=STANDARD_GRAVITY_MPS2, accel_cov_mps2=cov)
    # (A↑ − A↓)/2 = (1 + S)·g_true, so assuming g' gives 1 + S' = (1 + S)·g_true/g'.
    expected = (1 + local.scale_error) * G_LOCAL / STANDARD_GRAVITY_MPS2 - 1 - local.scale_error
    np.testing.assert_allclose(standard.scale_error - local.scale_error, expected, atol=1e-12)
    assert np.mean(standard.scale_error - local.scale_error) == pytest.approx(-0.0019, abs=0.0001)
    assert G_LOCAL == pytest.approx(9.788, abs=5e-4)  # the paper's local value


def test_faces_are_recognized_and_missing_ones_named():
    means = G_LOCAL * SIX_FACES_UP_B + 0.01
    np.testing.assert_array_equal(face_directions(means), SIX_FACES_UP_B)
    with pytest.raises(ValueError, match=r"missing: -z up"):
        face_directions(means[:5])
    tilted = means.copy()
    tilted[2] = G_LOCAL * np.array([0.7071, 0.7071, 0.0])
    with pytest.raises(ValueError, match="position 2 is 45° from the nearest axis"):
        face_directions(tilted)
    with pytest.raises(ValueError, match="give the covariances"):
        six_position_accel(means, gravity_mps2=G_LOCAL)


def test_paper_rate_profile():
    deg = np.degrees(paper_rate_profile_rps())
    assert deg.size == 31 and deg[0] == 0 and deg[10] == 200 and deg[-1] == -200
    np.testing.assert_allclose(np.abs(np.diff(deg)), 20.0)


def test_rate_table_recovers_the_scale_factor_within_its_uncertainty():
    model = adis_like_model()
    profile = paper_rate_profile_rps()
    slopes = rate_table_truth(model)
    z = []
    for axis, seed in ((0, 1), (1, 2), (2, 3)):
        session = simulate_rate_table(
            model, axis=axis, profile_rps=profile, hold_s=6.0, gravity_mps2=G_LOCAL, seed=seed
        )
        steps = find_rate_steps(
            session.t_s, session.gyro_rps, axis=axis, profile_rps=profile, min_hold_s=3.0
        )
        fit = rate_table_fit(
            profile, steps.gyro_mean_rps, axis=axis, gyro_var_rps=steps.gyro_var_rps[:, axis]
        )
        z.append((fit.scale_error - (slopes[axis, axis] - 1.0)) / fit.scale_error_std)
        np.testing.assert_allclose(
            fit.cross_coupling[[i for i in range(3) if i != axis]],
            0.0,
            atol=5 * fit.scale_error_std,
        )
        assert fit.nonlinearity < 1e-3
    assert np.max(np.abs(z)) < 4.0


def test_a_rate_record_that_does_not_match_the_profile_says_so():
    model = adis_like_model()
    profile = paper_rate_profile_rps()
    session = simulate_rate_table(
        model, axis=0, profile_rps=profile[:12], hold_s=6.0, gravity_mps2=G_LOCAL, seed=5
    )
    with pytest.raises(ValueError, match=r"found 12 constant-rate steps .* the profile has 31"):
        find_rate_steps(session.t_s, session.gyro_rps, axis=0, profile_rps=profile, min_hold_s=3.0)
    with pytest.raises(ValueError, match="at least 3 different table rates"):
        rate_table_fit(np.array([0.1, 0.1, -0.1]), np.zeros((3, 3)), axis=0)
