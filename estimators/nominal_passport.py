"""Nominal passports by sensor class: F0 and the diagnosis for a unit that has no passport (methods.md M1).

A real log never comes with its unit's passport. M1's predicates only need a
nominal value and a tolerance per parameter, and a datasheet gives the
tolerances a healthy sensor of its class stays within: a *nominal passport*
puts every error parameter at 0 (an ideal triad) with the class's tolerances,
so that F0 (a static sample outside the shell ``|½(|ã|²−1)| ≤ λ0`` that these
tolerances and the class's noise allow) and, where the log holds enough static
positions, F1…F9 run. A unit outside them is outside what its whole class
guarantees: a finding, not a nuisance. A vehicle resting on the ground is a
static unit, so a pre-flight |a| far from g — the symptom of a bad
accelerometer calibration that both autopilots' pre-arm checks look for — fails F0.

Classes, their representative parts and where each figure comes from (bias,
relative scale error, cross-axis cosine, white-noise density; accelerometer /
gyro). A figure marked *class-typical* is not one datasheet's number but the
turn-on / in-run repeatability the project uses for the grade
(:data:`estimators.passport.GRADE_FLOORS`) or the noise of the simulator's
preset (:mod:`estimators.sim.grades`); every other figure is the part's as its
document states it, used as the tolerance without a further factor.

* ``consumer_mems`` (the drone-autopilot IMU; the default) — TDK InvenSense
  MPU-6000, product specification PS-MPU-6000A-00 rev. 3.4, accelerometer and
  gyroscope specification tables: zero-g initial calibration tolerance ±80 mg
  (z; ±50 mg x, y), sensitivity initial calibration tolerance ±3 %, cross-axis
  sensitivity ±2 %, noise power spectral density 400 µg/√Hz; zero-rate output
  initial tolerance ±20 °/s, sensitivity initial tolerance ±3 %, cross-axis
  sensitivity ±2 %, rate noise spectral density 0.005 °/s/√Hz. These are
  initial (factory) tolerances, the largest errors a healthy part shows before
  any calibration. A newer part of the class, the TDK InvenSense ICM-42688-P
  (datasheet DS-000347 rev. 1.7, features: 70 µg/√Hz, 2.8 mdps/√Hz), is quieter
  and stays inside these bounds.
* ``industrial_mems`` (factory-calibrated MEMS IMU modules) — Analog Devices
  ADIS16470 data sheet rev. C (features): rate noise density 0.008 °/s/√Hz;
  Analog Devices ADIS16475 data sheet (features, same family and factory
  calibration): axis-to-axis misalignment ±0.1° (1.75 mrad), used for both
  triads. Class-typical: bias 2 mg and 20 °/h, scale 0.2 %, accelerometer
  noise 100 µg/√Hz (the ADIS16470's own 13 µg and 8 °/h are in-run bias
  stabilities, the Allan minimum, not the turn-on bias a tolerance needs).
* ``tactical`` — Honeywell HG1700 (AG58, the higher-end model) brochure
  N61-1619-000-001, figures 1σ as quoted by NavToolkit's ``hg1700_model``:
  accelerometer bias 1 mg, velocity random walk 0.065 ft/s/√h (0.0198 m/s/√h,
  i.e. 33.7 µg/√Hz), gyro bias 1 °/h, angle random walk 0.125 °/√h
  (0.00208 °/s/√Hz). Class-typical (the brochure gives none): scale 300 ppm,
  cross-axis 0.2 mrad.
* ``navigation`` — Honeywell HG9900 brochure N61-1638-000-000, figures 1σ as
  quoted by NavToolkit's ``hg9900_model``: accelerometer bias 25 µg, scale
  factor 100 ppm; gyro bias 0.0035 °/h, scale factor 5 ppm, angle random walk
  0.002 °/√h. Class-typical (the brochure gives none): cross-axis 50 µrad
  (accelerometer) and 20 µrad (gyro), accelerometer noise 10 µg/√Hz.

The gyro parameters of a triad whose bias tolerance exceeds the Earth rate are
not observable (M1's gyro check needs a gyro that resolves Ω): they are marked
so and the diagnosis leaves them out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from estimators.conventions import (
    EARTH_RATE_RPS,
    MPS2_PER_MG,
    N_PARAMS,
    RPS_PER_DPH,
    STANDARD_GRAVITY_MPS2,
    Triad,
)
from estimators.ninepar import Method
from estimators.passport import Passport, Provenance, TriadPassport, reference_kind

_DEG = math.pi / 180.0
NOISE_REFERENCE_RATE_HZ = 2.0
"""The rate the nominal per-sample noise refers to: a density ``d`` per √Hz is ``d`` per sample at a
bandwidth of 1 Hz (Nyquist of 2 Hz); the pipeline scales it with the square root of the log's rate."""


class SensorClass(StrEnum):
    """Datasheet class of an IMU without a passport (module docstring)."""

    CONSUMER_MEMS = "consumer_mems"
    INDUSTRIAL_MEMS = "industrial_mems"
    TACTICAL = "tactical"
    NAVIGATION = "navigation"


@dataclass(frozen=True)
class TriadTolerances:
    """Tolerances of one triad of a class (SI): bias, relative scale error, cross-axis cosine, noise density."""

    bias_si: float
    scale: float
    cross_axis: float
    noise_density_si: float


@dataclass(frozen=True)
class ClassTolerances:
    """What a class guarantees, and where the figures come from."""

    accel: TriadTolerances
    gyro: TriadTolerances
    source: str

    def triad(self, triad: Triad) -> TriadTolerances:
        return self.accel if Triad(triad) is Triad.ACCEL else self.gyro


_FT = 0.3048
"""Metres per foot (HG1700's velocity random walk is in ft/s/√h)."""
_PER_RT_HOUR = 1.0 / 60.0
"""A random walk per √h is a white-noise density per √Hz divided by √3600 s."""

CLASS_TOLERANCES: dict[SensorClass, ClassTolerances] = {
    SensorClass.CONSUMER_MEMS: ClassTolerances(
        TriadTolerances(80.0 * MPS2_PER_MG, 0.03, 0.02, 0.4 * MPS2_PER_MG),
        TriadTolerances(20.0 * _DEG, 0.03, 0.02, 0.005 * _DEG),
        "TDK InvenSense MPU-6000 product specification PS-MPU-6000A-00 rev. 3.4: initial tolerances, noise",
    ),
    SensorClass.INDUSTRIAL_MEMS: ClassTolerances(
        TriadTolerances(2.0 * MPS2_PER_MG, 2.0e-3, 0.1 * _DEG, 0.1 * MPS2_PER_MG),
        TriadTolerances(20.0 * RPS_PER_DPH, 2.0e-3, 0.1 * _DEG, 0.008 * _DEG),
        "Analog Devices ADIS16470 data sheet rev. C (rate noise), ADIS16475 data sheet (misalignment);"
        " bias, scale and accelerometer noise class-typical",
    ),
    SensorClass.TACTICAL: ClassTolerances(
        TriadTolerances(1.0 * MPS2_PER_MG, 3.0e-4, 2.0e-4, 0.065 * _FT * _PER_RT_HOUR),
        TriadTolerances(1.0 * RPS_PER_DPH, 3.0e-4, 2.0e-4, 0.125 * _DEG * _PER_RT_HOUR),
        "Honeywell HG1700 (AG58) brochure N61-1619-000-001, 1 sigma (bias, random walks);"
        " scale and cross-axis class-typical",
    ),
    SensorClass.NAVIGATION: ClassTolerances(
        TriadTolerances(0.025 * MPS2_PER_MG, 1.0e-4, 5.0e-5, 0.01 * MPS2_PER_MG),
        TriadTolerances(0.0035 * RPS_PER_DPH, 5.0e-6, 2.0e-5, 0.002 * _DEG * _PER_RT_HOUR),
        "Honeywell HG9900 brochure N61-1638-000-000, 1 sigma (bias, scale, angle random walk);"
        " cross-axis and accelerometer noise class-typical",
    ),
}


def nominal_passport(
    sensor_class: SensorClass,
    *,
    gravity_mps2: float = STANDARD_GRAVITY_MPS2,
    unit_id: str = "nominal",
) -> Passport:
    """The nominal passport of ``sensor_class`` (module docstring): nominal errors 0, the class's tolerances.

    Parameters
    ----------
    sensor_class : the class.
    gravity_mps2 : local gravity, the accelerometers' reference, m/s².
    unit_id : identity written into the passport.
    """
    cls = SensorClass(sensor_class)
    if not math.isfinite(gravity_mps2) or gravity_mps2 <= 0.0:
        raise ValueError(f"gravity_mps2 must be a positive number, got {gravity_mps2!r}")
    figures = CLASS_TOLERANCES[cls]
    triads = {}
    for triad in (Triad.ACCEL, Triad.GYRO):
        tol = figures.triad(triad)
        reference = gravity_mps2 if triad is Triad.ACCEL else EARTH_RATE_RPS
        tolerance = np.repeat([tol.bias_si / reference, tol.scale, tol.cross_axis], 3)
        # A gyro whose bias tolerance exceeds Ω cannot be checked against Ω (M1): nothing is observable.
        observable = np.full(N_PARAMS, triad is Triad.ACCEL or tol.bias_si < EARTH_RATE_RPS)
        nominal = np.zeros(N_PARAMS)
        triads[triad] = TriadPassport(
            triad=triad,
            reference=reference,
            reference_kind=reference_kind(triad),
            nominal=nominal,
            tolerance=tolerance,
            sigma=np.zeros(N_PARAMS),
            observable=observable,
            noise_std=np.full(3, tol.noise_density_si / reference),
            sample_rate_hz=NOISE_REFERENCE_RATE_HZ,
            provenance=Provenance(
                Method.LINEAR,
                0,
                0.95,
                nominal,
                nominal,
                procedure=f"nominal passport, class {cls.value}: {figures.source}",
            ),
        )
    return Passport(
        unit_id=unit_id,
        sensor_model=f"nominal {cls.value}",
        sensor_ids={},
        created="2026-01-01",
        triads=triads,
    )


def describe_class(sensor_class: SensorClass) -> dict[str, object]:
    """The class's tolerances in the units a datasheet states them (for reports)."""
    f = CLASS_TOLERANCES[SensorClass(sensor_class)]
    return {
        "class": SensorClass(sensor_class).value,
        "source": f.source,
        "accel_bias_mg": f.accel.bias_si / MPS2_PER_MG,
        "accel_scale_pct": 100.0 * f.accel.scale,
        "accel_cross_axis_pct": 100.0 * f.accel.cross_axis,
        "accel_noise_ug_per_rthz": 1e3 * f.accel.noise_density_si / MPS2_PER_MG,
        "gyro_bias_dph": f.gyro.bias_si / RPS_PER_DPH,
        "gyro_scale_pct": 100.0 * f.gyro.scale,
        "gyro_cross_axis_pct": 100.0 * f.gyro.cross_axis,
        "gyro_noise_dps_per_rthz": f.gyro.noise_density_si / _DEG,
    }
