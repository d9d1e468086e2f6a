"""M3: temperature polynomials of bias and scale, order chosen on held-out temperatures, compensation."""

import dataclasses

import numpy as np
import pytest

from estimators.conventions import normal_gravity_mps2
from estimators.passport import TemperatureModel
from estimators.sixpos import session_positions
from estimators.temperature import (
    PAPER_SCALE_ERROR,
    PAPER_TEMPS_C,
    PAPER_ZERO_ERROR_G,
    clamp_to_range,
    fit_temperature_model,
    group_temperatures,
    hidden_quartic_model,
    model_errors,
    remove_temperature_errors,
    simulate_chamber,
    temperature_series,
    temperature_truth,
    to_reference_temperature,
)

G = normal_gravity_mps2(45.0, 0.0)
TEMPS = np.array(PAPER_TEMPS_C)
GRID = np.linspace(TEMPS[0], TEMPS[-1], 481)


@pytest.fixture(scope="module")
def chamber():
    """Three simulated units through the whole chain: chamber session → positions → six-position tests → model."""
    model = hidden_quartic_model(gravity_mps2=G)
    out = []
    for seed in range(3):
        session = simulate_chamber(model, PAPER_TEMPS_C, seed=seed, static_s=8.0)
        series = temperature_series(session_positions(session), gravity_mps2=G)
        fit = fit_temperature_model(
            series.temp_c,
            series.bias_mps2,
            series.scale_error,
            bias_std_mps2=series.bias_std_mps2,
            scale_std=series.scale_std,
            gravity_mps2=G,
        )
        out.append((series, fit))
    return model, out


def _max_errors(model, fit):
    """Largest zero error (g) and scale error over −45…+75 °C: uncompensated (only the room-temperature
    passport) and compensated with the fitted polynomials."""
    bt, et = temperature_truth(model, GRID)
    b0, e0 = temperature_truth(model, np.array([20.0]))
    bm, em = model_errors(fit.model, GRID)
    return (np.max(np.abs(bt - b0)) / G, np.max(np.abs(et - e0))), (
        np.max(np.abs(bt / G - bm)),
        np.max(np.abs(et - em)),
    )


def test_the_hidden_dependence_is_sized_like_the_papers_channel():
    model = hidden_quartic_model(gravity_mps2=G)
    bt, et = temperature_truth(model, GRID)
    b0, e0 = temperature_truth(model, np.array([20.0]))
    np.testing.assert_allclose(np.max(np.abs(bt - b0), axis=0) / G, PAPER_ZERO_ERROR_G, rtol=1e-3)
    np.testing.assert_allclose(
        np.max(np.abs((1 + et) / (1 + e0) - 1), axis=0), PAPER_SCALE_ERROR, rtol=1e-3
    )


def test_chamber_tests_select_order_4_and_compensate_beyond_the_papers_factors(chamber):
    model, units = chamber
    for series, fit in units:
        assert series.temp_c.size == 25
        assert fit.order == 4, fit.reason
        (zero_before, scale_before), (zero_after, scale_after) = _max_errors(model, fit)
        assert zero_before == pytest.approx(0.0013, rel=0.01) and scale_before == pytest.approx(
            0.022, rel=0.01
        )
        assert zero_after < 0.0002 and scale_after < 0.0005  # the paper: < 0.0002 g and < 0.05 %
        # The six-position estimates scatter about the truth as their standard deviations say.
        bt, et = temperature_truth(model, series.temp_c)
        z = np.concatenate(
            [
                ((series.bias_mps2 - bt) / series.bias_std_mps2).ravel(),
                ((series.scale_error - et) / series.scale_std).ravel(),
            ]
        )
        assert np.max(np.abs(z)) < 4.5 and 0.7 < z.std() < 1.3


def test_the_fit_records_the_temperatures_it_was_fitted_on(chamber):
    _, units = chamber
    for series, fit in units:
        assert (fit.model.valid_min_c, fit.model.valid_max_c) == (
            series.temp_c.min(),
            series.temp_c.max(),
        )
        assert -45.5 < fit.model.valid_min_c < -44.5 and 74.5 < fit.model.valid_max_c < 75.5
    series, _ = units[0]
    with pytest.raises(
        ValueError,
        match=r"reference_temp_c 90 °C is outside the tested temperatures -4\d(\.\d+)?…7\d(\.\d+)? °C",
    ):
        fit_temperature_model(
            series.temp_c,
            series.bias_mps2,
            series.scale_error,
            bias_std_mps2=series.bias_std_mps2,
            scale_std=series.scale_std,
            gravity_mps2=G,
            reference_temp_c=90.0,
        )


def test_held_out_criterion_picks_the_order_that_training_residuals_cannot(chamber):
    _, units = chamber
    _, fit = units[0]
    training = [s.training for s in fit.scores]
    heldout = {s.order: s.regularity for s in fit.scores}
    # Training residuals only fall with the order, so they would pick the highest.
    assert np.all(np.diff(training) <= 1e-9 * np.array(training[:-1]))
    # On held-out temperatures order 3 misses by orders of magnitude and order 5 gains nothing.
    assert heldout[3] > 1e3 * heldout[4]
    assert heldout[5] > heldout[4] - next(s.regularity_se for s in fit.scores if s.order == 4)
    assert "order 4" in fit.reason


def _series_batch(truth_bias, truth_scale, seeds, noise=(1.6e-5, 2.3e-6)):
    """Six-position results at the paper's temperatures, with the noise the chamber simulation shows."""
    for seed in seeds:
        rng = np.random.default_rng(seed)
        sb, ss = noise
        yield fit_temperature_model(
            TEMPS,
            truth_bias + sb * rng.standard_normal(truth_bias.shape),
            truth_scale + ss * rng.standard_normal(truth_scale.shape),
            bias_std_mps2=np.full(truth_bias.shape, sb),
            scale_std=np.full(truth_scale.shape, ss),
            gravity_mps2=G,
        )


def test_order_is_right_in_a_seeded_batch_of_fifty_units():
    model = hidden_quartic_model(gravity_mps2=G)
    bt, et = temperature_truth(model, TEMPS)
    orders = [fit.order for fit in _series_batch(bt, et, range(100, 150))]
    assert orders == [4] * 50


def test_a_quadratic_dependence_selects_order_2():
    x = (TEMPS - 20.0) / 55.0
    bias = np.column_stack([1e-3 + 4e-3 * x - 6e-3 * x**2] * 3)
    scale = np.column_stack([1e-4 + 5e-3 * x + 8e-3 * x**2] * 3)
    orders = [fit.order for fit in _series_batch(bias, scale, range(10))]
    assert orders.count(2) >= 9, orders


def test_compensation_round_trips_and_keeps_the_passport_values_at_the_reference():
    rng = np.random.default_rng(2)
    model = TemperatureModel(
        20.0,
        rng.normal(0, 1e-4, (3, 5)) * 1e-2 ** np.arange(5),
        rng.normal(0, 1e-3, (3, 5)) * 1e-2 ** np.arange(5),
        valid_min_c=-45.0,
        valid_max_c=75.0,
    )
    temps = rng.uniform(-45.0, 75.0, 200)
    true_f = rng.normal(0, 5.0, (200, 3))
    b, e = model_errors(model, temps)
    measured = (1 + e) * true_f + G * b
    np.testing.assert_allclose(
        remove_temperature_errors(measured, temps, model, gravity_mps2=G), true_f, atol=1e-12
    )
    # At T_ref the unit reads (1 + e(T_ref))·f + g·b(T_ref): what the passport's nominal values describe.
    b_ref, e_ref = model_errors(model, np.array([20.0]))
    expected = (1 + e_ref) * true_f + G * b_ref
    np.testing.assert_allclose(
        to_reference_temperature(measured, temps, model, gravity_mps2=G), expected, atol=1e-12
    )
    with pytest.raises(ValueError, match=r"accel \(N, 3\) and temp_c \(N,\)"):
        remove_temperature_errors(measured, temps[:10], model, gravity_mps2=G)


def test_group_temperatures_joins_close_values():
    labels = group_temperatures(np.array([20.1, -45.0, 19.8, -44.2, 75.0, 20.3]))
    np.testing.assert_array_equal(labels, [1, 0, 1, 0, 2, 1])


@pytest.mark.parametrize(
    ("temps", "message"),
    [([20.0] * 6, "got 1"), ([-40.0, 0.0, 40.0] * 2, "4 or more different temperatures, got 3")],
)
def test_too_few_temperatures_say_what_is_missing(temps, message):
    t = np.array(temps)
    ones = np.ones((t.size, 3))
    with pytest.raises(ValueError, match=message):
        fit_temperature_model(t, ones, ones, bias_std_mps2=ones, scale_std=ones, gravity_mps2=G)


def test_a_session_without_temperature_or_with_an_incomplete_test_is_refused():
    model = hidden_quartic_model(gravity_mps2=G)
    session = simulate_chamber(model, (20.0, 40.0), seed=1, static_s=4.0)
    positions = session_positions(session, min_static_s=2.0)
    with pytest.raises(ValueError, match=r"at 40\.0 °C: .*missing: -z up"):
        temperature_series(positions[:-1], gravity_mps2=G)
    no_temp = [dataclasses.replace(p, temp_mean_c=None) for p in positions]
    with pytest.raises(ValueError, match="no temperature column"):
        temperature_series(no_temp, gravity_mps2=G)


def _quartic(**bounds):
    rng = np.random.default_rng(5)
    return TemperatureModel(
        20.0,
        rng.normal(0, 1e-4, (3, 5)) * 1e-2 ** np.arange(5),
        rng.normal(0, 1e-3, (3, 5)) * 1e-2 ** np.arange(5),
        **bounds,
    )


def test_outside_its_range_the_model_is_held_at_the_nearer_edge():
    model = _quartic(valid_min_c=-10.0, valid_max_c=50.0)
    temps = np.array([-1e6, -273.15, -10.0, 20.0, 50.0, 85.0, 1e6])
    np.testing.assert_array_equal(
        clamp_to_range(model, temps), [-10.0, -10.0, -10.0, 20.0, 50.0, 50.0, 50.0]
    )
    b, e = model_errors(model, temps)
    b_edge, e_edge = model_errors(model, np.array([-10.0, 50.0]))
    np.testing.assert_array_equal(b[:3], np.repeat(b_edge[:1], 3, axis=0))
    np.testing.assert_array_equal(b[4:], np.repeat(b_edge[1:], 3, axis=0))
    np.testing.assert_array_equal(e[4:], np.repeat(e_edge[1:], 3, axis=0))
    # The compensated output far outside is finite and equal to the one at the edge.
    f = np.tile([0.1, -0.2, 9.8], (temps.size, 1))
    out = to_reference_temperature(f, temps, model, gravity_mps2=G)
    assert np.all(np.isfinite(out))
    np.testing.assert_array_equal(out[-1], out[4])
    np.testing.assert_array_equal(
        remove_temperature_errors(f, temps, model, gravity_mps2=G)[0],
        remove_temperature_errors(f, temps, model, gravity_mps2=G)[2],
    )
    # What the clamp prevents: the polynomial itself at 1e6 °C (an unbounded, schema-1 model evaluates it).
    b_raw, e_raw = model_errors(_quartic(valid_min_c=None, valid_max_c=None), temps)
    assert np.max(np.abs(b_raw[-1])) > 1e6 and np.max(np.abs(e_raw[-1])) > 1e6
    np.testing.assert_array_equal(b_raw[2:5], b[2:5])  # inside the range both are the polynomial


def test_in_range_is_inclusive_and_all_true_without_a_range():
    np.testing.assert_array_equal(
        _quartic(valid_min_c=-10.0, valid_max_c=50.0).in_range([-10.001, -10.0, 50.0, 50.001]),
        [False, True, True, False],
    )
    assert _quartic(valid_min_c=None, valid_max_c=None).in_range([-1e9, 1e9]).all()
