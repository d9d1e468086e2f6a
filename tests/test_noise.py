"""Noise estimators on known noise: white level, Allan slope −½, quantization grid (M2)."""

import numpy as np

from estimators.noise import overlapping_allan_deviation, quantization_step, white_noise_sd


def test_white_noise_allan_falls_as_inverse_sqrt_tau():
    rng = np.random.default_rng(1)
    sd, n = 0.01, 40_000
    x = sd * rng.standard_normal((n, 3))
    ad = overlapping_allan_deviation(x, 100.0, np.array([1, 10, 100]))
    expected = sd / np.sqrt(np.array([1, 10, 100]))[:, None]
    # Relative standard error of an overlapping ADEV ≈ 1/√(2·N/m·(2/3)); 4 of them as bound.
    tol = 4.0 / np.sqrt(2.0 * n / np.array([1, 10, 100]) * 2.0 / 3.0)
    assert np.all(np.abs(ad.adev / expected - 1.0) < tol[:, None])
    assert np.allclose(white_noise_sd(x), sd, rtol=4.0 / np.sqrt(n))


def test_quantization_step_found_on_grid_and_not_off_it():
    rng = np.random.default_rng(2)
    x = 0.0024 * np.round(0.01 * rng.standard_normal(5000) / 0.0024)
    assert abs(quantization_step(x) - 0.0024) < 1e-12
    assert quantization_step(0.01 * rng.standard_normal(5000)) is None
