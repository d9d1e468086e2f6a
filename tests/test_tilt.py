"""M2: a single-axis accelerometer passport from a tilt table with whole-pulse output."""

import numpy as np
import pytest

from estimators.passport import Passport
from estimators.repeatability import fit_linear, t_quantile
from estimators.sim import Rounding
from estimators.tilt import (
    TiltBench,
    TiltRun,
    bench_session,
    detect_lsb,
    half_pulse_bias,
    nominal_scale,
    run_from_session,
    runs_from_samples,
    simulate_runs,
    simulate_samples,
    tilt_equations,
    tilt_passport,
    tilt_triad_passport,
)


@pytest.fixture(scope="module")
def paper():
    """The paper's bench (defaults of TiltBench), five runs, and its passport."""
    bench = TiltBench()
    runs = simulate_runs(bench, np.random.default_rng(2009))
    return bench, runs, tilt_passport(runs, gravity_mps2=bench.gravity_mps2)


def test_nominal_scale_is_eq7():
    assert nominal_scale(1275.0, -1275.0, 9.81) == pytest.approx(2 * 9.81 / 2550.0)
    with pytest.raises(ValueError, match="axis reversed"):
        nominal_scale(-1275.0, 1275.0, 9.81)


def test_k0_reproduces_the_papers_pulse_weight(paper):
    bench, _, result = paper
    # The paper: 0.00769 m/s² per pulse. The truncated counts make the up/down span one
    # pulse short, so eq. 7 gives k*·2g/(2g − k*); the noise of two 60 s means moves it by ~1e-5.
    expected = 2 * bench.gravity_mps2 / (2 * bench.gravity_mps2 / bench.pulse_mps2 - 1.0)
    assert result.k0_mps2 == pytest.approx(expected, rel=5e-5)
    assert round(result.k0_mps2, 5) == 0.00769


def test_per_run_intervals_cover_the_truth_at_their_level():
    # 200 runs of the paper's protocol, each solved with its own k0; truth per run: its own
    # turn-on zero offset, the mount error, and Δk relative to that run's k0.
    bench = TiltBench(n_runs=200)
    samples = simulate_samples(bench, np.random.default_rng(7))
    runs = runs_from_samples(bench, samples)
    half = t_quantile(0.95, len(bench.angles_deg) - 3)
    hits = np.zeros(3)
    for s, r in zip(samples, runs, strict=True):
        k0 = nominal_scale(r.counts_up, r.counts_down, bench.gravity_mps2)
        fit = fit_linear(*tilt_equations(r, k0, bench.gravity_mps2))
        truth = np.array([s.zero_offset_mps2, bench.misalignment_rad, bench.pulse_mps2 / k0 - 1.0])
        hits += np.abs(fit.values - truth) <= half * fit.std
    coverage = hits / len(runs)
    assert np.all(np.abs(coverage - 0.95) < 4 * np.sqrt(0.95 * 0.05 / len(runs))), coverage


def test_compensation_brings_the_error_from_the_papers_0_9_to_0_2_pulse(paper):
    bench, runs, result = paper
    g, k = bench.gravity_mps2, bench.pulse_mps2
    a = np.radians(np.asarray(bench.angles_deg))
    dk = bench.true_scale_error
    # Before (half-pulse corrected, no passport): the sensor's errors, the run-to-run zero
    # offset, the table's setting error and the noise of the 30 s means, all in pulses.
    systematic = (
        bench.zero_offset_mps2 + g * np.cos(a) * bench.misalignment_rad - g * np.sin(a) * dk
    ) / k
    random_var = (g * np.cos(a) * bench.setting_sigma_rad / k) ** 2 + (
        bench.noise_mps2 / k
    ) ** 2 / bench.samples_per_angle
    before = np.sqrt(np.mean(systematic**2 + random_var) + (bench.turn_on_sigma_mps2 / k) ** 2)
    # After: the fit leaves the random part, less the 3 degrees of freedom it used.
    after = np.sqrt(np.mean(random_var) * (a.size - 3) / a.size)
    # The bench's parameters are chosen so these expectations are the paper's figures ...
    assert round(before, 1) == 0.9 and round(after, 1) == 0.2
    # ... and the simulated runs meet them within their own scatter (5 runs: 5 draws of the
    # turn-on offset for "before", 285 residual degrees of freedom for "after").
    assert result.errors.half_pulse == pytest.approx(before, rel=0.25)
    assert result.errors.in_run == pytest.approx(
        after, rel=5 / np.sqrt(2 * len(runs) * (a.size - 3))
    )
    # The intersection's values, applied to every run, do nearly as well as each run's own fit.
    assert result.errors.in_run < result.errors.passport < 1.5 * result.errors.in_run


def test_passport_value_lies_in_the_intersection_and_near_the_truth(paper):
    bench, _, result = paper
    sp = result.spread
    assert sp.all_reproducible
    assert np.all(sp.common_lower <= sp.value) and np.all(sp.value <= sp.common_upper)
    # The truth is in every run's interval with probability 0.95⁵ per parameter; it is in their envelope.
    truth = bench.true_params
    assert np.all(np.abs(sp.value - truth) <= sp.tolerance)
    assert result.scale_mps2 == pytest.approx(bench.pulse_mps2, rel=3 * sp.tolerance[2])
    assert np.all(result.fits[0].stabilization.settled_at <= len(bench.angles_deg))


def test_without_the_half_pulse_correction_one_sided_angles_bias_the_zero_offset_by_half_a_pulse(
    paper,
):
    bench, runs, result = paper
    bias = half_pulse_bias(runs, gravity_mps2=bench.gravity_mps2)
    # Every angle is positive: the missing +½ pulse is a constant and only δa absorbs it.
    np.testing.assert_allclose(bias, [-0.5 * result.k0_mps2, 0.0, 0.0], atol=1e-12)


def test_without_the_half_pulse_correction_two_sided_angles_bias_the_scale_factor():
    bench = TiltBench(angles_deg=tuple(float(a) for a in range(-30, 30)), n_runs=3)
    runs = simulate_runs(bench, np.random.default_rng(5))
    with_it = tilt_passport(runs, gravity_mps2=bench.gravity_mps2)
    bias = half_pulse_bias(runs, gravity_mps2=bench.gravity_mps2)
    # The missing ½·sign(N̂) is odd in α: least squares puts it into Δk through −g·sin α.
    h, _ = tilt_equations(runs[0], with_it.k0_mps2, bench.gravity_mps2)
    expected = np.linalg.lstsq(
        h, -0.5 * with_it.k0_mps2 * np.sign(runs[0].counts_mean), rcond=None
    )[0]
    assert bias[2] == pytest.approx(expected[2], rel=0.05)
    assert abs(bias[2]) > 5 * np.mean(
        with_it.spread.std[:, 2]
    )  # a scale error of ~0.1 %, far beyond the noise
    assert abs(bias[2]) > 5e-4


def test_a_floor_converter_gets_its_own_half_pulse_and_no_scale_bias():
    bench = TiltBench(rounding=Rounding.FLOOR, n_runs=3)
    assert bench.true_scale_error == 0.0
    runs = simulate_runs(bench, np.random.default_rng(8))
    result = tilt_passport(runs, gravity_mps2=bench.gravity_mps2)
    assert np.all(np.abs(result.spread.value - bench.true_params) <= result.spread.tolerance)


def test_a_run_with_another_zero_offset_is_not_reproducible():
    bench = TiltBench(n_runs=3)
    runs = simulate_runs(bench, np.random.default_rng(9))
    moved = runs[2]
    shifted = TiltRun(
        angles_rad=moved.angles_rad,
        counts_mean=moved.counts_mean + 12.0,
        counts_std=moved.counts_std,
        n_samples=moved.n_samples,
        counts_up=moved.counts_up + 12.0,
        counts_down=moved.counts_down + 12.0,
    )
    result = tilt_passport([runs[0], runs[1], shifted], gravity_mps2=bench.gravity_mps2)
    assert result.spread.not_reproducible() == ("zero_offset_mps2",)
    tp = tilt_triad_passport(result, axis=0, lsb_mps2=bench.lsb_mps2, sample_rate_hz=bench.rate_hz)
    assert not tp.observable[0] and tp.observable[3]


def test_triad_passport_carries_the_axis_in_the_conventions_error_model(paper):
    bench, _, result = paper
    tp = tilt_triad_passport(result, axis=1, lsb_mps2=bench.lsb_mps2, sample_rate_hz=bench.rate_hz)
    g = bench.gravity_mps2
    # Output = N·lsb = (g sin α* + δa)·lsb/k*: e = lsb/k* − 1, b = δa·(lsb/k*)/g.
    assert tp.nominal[4] == pytest.approx(bench.lsb_mps2 / result.scale_mps2 - 1.0, rel=1e-12)
    assert tp.nominal[1] == pytest.approx(
        result.spread.value[0] * bench.lsb_mps2 / result.scale_mps2 / g, rel=1e-12
    )
    assert list(np.flatnonzero(tp.observable)) == [1, 4]
    assert (
        tp.provenance.procedure == "M2 tilt table, axis y" and tp.provenance.n_runs == bench.n_runs
    )
    assert list(np.flatnonzero(tp.provenance.reproducible)) == [1, 4]
    low, high = tp.provenance.ci_low, tp.provenance.ci_high
    assert low[1] < tp.nominal[1] < high[1] and low[4] < tp.nominal[4] < high[4]
    assert tp.noise_std[1] == pytest.approx(result.noise_pulses * bench.lsb_mps2 / g)
    passport = Passport(
        unit_id="adxl",
        sensor_model="ADXL203",
        sensor_ids={},
        created="2009-02-05",
        triads={tp.triad: tp},
    )
    assert Passport.from_dict(passport.to_dict()).to_dict() == passport.to_dict()


def test_a_session_file_gives_back_the_same_run():
    bench = TiltBench(n_runs=1)
    rng = np.random.default_rng(4)
    samples = simulate_samples(bench, rng)
    direct = runs_from_samples(bench, samples)[0]
    session = bench_session(bench, samples[0], axis=2, rng=rng)
    run, lsb = run_from_session(session, angles_rad=np.radians(bench.angles_deg), axis=2)
    assert lsb == pytest.approx(bench.lsb_mps2, rel=1e-9)
    # The plateau finder trims the ends of each hold: the means agree within their noise.
    sigma = direct.counts_std / np.sqrt(run.n_samples)
    assert np.all(np.abs(run.counts_mean - direct.counts_mean) < 5 * sigma)
    assert np.all(run.n_samples > 0.8 * bench.samples_per_angle)
    with pytest.raises(ValueError, match=r"found 62 holds .* protocol has 61"):
        run_from_session(session, angles_rad=np.radians(bench.angles_deg[:-1]), axis=2)


@pytest.mark.parametrize(
    ("angles_deg", "message"),
    [
        ((10.0, 20.0, 30.0), "at least 4 angles"),
        ((10.0, 10.0, 20.0, 20.0), "at least 3 different angles"),
        ((10.0, 20.0, 30.0, 95.0), "within"),
    ],
)
def test_a_run_with_unusable_angles_says_what_is_missing(angles_deg, message):
    n = len(angles_deg)
    with pytest.raises(ValueError, match=message):
        TiltRun(
            angles_rad=np.radians(angles_deg),
            counts_mean=np.zeros(n),
            counts_std=np.ones(n),
            n_samples=np.ones(n, int),
            counts_up=1275.0,
            counts_down=-1275.0,
        )


def test_one_run_is_not_a_reproducibility_check(paper):
    bench, runs, _ = paper
    with pytest.raises(ValueError, match="at least 2 runs"):
        tilt_passport(runs[:1], gravity_mps2=bench.gravity_mps2)


def test_unquantized_values_ask_for_the_pulse_weight():
    with pytest.raises(ValueError, match="--lsb-mps2"):
        detect_lsb(np.array([0.0, 0.1, 0.25, 0.3333]))
    assert detect_lsb(np.array([0.0, 0.0077, 0.0154, -0.0231])) == pytest.approx(0.0077)
