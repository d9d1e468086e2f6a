"""The simulator: exact truth, consistent motion, each effect and fault as documented.

Tolerances come from the noise of what is compared (stated next to each), or
are floating-point round-off where the comparison is exact by construction.
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimators.conventions import EARTH_RATE_RPS, N_PARAMS, Triad
from estimators.noise import gm_mean_variance
from estimators.session import validate_session
from estimators.sim import (
    EFFECTS,
    GRADES,
    Bias,
    BiasDrift,
    BiasInstability,
    ColouredNoise,
    CycleTemperature,
    ErrorModel,
    Fault,
    FaultKind,
    Fly,
    Grade,
    GravityMismatch,
    GSensitivity,
    MotionProfile,
    NonOrthogonality,
    NonstaticPositions,
    OrientationScheme,
    Quantization,
    Rounding,
    ScaleFactor,
    ScaleNonlinearity,
    SessionSpec,
    Spin,
    TemperatureBias,
    TemperatureScale,
    TriadErrorModel,
    WarmupTemperature,
    WhiteNoise,
    effect_params,
    eighteen_position_attitudes,
    flight_spec,
    grade_error_model,
    half_pulse_correction,
    make_effect,
    multi_position_spec,
    simulate,
    static_spec,
)

NOISE_FREE = ErrorModel()
G_ANGLES = (1e-3, -2e-3, 1.5e-3, 0.5e-3, -1e-3, 2e-3)


def _linear_model(bias_si, scale=(2e-3, -1e-3, 3e-3), angles=G_ANGLES, extra=()):
    return TriadErrorModel(
        (NonOrthogonality(angles), ScaleFactor(scale), Bias(bias_si), *tuple(extra))
    )


def _exact_residual(y, ref, params):
    """``(ã − b)ᵀ (A Aᵀ)⁻¹ (ã − b) − 1`` per sample from the nine parameters (conventions.py)."""
    b, e, d = params[:3], params[3:6], params[6:]
    gram = np.array([[1.0, d[0], d[1]], [d[0], 1.0, d[2]], [d[1], d[2], 1.0]])
    aat = (1 + e)[:, None] * gram * (1 + e)[None, :]
    z = y / ref - b
    return np.einsum("ni,ni->n", z, np.linalg.solve(aat, z.T).T) - 1.0


def _short_mp(model, **kw):
    kw.setdefault("static_s", 5.0)
    kw.setdefault("transition_s", 2.0)
    return multi_position_spec(model=model, **kw)


# --- determinism ----------------------------------------------------------------


def test_same_seed_gives_identical_arrays_and_another_seed_does_not():
    spec = multi_position_spec(
        grade=Grade.MEMS,
        static_s=5.0,
        faults=(Fault(FaultKind.NOISE_BURST, Triad.GYRO, 1, 30.0, 0.01, 5.0),),
    )
    a, b, c = simulate(spec, 11), simulate(spec, 11), simulate(spec, 12)
    for name in ("t_s", "accel_mps2", "gyro_rps"):
        np.testing.assert_array_equal(getattr(a.session, name), getattr(b.session, name))
    np.testing.assert_array_equal(a.truth.mat_nb, b.truth.mat_nb)
    assert not np.array_equal(a.session.accel_mps2, c.session.accel_mps2)
    g1, g2 = np.random.default_rng(5), np.random.default_rng(5)
    np.testing.assert_array_equal(
        simulate(spec, g1).session.gyro_rps, simulate(spec, g2).session.gyro_rps
    )


def test_adding_an_effect_leaves_the_other_noise_streams_unchanged():
    base = ErrorModel(accel=TriadErrorModel((WhiteNoise((1e-3,) * 3),)))
    more = base.with_effect(BiasDrift([[1e-4], [0.0], [0.0]]), Triad.ACCEL)
    spec = static_spec(duration_s=10.0, model=base)
    a = simulate(spec, 3).session.accel_mps2
    b = simulate(static_spec(duration_s=10.0, model=more), 3).session.accel_mps2
    t = np.arange(a.shape[0]) / 100.0
    np.testing.assert_allclose(b[:, 0] - a[:, 0], 1e-4 * t, atol=1e-15)
    np.testing.assert_array_equal(b[:, 1:], a[:, 1:])


def test_bad_seed_is_rejected():
    with pytest.raises(ValueError, match="seed"):
        simulate(static_spec(duration_s=1.0), -1)


# --- truth ----------------------------------------------------------------------


def test_static_truth_is_gravity_up_and_earth_rate():
    lat = 50.0
    res = simulate(_short_mp(NOISE_FREE, latitude_deg=lat), 0)
    tr = res.truth
    st = tr.static
    assert st.sum() > 0.5 * st.size
    # The up axis reads +g (conventions.py) and the gyro sees Ω projected.
    up_b = tr.mat_nb[st][:, 2, :]
    np.testing.assert_allclose(
        tr.specific_force_b_mps2[st], tr.gravity_true_mps2 * up_b, atol=1e-12
    )
    np.testing.assert_allclose(
        np.linalg.norm(res.session.gyro_rps[st], axis=1), EARTH_RATE_RPS, rtol=1e-12
    )
    omega_n = EARTH_RATE_RPS * np.array(
        [0.0, math.cos(math.radians(lat)), math.sin(math.radians(lat))]
    )
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", tr.mat_nb[st], res.session.gyro_rps[st]),
        np.tile(omega_n, (st.sum(), 1)),
        atol=1e-18,
    )
    np.testing.assert_allclose(
        np.linalg.norm(res.session.accel_mps2[st], axis=1), tr.gravity_true_mps2, rtol=1e-14
    )


def test_static_specific_force_magnitude_is_g_within_noise():
    sd = 0.01
    model = ErrorModel(accel=TriadErrorModel((WhiteNoise.from_sample_sd(sd, 100.0),)))
    res = simulate(_short_mp(model, static_s=10.0), 4)
    tr = res.truth
    for j in range(len(tr.static_intervals_s)):
        m = tr.position_index == j
        mean = res.session.accel_mps2[m].mean(axis=0)
        # |mean| − g is the noise of the mean along the gravity direction: sd/√n.
        assert abs(np.linalg.norm(mean) - tr.gravity_true_mps2) < 5.0 * sd / math.sqrt(m.sum())


def test_nine_params_of_the_truth_are_exact():
    """Noise-free static outputs lie exactly on the ellipsoid that the truth's nine parameters define."""
    model = ErrorModel(
        accel=_linear_model((0.03, -0.02, 0.05)), gyro=_linear_model((2e-6, -1e-6, 3e-6))
    )
    res = simulate(_short_mp(model), 1)
    tr, st = res.truth, res.truth.static
    assert (
        np.abs(
            _exact_residual(res.session.accel_mps2[st], tr.gravity_true_mps2, tr.accel_params)
        ).max()
        < 1e-12
    )
    assert (
        np.abs(_exact_residual(res.session.gyro_rps[st], EARTH_RATE_RPS, tr.gyro_params)).max()
        < 1e-10
    )
    # Perturbing any one parameter breaks the relation by far more than round-off.
    for j in range(N_PARAMS):
        p = tr.accel_params.copy()
        p[j] += 1e-4
        assert (
            np.abs(_exact_residual(res.session.accel_mps2[st], tr.gravity_true_mps2, p)).max()
            > 1e-6
        )


def _integrate(tr):
    """Attitude from the body rates with the trapezoid rotation vector (second-order accurate)."""
    dt = np.diff(tr.t_s)[:, None]
    inc = Rotation.from_rotvec(
        0.5 * (tr.rate_nb_b_rps[:-1] + tr.rate_nb_b_rps[1:]) * dt
    ).as_matrix()
    out = np.empty_like(tr.mat_nb)
    out[0] = tr.mat_nb[0]
    for k in range(inc.shape[0]):
        out[k + 1] = out[k] @ inc[k]
    return Rotation.from_matrix(np.swapaxes(out, 1, 2) @ tr.mat_nb).magnitude().max()


@pytest.mark.parametrize(
    "make",
    [
        lambda rate: _short_mp(
            NOISE_FREE.with_effect(NonstaticPositions(angle_rms_rad=1e-3)),
            rate_hz=rate,
            static_s=4.0,
        ),
        lambda rate: flight_spec(
            model=NOISE_FREE, fly=Fly(40.0, vibration_rad=0.0), rest_s=2.0, rate_hz=rate
        ),
    ],
    ids=["multiposition_with_wobble", "flight"],
)
def test_integrated_body_rates_reproduce_the_attitude(make):
    # A consistent rate integrates to the attitude with the integrator's O(dt²)
    # error: small, and four times smaller at twice the rate. An inconsistent
    # rate would leave an error that does not shrink with dt.
    e100 = _integrate(simulate(make(100.0), 2).truth)
    e200 = _integrate(simulate(make(200.0), 2).truth)
    assert e100 < 5e-4
    assert 3.0 < e100 / e200 < 5.0


def test_flight_moves_and_ends_at_rest_where_it_started():
    res = simulate(flight_spec(model=NOISE_FREE, fly=Fly(30.0), rest_s=2.0), 8)
    tr = res.truth
    moving = ~tr.static
    assert np.abs(tr.rate_nb_b_rps[moving]).max() > 0.1
    assert (
        np.abs(
            np.linalg.norm(tr.specific_force_b_mps2[moving], axis=1) - tr.gravity_true_mps2
        ).max()
        > 0.5
    )
    np.testing.assert_allclose(tr.mat_nb[-1], tr.mat_nb[0], atol=1e-12)
    assert len(tr.static_intervals_s) == 2


def test_a_spin_turns_at_its_rate_about_its_axis():
    # A rate linear in time about a fixed axis makes the trapezoid rotation
    # vector exact: integrating the rate reproduces the attitude to round-off
    # (a rate inconsistent with the attitude would leave a visible angle).
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    segments = (
        Spin(2.0, 0.0, axis, end_rate_rps=1.5),
        Spin(4.0, 1.5, axis),
        Spin(2.0, 1.5, axis, end_rate_rps=-0.5),
    )
    tr = simulate(
        SessionSpec(MotionProfile(np.eye(3), segments), NOISE_FREE, rate_hz=100.0), 0
    ).truth
    assert _integrate(tr) < 1e-9
    np.testing.assert_allclose(
        tr.rate_nb_b_rps, np.outer(tr.rate_nb_b_rps @ axis, axis), atol=1e-15
    )
    np.testing.assert_allclose(tr.rate_nb_b_rps[200:600] @ axis, 1.5, rtol=1e-15)
    # Angle at the last sample (τ = 1.99 s into the last ramp): 1.5 + 6 + 1.5·1.99 − 1.99²/2 rad.
    angle = 7.5 + 1.5 * 1.99 - 0.5 * 1.99**2
    np.testing.assert_allclose(
        tr.mat_nb[-1], Rotation.from_rotvec(angle * axis).as_matrix(), atol=1e-12
    )
    assert not tr.static.any()
    with pytest.raises(ValueError, match="axis_b"):
        Spin(1.0, 0.1, (0.0, 0.0, 0.0))


def test_eighteen_positions_span_two_axes_with_hand_sized_turns():
    att = eighteen_position_attitudes(heading_rad=0.3)
    up_b = att[:, 2, :]
    assert len({tuple(np.round(u, 9)) for u in up_b}) == 18
    # Every axis both up and down: the rotations are about more than one axis.
    for i in range(3):
        assert up_b[:, i].max() > 0.99 and up_b[:, i].min() < -0.99
    # Every prefix of nine or more positions is well conditioned for M1's H.
    h = np.column_stack(
        [up_b, up_b**2, up_b[:, 0] * up_b[:, 1], up_b[:, 0] * up_b[:, 2], up_b[:, 1] * up_b[:, 2]]
    )
    assert max(np.linalg.cond(h[:n]) for n in range(9, 19)) < 5.0
    angles = Rotation.from_matrix(np.swapaxes(att[:-1], 1, 2) @ att[1:]).magnitude()
    assert math.pi / 4 - 1e-9 <= angles.min() and angles.max() <= math.pi / 2 + 1e-9
    res = simulate(multi_position_spec(model=NOISE_FREE, static_s=3.0, transition_s=2.0), 0)
    assert res.truth.static_intervals_s.shape == (18, 2)
    np.testing.assert_allclose(np.diff(res.truth.static_intervals_s, axis=1), 2.99, atol=1e-9)


def test_random_orientations_need_a_generator_and_are_seeded():
    with pytest.raises(ValueError, match="Generator"):
        multi_position_spec(n_positions=9, scheme=OrientationScheme.RANDOM)
    a = multi_position_spec(
        n_positions=9, scheme=OrientationScheme.RANDOM, orientation_rng=np.random.default_rng(1)
    )
    b = multi_position_spec(
        n_positions=9, scheme=OrientationScheme.RANDOM, orientation_rng=np.random.default_rng(1)
    )
    assert a.profile == b.profile
    assert len(a.profile.segments) == 17


# --- effects ----------------------------------------------------------------------


def _static_error(
    effects,
    *,
    triad=Triad.ACCEL,
    duration_s=20.0,
    temperature=None,
    rate_hz=100.0,
    seed=0,
    mat_nb=None,
):
    tm = TriadErrorModel(tuple(effects))
    model = ErrorModel(accel=tm) if triad is Triad.ACCEL else ErrorModel(gyro=tm)
    res = simulate(
        static_spec(
            duration_s=duration_s,
            model=model,
            temperature=temperature,
            rate_hz=rate_hz,
            mat_nb=mat_nb,
        ),
        seed,
    )
    tr = res.truth
    y = res.session.accel_mps2 if triad is Triad.ACCEL else res.session.gyro_rps
    x = tr.specific_force_b_mps2 if triad is Triad.ACCEL else tr.rate_ib_b_rps
    return res, y, x


def test_white_noise_has_the_stated_standard_deviation():
    sd = np.array([1e-3, 2e-3, 5e-3])
    _, y, x = _static_error([WhiteNoise.from_sample_sd(sd, 100.0)], duration_s=300.0)
    n = y.shape[0]
    # The sample sd of n normal draws has relative sd 1/√(2n).
    np.testing.assert_allclose((y - x).std(axis=0), sd, rtol=5.0 / math.sqrt(2 * n))


def test_white_and_coloured_noise_carry_the_axes_correlation_and_keep_each_axis_level():
    # x–y correlation −0.4, x–z +0.2 (the Xsens accelerometers' x–y noise correlates at −0.35); one colour term
    # with the same τ on every axis, so its outputs have the drivers' correlation at the same sample.
    corr = np.array([[1.0, -0.4, 0.2], [-0.4, 1.0, 0.0], [0.2, 0.0, 1.0]])
    sd = np.array([1e-3, 2e-3, 5e-3])
    sigma, tau = np.array([[2e-3], [1e-3], [3e-3]]), np.full((3, 1), 0.05)
    for effect, n_eff in (
        (WhiteNoise.from_sample_sd(sd, 100.0, corr), 30_000.0),
        (
            ColouredNoise(sigma, tau, corr),
            30_000.0 / 10.0,
        ),  # independent stretches of 2τ = 10 samples
    ):
        _, y, x = _static_error([effect], duration_s=300.0, seed=5)
        c = y - x
        level = sd if isinstance(effect, WhiteNoise) else sigma[:, 0]
        # A sample correlation has sd (1 − ρ²)/√n, a sample sd a relative sd 1/√(2n): 5 of each.
        np.testing.assert_array_less(
            np.abs(np.corrcoef(c.T) - corr), 5.0 * (1.0 - corr**2) / np.sqrt(n_eff) + 1e-12
        )
        np.testing.assert_allclose(c.std(axis=0), level, rtol=5.0 / np.sqrt(2.0 * n_eff))
    # Without a correlation the generator's draws are used unchanged (seeded sessions stay as they were).
    _, y0, _ = _static_error([WhiteNoise.from_sample_sd(sd, 100.0)], seed=5)
    _, y1, _ = _static_error([WhiteNoise.from_sample_sd(sd, 100.0, np.eye(3))], seed=5)
    np.testing.assert_array_equal(y0, y1)
    with pytest.raises(ValueError, match="positive definite"):
        WhiteNoise(correlation=[[1.0, 0.9, -0.9], [0.9, 1.0, 0.9], [-0.9, 0.9, 1.0]])
    with pytest.raises(ValueError, match="unit diagonal"):
        ColouredNoise(sigma, tau, 2.0 * np.eye(3))


def test_white_noise_density_scales_with_the_rate():
    eff = WhiteNoise((1e-3,) * 3)
    np.testing.assert_allclose(eff.sample_sd(400.0), 2.0 * eff.sample_sd(100.0))


@pytest.mark.parametrize("rounding", list(Rounding))
def test_quantized_output_lies_on_the_grid_and_the_half_pulse_correction_removes_its_offset(
    rounding,
):
    step = 0.01
    sd = 2 * step  # noise above one count makes the rounding error uniform (M2)
    tilted = Rotation.from_rotvec([0.3, -0.5, 0.0]).as_matrix()  # axes read + and − values
    _res, y, x = _static_error(
        [WhiteNoise.from_sample_sd(sd, 100.0), Quantization((step,) * 3, rounding)],
        duration_s=200.0,
        mat_nb=tilted,
    )
    counts = y / step
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-9)
    mean_counts = counts.mean(axis=0)
    n = y.shape[0]
    # Bound: noise and rounding error of the mean, in counts.
    bound = 5.0 * math.sqrt(sd**2 / step**2 + 1 / 12) / math.sqrt(n)
    truth_counts = x[0] / step
    np.testing.assert_allclose(
        half_pulse_correction(mean_counts, rounding), truth_counts, atol=bound
    )
    if rounding is not Rounding.NEAREST:
        assert np.abs(mean_counts - truth_counts).min() > 0.4  # uncorrected: half a count off


def test_bias_scale_and_nonlinearity_act_as_documented():
    k2, k3 = np.array([1e-3, -2e-3, 0.5e-3]), np.array([1e-5, 2e-5, -3e-5])
    tilted = Rotation.from_rotvec([0.4, 0.7, 0.1]).as_matrix()
    _, y, x = _static_error(
        [ScaleNonlinearity(k2, k3), ScaleFactor((1e-3, 2e-3, -1e-3)), Bias((0.01, -0.02, 0.03))],
        duration_s=1.0,
        mat_nb=tilted,
    )
    expected = (x + k2 * x**2 + k3 * x**3) * (1 + np.array([1e-3, 2e-3, -1e-3])) + np.array(
        [0.01, -0.02, 0.03]
    )
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-13)


def test_temperature_effects_follow_their_polynomials_on_a_non_monotone_profile():
    temp = CycleTemperature(base_c=20.0, peak_c=40.0, period_s=60.0)
    dbias = np.array([[1e-3, 1e-5], [-2e-3, 0.0], [0.0, 3e-5]])
    dscale = np.array([[1e-4], [-2e-4], [5e-5]])
    res, y, x = _static_error(
        [TemperatureScale(dscale, t_ref_c=25.0), TemperatureBias(dbias, t_ref_c=25.0)],
        duration_s=60.0,
        temperature=temp,
    )
    t_c = res.session.temp_c
    assert t_c.max() - t_c.min() > 19.0 and np.argmax(t_c) not in (0, t_c.size - 1)  # up then down
    dt = (t_c - 25.0)[:, None]
    expected = x * (1 + dscale.T * dt) + dbias[:, 0] * dt + dbias[:, 1] * dt**2
    np.testing.assert_allclose(y, expected, atol=1e-13)


def test_temperature_effects_need_a_temperature_profile():
    with pytest.raises(ValueError, match="temperature profile"):
        _static_error([TemperatureBias([1e-3])], duration_s=1.0)


def test_bias_drift_is_a_polynomial_in_time():
    c = np.array([[1e-4, 1e-6], [0.0, -2e-6], [3e-4, 0.0]])
    res, y, x = _static_error([BiasDrift(c)], duration_s=30.0, temperature=WarmupTemperature())
    t = res.session.t_s - res.session.t_s[0]
    np.testing.assert_allclose(y - x, c[:, 0] * t[:, None] + c[:, 1] * t[:, None] ** 2, atol=1e-15)


def test_g_sensitivity_is_gyro_bias_proportional_to_specific_force():
    coef = np.array([[1e-4, 0.0, 2e-4], [0.0, -1e-4, 0.0], [5e-5, 0.0, 1e-4]])
    res, y, x = _static_error([GSensitivity(coef)], triad=Triad.GYRO, duration_s=1.0)
    np.testing.assert_allclose(y - x, res.truth.specific_force_b_mps2 @ coef.T, atol=1e-18)
    with pytest.raises(ValueError, match="does not apply to the accel"):
        ErrorModel(accel=TriadErrorModel((GSensitivity(coef),)))


def test_gauss_markov_bias_has_its_variance_and_correlation_time():
    sigma, tau = 2e-3, 0.5
    _, y, x = _static_error(
        [BiasInstability(gm_sigma_si=(sigma,) * 3, gm_tau_s=(tau,) * 3)],
        duration_s=600.0,
        rate_hz=20.0,
    )
    beta = y - x
    phi = math.exp(-1 / 20.0 / tau)
    lag1 = (beta[1:] * beta[:-1]).mean(axis=0) / (beta**2).mean(axis=0)
    # About T/(2τ) = 600 independent stretches per axis, three axes pooled.
    n_eff = 3 * 600.0 / (2 * tau)
    assert abs((beta**2).mean() / sigma**2 - 1) < 5 * math.sqrt(2 / n_eff)
    np.testing.assert_allclose(lag1, phi, atol=5 * math.sqrt((1 - phi**2) / (600.0 * 20)))


def test_gauss_markov_loading_moves_the_axes_its_column_names():
    # One process on z whose column is (−0.5, 0, 1): x wanders by −0.5 times z's wander, y not at all.
    loading = np.eye(3)
    loading[0, 2] = -0.5
    _, y, x = _static_error(
        [
            BiasInstability(
                gm_sigma_si=(0.0, 0.0, 2e-3), gm_tau_s=(1.0, 1.0, 2.0), gm_loading=loading
            )
        ],
        duration_s=30.0,
    )
    beta = y - x
    assert np.std(beta[:, 2]) > 1e-4
    np.testing.assert_allclose(beta[:, 0], -0.5 * beta[:, 2], atol=1e-15)
    np.testing.assert_allclose(beta[:, 1], 0.0, atol=1e-15)


def test_coloured_noise_sums_gauss_markov_terms_and_averages_down_as_they_say():
    # Axis x: two terms (20 ms and 0.2 s), y: one, z: none; 100 Hz for 400 s.
    sigma = np.array([[3e-3, 2e-3], [4e-3, 0.0], [0.0, 0.0]])
    tau = np.array([[0.02, 0.2], [0.05, 1.0], [1.0, 1.0]])
    _, y, x = _static_error([ColouredNoise(sigma, tau)], duration_s=400.0, seed=3)
    c = y - x
    phi = np.exp(-1.0 / (100.0 * tau))
    var = np.sum(sigma**2, axis=1)
    lag1 = np.sum(sigma**2 * phi, axis=1)
    assert np.all(c[:, 2] == 0.0)
    # Independent stretches: 400 s over 2τ of the slowest term (1000 for x, 4000 for y); 5 sd.
    n_eff = np.array([1000.0, 4000.0])
    np.testing.assert_array_less(
        np.abs(np.var(c[:, :2], axis=0) / var[:2] - 1), 5 * np.sqrt(2 / n_eff)
    )
    got = np.mean(c[1:, :2] * c[:-1, :2], axis=0)
    np.testing.assert_array_less(np.abs(got / lag1[:2] - 1), 5 * np.sqrt(2 / n_eff))
    # 1 s means (400 of them) scatter as estimators.noise.gm_mean_variance says: 5 sd of a variance from 400 means.
    means = c[: 400 * 100, :2].reshape(400, 100, 2).mean(axis=1)
    expected = np.sum(sigma[:2] ** 2 * gm_mean_variance(phi[:2], 100), axis=1)
    np.testing.assert_array_less(np.abs(np.var(means, axis=0) / expected - 1), 5 * np.sqrt(2 / 400))
    with pytest.raises(ValueError, match="tau_s positive"):
        ColouredNoise(sigma, np.zeros((3, 2)))


def test_random_walk_bias_increments_grow_with_the_square_root_of_time():
    k = 1e-4
    _, y, x = _static_error([BiasInstability(random_walk_si_per_sqrt_s=(k,) * 3)], duration_s=600.0)
    inc = np.diff((y - x)[::100], axis=0)  # 1 s increments: N(0, K²·1 s)
    assert np.abs(y[0] - x[0]).max() < 1e-12  # starts at the bias
    assert abs(inc.std() / k - 1) < 5 / math.sqrt(2 * inc.size)


def _allan_var(x, m):
    c = x[: x.size // m * m].reshape(-1, m).mean(axis=1)
    return 0.5 * np.mean(np.diff(c) ** 2)


def test_flicker_bias_has_a_flat_allan_deviation_at_the_ieee_floor():
    b = 1e-3
    est = []
    for seed in range(4):
        _, y, x = _static_error(
            [BiasInstability(flicker_si=(b,) * 3)], duration_s=2000.0, rate_hz=10.0, seed=seed
        )
        est += [[_allan_var(col, m) for m in (10, 40, 100)] for col in (y - x).T]
    adev = np.sqrt(np.mean(est, axis=0))
    # Floor B·√(2 ln2 / π) for τ from 1 s to 10 s. Twelve 2000 s records give the
    # Allan variance at τ = 10 s to a few %; 10 % on the deviation allows the
    # discrete filter's departure from an ideal 1/f law.
    np.testing.assert_allclose(adev, b * math.sqrt(2 * math.log(2) / math.pi), rtol=0.10)


def test_gravity_mismatch_changes_the_true_gravity_only():
    model = NOISE_FREE.with_effect(GravityMismatch(0.01))
    res = simulate(static_spec(duration_s=1.0, model=model, gravity_mps2=9.8), 0)
    assert res.truth.gravity_mps2 == 9.8
    assert res.truth.gravity_true_mps2 == pytest.approx(9.81, abs=1e-12)
    np.testing.assert_allclose(np.linalg.norm(res.session.accel_mps2, axis=1), 9.81, atol=1e-12)


def test_nonstatic_positions_move_the_unit_inside_positions_without_changing_g():
    rms = 2e-3
    model = NOISE_FREE.with_effect(NonstaticPositions(angle_rms_rad=rms))
    res = simulate(_short_mp(model, static_s=20.0), 5)
    tr = res.truth
    st = tr.static
    # Pure rotation: |f| stays g; the direction wanders by about the RMS angle.
    np.testing.assert_allclose(
        np.linalg.norm(res.session.accel_mps2[st], axis=1), tr.gravity_true_mps2, rtol=1e-13
    )
    spread = []
    for j in range(len(tr.static_intervals_s)):
        a = res.session.accel_mps2[tr.position_index == j]
        u = a / np.linalg.norm(a, axis=1, keepdims=True)
        spread.append(
            np.arccos(np.clip(u @ u.mean(axis=0) / np.linalg.norm(u.mean(axis=0)), -1, 1)).max()
        )
    assert 0.3 * rms < np.median(spread) < 10 * rms


def test_model_order_and_names_are_enforced():
    with pytest.raises(ValueError, match="signal-path order"):
        TriadErrorModel((Bias((0.0,) * 3), ScaleFactor((0.0,) * 3)))
    with pytest.raises(ValueError, match="once"):
        TriadErrorModel((Bias((0.0,) * 3), Bias((1.0,) * 3)))
    m = TriadErrorModel((NonOrthogonality(), Bias((0.0,) * 3), WhiteNoise()))
    assert m.with_effect(ScaleFactor((1e-3,) * 3)).names == (
        "non_orthogonality",
        "scale_factor",
        "bias",
        "white_noise",
    )
    assert m.with_effect(Bias((1.0,) * 3)).find("bias").bias_si == (1.0, 1.0, 1.0)
    assert m.without("bias").names == ("non_orthogonality", "white_noise")
    with pytest.raises(ValueError, match="needs the triad"):
        ErrorModel().with_effect(Bias((0.0,) * 3))
    with pytest.raises(ValueError, match="broadcast"):
        Bias((1.0, 2.0))


# --- grades -------------------------------------------------------------------------


def test_grades_put_earth_rate_below_mems_gyro_bias_and_above_navigation_noise():
    mems, nav = GRADES[Grade.MEMS], GRADES[Grade.NAVIGATION]
    assert mems.gyro.bias_sd_si > 100 * EARTH_RATE_RPS
    assert mems.accel.noise_density_si * 10.0 == pytest.approx(
        1e-3 * 9.80665
    )  # 1 mg per sample at 100 Hz
    assert nav.gyro.bias_sd_si < 1e-3 * EARTH_RATE_RPS
    # A minute of navigation-grade gyro data resolves Ω to about 1e-3 of itself.
    assert nav.gyro.noise_density_si / math.sqrt(60.0) < 1.5e-3 * EARTH_RATE_RPS
    a = grade_error_model(Grade.MEMS, rng=np.random.default_rng(1))
    b = grade_error_model(Grade.MEMS, rng=np.random.default_rng(2))
    assert a.accel.find("bias") != b.accel.find("bias")
    assert grade_error_model(Grade.NAVIGATION) == grade_error_model(Grade.NAVIGATION)
    assert grade_error_model(Grade.MEMS, quantization=False).accel.find("quantization") is None
    # One grade enum for passports and simulation; a grade without a preset is a clear error.
    with pytest.raises(ValueError, match="no simulation preset for grade 'tactical'"):
        grade_error_model(Grade.TACTICAL)


def test_a_mems_session_passes_validation_within_its_range():
    res = simulate(multi_position_spec(grade=Grade.MEMS, static_s=5.0), 1)
    spec = GRADES[Grade.MEMS]
    out, rej = validate_session(
        res.session, accel_limit_mps2=spec.accel.range_si, gyro_limit_rps=spec.gyro.range_si
    )
    assert rej.total == 0 and out.n_samples == res.session.n_samples


# --- faults ---------------------------------------------------------------------------


def _paired(faults, model=None, **kw):
    """The same seed with and without faults: the noise cancels in the difference."""
    model = model or ErrorModel(
        accel=_linear_model((0.02, -0.01, 0.03), extra=(WhiteNoise((1e-3,) * 3),)),
        gyro=_linear_model((1e-3, 2e-3, -1e-3), extra=(WhiteNoise((1e-4,) * 3),)),
    )
    spec = _short_mp(model, static_s=10.0, **kw)
    clean = simulate(spec, 9)
    faulty = simulate(_short_mp(model, static_s=10.0, faults=tuple(faults), **kw), 9)
    return clean, faulty


@pytest.mark.parametrize("triad", list(Triad))
@pytest.mark.parametrize("index", range(9))
def test_a_step_in_any_parameter_appears_at_its_time(triad, index):
    t0, mag = 40.0, 2e-3
    fault = Fault(FaultKind.STEP, triad, index, t0, mag)
    clean, faulty = _paired([fault])
    t = clean.session.t_s
    y0, y1 = (
        (clean.session.accel_mps2, faulty.session.accel_mps2)
        if triad is Triad.ACCEL
        else (clean.session.gyro_rps, faulty.session.gyro_rps)
    )
    other = (
        (clean.session.gyro_rps, faulty.session.gyro_rps)
        if triad is Triad.ACCEL
        else (clean.session.accel_mps2, faulty.session.accel_mps2)
    )
    np.testing.assert_array_equal(other[0], other[1])
    np.testing.assert_array_equal(y0[t < t0], y1[t < t0])
    assert np.abs(y1[t >= t0] - y0[t >= t0]).max() > 0
    tr = faulty.truth
    expected = tr.params(triad).copy()
    expected[index] += mag
    np.testing.assert_allclose(tr.params_at(triad, t0 + 1.0), expected, atol=1e-15)
    np.testing.assert_allclose(tr.params_at(triad, t0 - 1.0), tr.params(triad), atol=0)


def test_parameter_faults_keep_the_exact_ellipsoid_with_the_faulted_parameters():
    model = ErrorModel(
        accel=_linear_model((0.02, -0.01, 0.03)), gyro=_linear_model((1e-6, 0.0, 0.0))
    )
    faults = [
        Fault(FaultKind.STEP, Triad.ACCEL, 6, 40.0, 3e-3),
        Fault(FaultKind.RAMP, Triad.ACCEL, 4, 60.0, 1e-3, 30.0),
    ]
    _, res = _paired(faults, model=model)
    tr, st = res.truth, res.truth.static
    y = res.session.accel_mps2
    params = tr.params_at(Triad.ACCEL, tr.t_s)
    resid = [
        _exact_residual(y[k : k + 1], tr.gravity_true_mps2, params[k])[0]
        for k in np.flatnonzero(st)[::50]
    ]
    assert np.abs(resid).max() < 1e-12
    after = st & (tr.t_s > 100.0)
    assert np.abs(_exact_residual(y[after], tr.gravity_true_mps2, tr.accel_params)).max() > 1e-3


def test_a_ramp_rises_linearly_then_holds():
    fault = Fault(FaultKind.RAMP, Triad.ACCEL, 0, 30.0, 0.01, 20.0)
    clean, faulty = _paired([fault])
    d = faulty.session.accel_mps2[:, 0] - clean.session.accel_mps2[:, 0]
    g = faulty.truth.gravity_true_mps2
    t = clean.session.t_s
    np.testing.assert_allclose(d, 0.01 * g * np.clip((t - 30.0) / 20.0, 0, 1), atol=1e-12)


def test_a_stuck_axis_holds_its_value_from_onset():
    fault = Fault(FaultKind.STUCK, Triad.GYRO, 2, 25.0, 0.0, 10.0)
    clean, faulty = _paired([fault])
    t, g0, g1 = clean.session.t_s, clean.session.gyro_rps, faulty.session.gyro_rps
    inside = (t >= 25.0) & (t < 35.0)
    k0 = np.argmax(inside)
    assert np.all(g1[inside, 2] == g0[k0 - 1, 2])
    np.testing.assert_array_equal(g1[~inside], g0[~inside])
    np.testing.assert_array_equal(g1[:, :2], g0[:, :2])


def test_a_noise_burst_has_its_standard_deviation_inside_its_window_only():
    fault = Fault(FaultKind.NOISE_BURST, Triad.ACCEL, 1, 20.0, 0.5, 30.0)
    clean, faulty = _paired([fault])
    t = clean.session.t_s
    d = faulty.session.accel_mps2[:, 1] - clean.session.accel_mps2[:, 1]
    inside = (t >= 20.0) & (t < 50.0)
    assert np.all(d[~inside] == 0)
    assert abs(d[inside].std() / 0.5 - 1) < 5 / math.sqrt(2 * inside.sum())


def test_saturation_clips_at_full_scale():
    full_scale = 8.0
    fault = Fault(FaultKind.SATURATION, Triad.ACCEL, 2, 30.0, full_scale)
    clean, faulty = _paired([fault])
    a0, a1 = clean.session.accel_mps2[:, 2], faulty.session.accel_mps2[:, 2]
    after = clean.session.t_s >= 30.0
    assert np.abs(a0[~after]).max() > full_scale  # the unit lies z-up first: clipping would show
    np.testing.assert_array_equal(a1[~after], a0[~after])
    assert np.abs(a1[after]).max() <= full_scale and np.sum(np.abs(a1[after]) == full_scale) > 100
    np.testing.assert_array_equal(a1[np.abs(a0) < full_scale], a0[np.abs(a0) < full_scale])
    np.testing.assert_array_equal(faulty.session.accel_mps2[:, :2], clean.session.accel_mps2[:, :2])


def test_faults_are_validated_and_need_their_effect():
    with pytest.raises(ValueError, match=r"index must be an integer in \[0, 3\)"):
        Fault(FaultKind.STUCK, Triad.GYRO, 3, 0.0, 0.0)
    with pytest.raises(ValueError, match="finite duration"):
        Fault(FaultKind.RAMP, Triad.GYRO, 0, 0.0, 1.0)
    with pytest.raises(ValueError, match="positive"):
        Fault(FaultKind.SATURATION, Triad.GYRO, 0, 0.0, 0.0)
    no_bias = ErrorModel(accel=TriadErrorModel((WhiteNoise((1e-3,) * 3),)))
    with pytest.raises(ValueError, match="needs a 'bias' effect"):
        simulate(
            static_spec(
                duration_s=1.0, model=no_bias, faults=(Fault("step", "accel", 1, 0.0, 1e-3),)
            ),
            0,
        )
    assert Fault("step", "gyro", 7, 0.0, 1e-3).target == "d2"


AUDIT_EFFECTS = {
    "bias_instability",
    "bias_drift",
    "temperature_bias",
    "temperature_scale",
    "scale_nonlinearity",
    "g_sensitivity",
    "quantization",
    "gravity_mismatch",
    "nonstatic_positions",
    "cross_axis_nonlinearity",
    "bias_step",
    "nonorthogonality_change",
    "temperature_hysteresis",
    "clipping",
    "spectral_line",
    "lowpass",
}


def test_every_audit_effect_exists_by_name_and_round_trips_through_plain_parameters():
    assert AUDIT_EFFECTS <= set(EFFECTS)
    assert {"bias", "scale_factor", "non_orthogonality", "white_noise"} <= set(EFFECTS)
    for name, cls in EFFECTS.items():
        effect = cls()
        assert effect.name == name
        assert make_effect(name, effect_params(effect)) == effect
    q = make_effect("quantization", {"step_si": 0.5, "rounding": "toward_zero"})
    assert effect_params(q) == {"step_si": [0.5, 0.5, 0.5], "rounding": "toward_zero"}
    with pytest.raises(ValueError, match="unknown parameter 'sigma'"):
        make_effect("bias_instability", {"sigma": 1.0})
    with pytest.raises(ValueError, match="unknown effect 'flicker'"):
        make_effect("flicker", {})


def test_positions_and_turns_may_have_their_own_lengths():
    att = eighteen_position_attitudes()[:4]
    res = simulate(
        multi_position_spec(
            model=NOISE_FREE,
            n_positions=4,
            static_s=np.array([3.0, 5.0, 2.0, 4.0]),
            transition_s=np.array([1.0, 2.0, 3.0]),
        ),
        0,
    )
    iv = res.truth.static_intervals_s
    np.testing.assert_allclose(iv[:, 1] - iv[:, 0] + 0.01, [3.0, 5.0, 2.0, 4.0])
    np.testing.assert_allclose(iv[1:, 0] - iv[:-1, 1] - 0.01, [1.0, 2.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(res.truth.mat_nb[-1], att[-1], atol=1e-12)
    with pytest.raises(ValueError, match="transition_s a number or 3"):
        multi_position_spec(n_positions=4, transition_s=np.ones(4))
