"""Presets of typical IMU grades for simulation.

Figures are typical datasheet orders of magnitude, not a particular product:

* MEMS (consumer / drone IMU, e.g. ICM-42688-, BMI088-class): accelerometer
  bias a few mg, scale errors ~0.3 %, noise about 1 mg per sample at 100 Hz,
  16-bit converter over ±8 g; gyro bias ~0.01 rad/s (≈ 2000 °/h, far above
  Ω ≈ 15 °/h, so the gyro scalar check of M1 is not applicable), noise
  ~0.005 °/s/√Hz, 16-bit over ±250 °/s.
* Navigation grade (ring-laser / high-end FOG with servo accelerometers):
  accelerometer bias ~25 µg, scale ~50 ppm, noise ~10 µg/√Hz; gyro bias
  0.01 °/h, scale ~10 ppm, angle random walk 0.002 °/√h, so Ω is resolved
  to ~1e-3 of itself in a minute of averaging.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators._typing import FloatArray
from estimators.conventions import MPS2_PER_MG, RPS_PER_DPH, STANDARD_GRAVITY_MPS2, Grade

from .errors import (
    Bias,
    ErrorModel,
    NonOrthogonality,
    Quantization,
    ScaleFactor,
    TriadErrorModel,
    WhiteNoise,
)

_DEG = np.pi / 180.0


@dataclass(frozen=True)
class TriadGrade:
    """Typical error sizes of one triad (SI; standard deviations of the population).

    Attributes
    ----------
    bias_sd_si : zero signal.
    scale_sd : relative scale-factor error.
    nonorth_sd_rad : each of the six non-orthogonality angles.
    noise_density_si : white noise, SI/√Hz.
    quant_step_si : count size, SI (None: no quantization).
    range_si : full scale, SI.
    """

    bias_sd_si: float
    scale_sd: float
    nonorth_sd_rad: float
    noise_density_si: float
    quant_step_si: float | None
    range_si: float


@dataclass(frozen=True)
class GradeSpec:
    accel: TriadGrade
    gyro: TriadGrade


GRADES: dict[Grade, GradeSpec] = {
    Grade.MEMS: GradeSpec(
        accel=TriadGrade(
            bias_sd_si=3.0 * MPS2_PER_MG,
            scale_sd=3.0e-3,
            nonorth_sd_rad=1.0e-3,
            noise_density_si=0.1 * MPS2_PER_MG,
            quant_step_si=16.0 * STANDARD_GRAVITY_MPS2 / 65536.0,
            range_si=8.0 * STANDARD_GRAVITY_MPS2,
        ),
        gyro=TriadGrade(
            bias_sd_si=0.01,
            scale_sd=3.0e-3,
            nonorth_sd_rad=1.0e-3,
            noise_density_si=0.005 * _DEG,
            quant_step_si=500.0 * _DEG / 65536.0,
            range_si=250.0 * _DEG,
        ),
    ),
    Grade.NAVIGATION: GradeSpec(
        accel=TriadGrade(
            bias_sd_si=0.025 * MPS2_PER_MG,
            scale_sd=50.0e-6,
            nonorth_sd_rad=20.0e-6,
            noise_density_si=0.01 * MPS2_PER_MG,
            quant_step_si=1.0e-5,
            range_si=40.0 * STANDARD_GRAVITY_MPS2,
        ),
        gyro=TriadGrade(
            bias_sd_si=0.01 * RPS_PER_DPH,
            scale_sd=10.0e-6,
            nonorth_sd_rad=10.0e-6,
            noise_density_si=0.002 * _DEG / 60.0,
            quant_step_si=1.0e-7,
            range_si=400.0 * _DEG,
        ),
    ),
}

# Fixed patterns (in units of the grade's standard deviation) for the
# deterministic preset: distinct per axis, mixed signs, so no parameter is zero
# and no two are equal.
_BIAS_PATTERN = np.array([1.0, -0.7, 0.4])
_SCALE_PATTERN = np.array([0.8, -0.5, 1.1])
_NONORTH_PATTERN = np.array([0.5, -1.0, 0.8, 0.3, -0.6, 1.2])


def _triad_model(
    g: TriadGrade, bias: FloatArray, scale: FloatArray, nonorth: FloatArray, *, quantization: bool
) -> TriadErrorModel:
    effects = [
        NonOrthogonality(nonorth),
        ScaleFactor(scale),
        Bias(bias),
        WhiteNoise((g.noise_density_si,) * 3),
    ]
    if quantization and g.quant_step_si is not None:
        effects.append(Quantization((g.quant_step_si,) * 3))
    return TriadErrorModel(tuple(effects))


def grade_error_model(
    grade: Grade, *, rng: np.random.Generator | None = None, quantization: bool = True
) -> ErrorModel:
    """The baseline error model of ``grade``: non-orthogonality, scale, bias, white noise, quantization.

    With ``rng`` the bias, scale and non-orthogonality are drawn from zero-mean
    normal laws with the grade's standard deviations; without it a fixed
    representative set is used (the same every time).
    """
    grade = Grade(grade)
    if grade not in GRADES:
        raise ValueError(
            f"no simulation preset for grade {grade.value!r} (presets: {', '.join(g.value for g in GRADES)})"
        )
    spec = GRADES[grade]

    def triad(g: TriadGrade) -> TriadErrorModel:
        if rng is None:
            draws = (_BIAS_PATTERN, _SCALE_PATTERN, _NONORTH_PATTERN)
        else:
            draws = (rng.standard_normal(3), rng.standard_normal(3), rng.standard_normal(6))
        return _triad_model(
            g,
            g.bias_sd_si * draws[0],
            g.scale_sd * draws[1],
            g.nonorth_sd_rad * draws[2],
            quantization=quantization,
        )

    return ErrorModel(accel=triad(spec.accel), gyro=triad(spec.gyro))
