"""Position-level synthetic data for the nine-parameter tests (hand-derived layer, methods.md M1).

True unit directions ``u_k``, the exact error model of ``estimators.conventions``
``ã = triad_matrix(e, sensor_axes(angles)) @ u + b``, and Gaussian noise on each
position mean with a known covariance. No session simulator involved.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimators.conventions import (
    EARTH_RATE_RPS,
    RPS_PER_DPH,
    Grade,
    Triad,
    nine_params,
    sensor_axes,
    triad_matrix,
)
from estimators.ninepar import estimate_refined, scheme_directions
from estimators.passport import Passport, TemperatureModel, passport_from_estimates

DEG_PER_H_NORM = RPS_PER_DPH / EARTH_RATE_RPS
"""1 °/h in units of Ω."""

# Where a cosine d_j is moved by one of the six angles (conventions.py, first order):
# d1 ≈ δ_xz − δ_yz, d2 ≈ δ_zy − δ_xy, d3 ≈ δ_yx − δ_zx; angle order [δ_xy δ_xz δ_yx δ_yz δ_zx δ_zy].
_ANGLE_OF_COSINE = {6: 1, 7: 5, 8: 2}


@dataclass(frozen=True)
class TriadCase:
    """A triad with known errors seen in a position scheme with known noise.

    Attributes: triad; bias (3,) and scale (3,) normalized; angles (6,) rad;
    directions (n, 3) true unit reference directions; cov (n, 3, 3) covariance of each mean.
    """

    triad: Triad
    bias: np.ndarray
    scale: np.ndarray
    angles: np.ndarray
    directions: np.ndarray
    cov: np.ndarray

    @property
    def params(self) -> np.ndarray:
        return nine_params(self.bias, self.scale, sensor_axes(self.angles))

    @property
    def means_true(self) -> np.ndarray:
        return self.directions @ triad_matrix(self.scale, sensor_axes(self.angles)).T + self.bias

    def draw(self, rng: np.random.Generator, trials: int) -> np.ndarray:
        """(trials, n, 3) noisy means, all trials in one vectorized draw."""
        chol = np.linalg.cholesky(self.cov)
        noise = np.einsum(
            "nij,tnj->tni", chol, rng.standard_normal((trials, *self.directions.shape))
        )
        return self.means_true + noise

    def with_fault(self, j: int, delta: float) -> TriadCase:
        """The same triad with parameter ``j`` (PARAM_NAMES order) moved by about ``delta``."""
        if j < 3:
            return replace(self, bias=self.bias + delta * np.eye(3)[j])
        if j < 6:
            return replace(self, scale=self.scale + delta * np.eye(3)[j - 3])
        return replace(self, angles=self.angles + delta * np.eye(6)[_ANGLE_OF_COSINE[j]])


def _cov(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """Per-position diagonal covariances, axis variances spread over a factor 4 (exercises the weights)."""
    return np.einsum("ni,ij->nij", (sigma * rng.uniform(0.7, 1.4, (n, 3))) ** 2, np.eye(3))


def mems_accel(rng: np.random.Generator, n_positions: int = 18) -> TriadCase:
    """MEMS accelerometer: bias few mg, scale 2…6e-3, angles ~1e-3 rad; 1 mg per sample averaged over 1000."""
    return TriadCase(
        Triad.ACCEL,
        bias=np.array([3.0e-3, -2.0e-3, 4.0e-3]),
        scale=np.array([2.0e-3, -4.0e-3, 6.0e-3]),
        angles=rng.normal(0.0, 1.0e-3, 6),
        directions=scheme_directions(n_positions),
        cov=_cov(rng, n_positions, 1.0e-3 / np.sqrt(1000.0)),
    )


def nav_accel(rng: np.random.Generator, n_positions: int = 18) -> TriadCase:
    """Navigation-grade accelerometer: bias ~25 µg, scale ~50 ppm, angles ~2e-5 rad; 0.1 mg per sample over 6000."""
    return TriadCase(
        Triad.ACCEL,
        bias=np.array([25.0e-6, -30.0e-6, 20.0e-6]),
        scale=np.array([50.0e-6, -40.0e-6, 60.0e-6]),
        angles=rng.normal(0.0, 2.0e-5, 6),
        directions=scheme_directions(n_positions),
        cov=_cov(rng, n_positions, 1.0e-4 / np.sqrt(6000.0)),
    )


def nav_gyro(rng: np.random.Generator, n_positions: int = 18) -> TriadCase:
    """Navigation-grade gyro against Ω: bias ~0.01 °/h, scale ~20 ppm, angles ~2e-5 rad.

    Angle random walk 0.002 °/√h averaged over 300 s per position: 6.9e-3 °/h ≈ 4.6e-4 Ω per mean.
    """
    arw_deg_per_sqrt_h = 0.002
    sigma_deg_h = arw_deg_per_sqrt_h * 60.0 / np.sqrt(300.0)
    return TriadCase(
        Triad.GYRO,
        bias=np.array([0.01, -0.008, 0.012]) * DEG_PER_H_NORM,
        scale=np.array([2.0e-5, -1.0e-5, 3.0e-5]),
        angles=rng.normal(0.0, 2.0e-5, 6),
        directions=scheme_directions(n_positions),
        cov=_cov(rng, n_positions, sigma_deg_h * DEG_PER_H_NORM),
    )


def mems_gyro(
    rng: np.random.Generator, *, seconds_per_position: float, n_positions: int = 18
) -> TriadCase:
    """MEMS gyro against Ω: bias ~0.01 rad/s (≈ 140 Ω), noise 0.005 °/s/√Hz averaged over the position."""
    sigma_dps = 0.005 / np.sqrt(seconds_per_position)
    return TriadCase(
        Triad.GYRO,
        bias=np.array([0.01, -0.007, 0.012]) / EARTH_RATE_RPS,
        scale=np.array([3.0e-3, -2.0e-3, 4.0e-3]),
        angles=rng.normal(0.0, 1.0e-3, 6),
        directions=scheme_directions(n_positions),
        cov=_cov(rng, n_positions, sigma_dps * 3600.0 * DEG_PER_H_NORM),
    )


def single_axis_directions(
    axis: np.ndarray, n_positions: int, *, cone_deg: float = 90.0
) -> np.ndarray:
    """Directions reached by turning the unit about one ``axis``: a circle at ``cone_deg`` from it."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    c = np.cross(axis, a)
    phi = 2.0 * np.pi * np.arange(n_positions) / n_positions
    cone = np.radians(cone_deg)
    return np.cos(cone) * axis + np.sin(cone) * (
        np.outer(np.cos(phi), a) + np.outer(np.sin(phi), c)
    )


PASSPORT_G_MPS2 = 9.7953
"""Local gravity of :func:`synthetic_passport`'s accelerometer fit, m/s²."""


def synthetic_passport(seed: int) -> Passport:
    """A passport of a MEMS accelerometer and a navigation gyro fitted from one draw of their positions,
    with a quantization step and an accelerometer temperature model."""
    rng = np.random.default_rng(seed)
    accel, gyro = mems_accel(rng), nav_gyro(rng)
    estimates = {
        Triad.ACCEL: estimate_refined(
            accel.draw(rng, 1)[0], accel.cov, Triad.ACCEL, reference=PASSPORT_G_MPS2
        ),
        Triad.GYRO: estimate_refined(
            gyro.draw(rng, 1)[0], gyro.cov, Triad.GYRO, reference=EARTH_RATE_RPS
        ),
    }
    p = passport_from_estimates(
        estimates,
        unit_id="imu-0042",
        sensor_model="synthetic-9dof",
        sensor_ids={"accel": "A-17", "gyro": "G-23"},
        created="2024-05-01T12:00:00+00:00",
        noise_std={Triad.ACCEL: np.full(3, 1e-3), Triad.GYRO: np.full(3, 0.08)},
        sample_rate_hz=100.0,
        grade={Triad.ACCEL: Grade.MEMS, Triad.GYRO: Grade.NAVIGATION},
        quantization_step={Triad.ACCEL: np.full(3, 2.44e-4)},
    )
    temp = TemperatureModel(
        25.0,
        np.array([[1e-4, 2e-6, 0.0]] * 3),
        np.array([[0.0, 1e-5, -3e-8]] * 3),
        valid_min_c=-20.0,
        valid_max_c=60.0,
    )
    triads = {**p.triads, Triad.ACCEL: replace(p.triads[Triad.ACCEL], temperature=temp)}
    return Passport(p.unit_id, p.sensor_model, p.sensor_ids, p.created, triads)
