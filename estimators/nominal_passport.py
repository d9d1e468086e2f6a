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

Classes and their figures (bias, relative scale error, cross-axis cosine,
white-noise density; accelerometer / gyro):

* ``consumer_mems`` — the InvenSense MPU-6000 product specification (rev. 3.4,
  tables of accelerometer and gyroscope specifications): zero-g initial
  tolerance ±80 mg (z; ±50 mg x, y), sensitivity initial tolerance ±3 %,
  cross-axis sensitivity ±2 %, noise 400 µg/√Hz; zero-rate output ±20 °/s,
  sensitivity ±3 %, cross-axis ±2 %, rate noise 0.005 °/s/√Hz. These are the
  initial (factory) tolerances of the drone-autopilot class of IMU, the
  largest errors a healthy part shows before any calibration: the default.
* ``industrial_mems`` — the Analog Devices ADIS16470 data sheet (rev. C):
  rate noise density 0.008 °/s/√Hz; factory calibrated, so the residual
  errors are the repeatability floors of a calibrated MEMS unit of this project
  (:data:`estimators.passport.GRADE_FLOORS`, MEMS: 2 mg, 0.2 %, 1 mrad;
  20 °/h); accelerometer noise 0.1 mg/√Hz (the simulator's MEMS grade).
* ``tactical`` and ``navigation`` — the project's floors for those grades
  (:data:`estimators.passport.GRADE_FLOORS`, the turn-on and in-run
  repeatability of the grade) and the noise of the simulator's presets
  (:mod:`estimators.sim.grades`; tactical: 0.05 mg/√Hz, 0.15 °/√h).

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
    Grade,
    Triad,
)
from estimators.ninepar import Method
from estimators.passport import (
    GRADE_FLOORS,
    Passport,
    Provenance,
    TriadPassport,
    reference_kind,
)

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


def _floors(grade: Grade, accel_noise: float, gyro_noise: float, source: str) -> ClassTolerances:
    a = GRADE_FLOORS[(Triad.ACCEL, grade)]
    g = GRADE_FLOORS[(Triad.GYRO, grade)]
    return ClassTolerances(
        TriadTolerances(a[0], a[1], a[2], accel_noise),
        TriadTolerances(g[0], g[1], g[2], gyro_noise),
        source,
    )


CLASS_TOLERANCES: dict[SensorClass, ClassTolerances] = {
    SensorClass.CONSUMER_MEMS: ClassTolerances(
        TriadTolerances(80.0 * MPS2_PER_MG, 0.03, 0.02, 0.4 * MPS2_PER_MG),
        TriadTolerances(20.0 * _DEG, 0.03, 0.02, 0.005 * _DEG),
        "InvenSense MPU-6000 product specification rev. 3.4: initial tolerances",
    ),
    SensorClass.INDUSTRIAL_MEMS: _floors(
        Grade.MEMS,
        0.1 * MPS2_PER_MG,
        0.008 * _DEG,
        "ADIS16470 data sheet rev. C (rate noise); calibrated-MEMS floors of estimators.passport.GRADE_FLOORS",
    ),
    SensorClass.TACTICAL: _floors(
        Grade.TACTICAL,
        0.05 * MPS2_PER_MG,
        0.15 * _DEG / 60.0,
        "estimators.passport.GRADE_FLOORS (tactical); noise of a tactical-grade IMU",
    ),
    SensorClass.NAVIGATION: _floors(
        Grade.NAVIGATION,
        0.01 * MPS2_PER_MG,
        0.002 * _DEG / 60.0,
        "estimators.passport.GRADE_FLOORS (navigation); noise of estimators.sim.grades (navigation)",
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
