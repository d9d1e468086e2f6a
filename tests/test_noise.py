"""Noise estimators on known noise: white level, Allan slopes, noise for averages, quantization grid (M2)."""

import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.stats import chi2

from estimators.noise import (
    batch_means_sd,
    fit_noise_colour,
    gm_mean_variance,
    overlapping_allan_deviation,
    quantization_step,
    sample_noise_cov,
    sample_noise_sd,
    white_noise_sd,
)

RATE_HZ = 100.0
COLOUR_THRESHOLD = float(chi2.isf(0.01 / 6, 2))
"""The audit's colour threshold: χ²(2) at 1 % family-wise over two terms on three axes."""


def _adev_tol(n: int, m: np.ndarray) -> np.ndarray:
    # Relative standard error of an overlapping ADEV ≈ 1/√(2·(N/m)·(2/3)) (IEEE Std 952, white noise); 4 of them as bound.
    return 4.0 / np.sqrt(2.0 * n / m * 2.0 / 3.0)


def test_white_noise_allan_falls_as_inverse_sqrt_tau():
    rng = np.random.default_rng(1)
    sd, n = 0.01, 40_000
    x = sd * rng.standard_normal((n, 3))
    m = np.array([1, 10, 100])
    ad = overlapping_allan_deviation(x, RATE_HZ, m)
    np.testing.assert_allclose(ad.tau_s, m / RATE_HZ)
    assert np.all(np.abs(ad.adev / (sd / np.sqrt(m))[:, None] - 1.0) < _adev_tol(n, m)[:, None])
    np.testing.assert_array_equal(ad.n_terms, n - 2 * m + 1)
    assert np.allclose(white_noise_sd(x), sd, rtol=4.0 / np.sqrt(n))


def test_random_walk_allan_rises_as_sqrt_tau():
    # Rate random walk K: σ_A(τ) = K·√(τ/3) (IEEE Std 952).
    rng = np.random.default_rng(2)
    k, n = 1e-3, 200_000
    x = np.cumsum(k * np.sqrt(1.0 / RATE_HZ) * rng.standard_normal(n))
    m = np.array([100, 400])
    ad = overlapping_allan_deviation(x, RATE_HZ, m).adev[:, 0]
    # A random walk's Allan variance estimate is far noisier than white noise's: a factor 1.6 either way.
    ratio = ad / (k * np.sqrt(m / RATE_HZ / 3.0))
    assert np.all((ratio > 1 / 1.6) & (ratio < 1.6)), ratio


def test_default_cluster_sizes_are_log_spaced_and_stay_within_a_quarter_of_the_record():
    ad = overlapping_allan_deviation(np.random.default_rng(3).standard_normal(1000), RATE_HZ)
    m = np.round(ad.tau_s * RATE_HZ).astype(int)
    assert m[0] == 1 and m[-1] <= 250 and np.all(np.diff(m) > 0)


def test_sample_noise_cov_reads_the_axes_correlation_under_a_slow_wander():
    rng = np.random.default_rng(6)
    n, rho = 20_000, -0.4
    z = rng.standard_normal((n, 2)) @ np.linalg.cholesky([[1.0, rho], [rho, 1.0]]).T
    slow = 0.05 * np.sin(
        2 * np.pi * 0.05 * np.arange(n) / RATE_HZ
    )  # common to both axes: +1 correlation
    x = 0.01 * z * [1.0, 2.0] + slow[:, None]
    cov = sample_noise_cov(x, 50)
    # A sample correlation has sd (1 − ρ²)/√n: 4 of them; the wander (5× the noise) would push it towards +1.
    assert abs(cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]) - rho) < 4.0 * (1 - rho**2) / np.sqrt(n)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), sample_noise_sd(x, 50), rtol=1e-12)
    assert np.corrcoef(x.T)[0, 1] > 0.5


def test_sample_noise_sd_ignores_a_slow_wander_but_keeps_the_white_level():
    rng = np.random.default_rng(4)
    n, sd = 20_000, 0.01
    slow = 0.05 * np.sin(2 * np.pi * 0.05 * np.arange(n) / RATE_HZ)  # 5× the noise, 20 s period
    x = sd * rng.standard_normal(n) + slow
    assert abs(sample_noise_sd(x, 50)[0] / sd - 1.0) < 4.0 / np.sqrt(n)
    assert np.std(x) > 2.0 * sd  # the plain spread would not


def test_batch_means_sd_is_the_level_at_which_averages_shrink():
    # MA(1) noise x_k = e_k + θ e_{k−1}: per-sample variance (1+θ²)σ², averages shrink as (1+θ)²σ²/n.
    rng = np.random.default_rng(5)
    theta, sd = 0.6, 0.01
    e = sd * rng.standard_normal((30, 2000))
    records = [lfilter([1.0, theta], [1.0], r) for r in e]
    got = batch_means_sd(records, 50)[0]
    # 30 records × 39 batches of dof: relative sd of the estimate ≈ 1/√(2·1170); 4 of them.
    assert abs(got / ((1.0 + theta) * sd) - 1.0) < 4.0 / np.sqrt(2 * 30 * 39)
    assert (
        abs(
            np.mean([sample_noise_sd(r, 50)[0] for r in records]) / (np.sqrt(1 + theta**2) * sd)
            - 1.0
        )
        < 0.02
    )


def test_quantization_step_found_on_an_offset_grid_and_not_off_it():
    rng = np.random.default_rng(6)
    step = 0.002418
    counts = np.round(0.01 * rng.standard_normal(5000) / step) + 12_345
    x = (
        counts - 32_768
    ) * step  # raw counts minus a mid-scale offset, as a session reader converts them
    assert abs(quantization_step(x) - step) < 1e-9
    assert quantization_step(0.01 * rng.standard_normal(5000)) is None
    assert quantization_step(np.full(100, 9.81)) is None  # one level: no grid to read


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: overlapping_allan_deviation(np.zeros(2), RATE_HZ), "at least 3 samples"),
        (lambda: white_noise_sd(np.zeros(2)), "at least 3 samples"),
        (lambda: sample_noise_sd(np.zeros(10), 11), r"window must be within \[2, 10\]"),
        (lambda: batch_means_sd([np.zeros(10)], 6), "no record holds two batches of 6 samples"),
        (lambda: batch_means_sd([np.zeros(10)], 0), "batch must be at least 1"),
    ],
)
def test_bad_input_is_a_clear_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def _records(x: np.ndarray, length: int) -> list[np.ndarray]:
    return [x[k : k + length] for k in range(0, x.shape[0] - length + 1, length)]


def test_noise_colour_names_nothing_on_white_noise():
    # 40 sessions of 30 positions × 5 s at 100 Hz: each axis tries up to two terms at 1 % family-wise over the triad.
    coloured = []
    for seed in range(40):
        x = 0.01 * np.random.default_rng(seed).standard_normal((30 * 500, 3))
        c = fit_noise_colour(_records(x, 500), RATE_HZ, 100, COLOUR_THRESHOLD, max_tau_s=0.5)
        coloured.append(bool(np.any(c.sigma_si > 0)))
        np.testing.assert_allclose(c.level_ratio[c.sigma_si.max(axis=1) == 0], 1.0)
    assert sum(coloured) <= 1, [k for k, c in enumerate(coloured) if c]


def test_noise_colour_finds_a_gauss_markov_term_and_the_level_averages_shrink_to():
    # White 6e-3 plus a Gauss–Markov term of 6e-3 per sample, τ = 30 ms (φ = 0.72): 40 positions × 8 s.
    sigma, tau, white = 6e-3, 0.03, 6e-3
    phi = np.exp(-1.0 / (RATE_HZ * tau))
    level = np.sqrt((white**2 + sigma**2 * (1 + phi) / (1 - phi)) / (white**2 + sigma**2))
    for seed in range(3):
        rng = np.random.default_rng(seed)
        n = 40 * 800
        gm = lfilter([1.0], [1.0, -phi], sigma * np.sqrt(1 - phi**2) * rng.standard_normal((3, n)))
        x = (gm + white * rng.standard_normal((3, n))).T
        c = fit_noise_colour(_records(x, 800), RATE_HZ, 100, COLOUR_THRESHOLD, max_tau_s=0.5)
        # One term per axis. Bounds: 4 sd of each estimate over 12 seeds × 3 axes of this session
        # (σ 1.3 %, ln τ 0.038, the level 1.6 %; the 1 s batch means, 800 batches, 5 %).
        assert np.all(c.sigma_si[:, 1] == 0) and np.all(c.lr[:, 0] > 10 * COLOUR_THRESHOLD)
        assert np.all(np.abs(np.log(c.tau_s[:, 0] / tau)) < 0.15), c.tau_s
        np.testing.assert_allclose(c.sigma_si[:, 0], sigma, rtol=0.055)
        np.testing.assert_allclose(c.level_ratio, level, rtol=0.065)
        # The level is what 1 s means of the records do.
        np.testing.assert_allclose(
            batch_means_sd(_records(x, 800), 100) / np.sqrt(white**2 + sigma**2),
            np.full(3, level),
            rtol=0.2,
        )


def test_mean_variance_of_a_gauss_markov_sequence_is_exact():
    phi, n = 0.8, 25
    lag = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    assert gm_mean_variance(np.array(phi), n) == pytest.approx(np.sum(phi**lag) / n**2, rel=1e-12)
    assert gm_mean_variance(np.array(0.0), n) == pytest.approx(1.0 / n)
