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
  gyroscope specification tables: zero-g initial calibration tolerance ±50 mg
  (x, y) and ±80 mg (z), sensitivity initial calibration tolerance ±3 %,
  cross-axis sensitivity ±2 %, noise power spectral density 400 µg/√Hz; zero-rate output
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

From the datasheet to the passport
----------------------------------
A datasheet's errors act on the output as ``ã = (I + S + C) u + b`` (``u`` the
unit reference direction): ``b`` the zero signals (per axis, as stated), ``S``
the diagonal of sensitivity errors, ``C`` the cross-axis sensitivities off the
diagonal. The nine parameters of M1 (:mod:`estimators.conventions`) are their
image: ``bᵢ`` the zero-signal limit over the reference, ``eᵢ`` the sensitivity
limit, and ``δ = sᵢ·sⱼ``, the cosine of two sensitive axes, which is
``C_ij + C_ji`` to first order: twice a per-sensor cross-axis sensitivity (two
axes may lean toward each other), the figure itself for an axis-to-axis
misalignment (:attr:`TriadTolerances.cosine`). The two boxes agree to first
order; their second-order difference is at most ``max eᵢ · max δ`` in ``s``
(0.0012 for consumer MEMS).

The F0 shell they imply
-----------------------
F0's shell (:func:`estimators.scalar.derive_lambda0`) is the exact worst ``|s|``,
``s = ½(|ã|² − 1)``, over every orientation and every unit within these limits
(:func:`estimators.scalar.tolerance_extremes`), plus the noise term at the
stated false-alarm probability and the reference term. Accelerometers, the
pipeline's defaults (1e-9 per sample, ``|g|`` known to 0.3 %), λ0 in ``s`` (≈ |a|/g − 1):

==================  =========  ======  =======  =======  ====================
class               tolerance  50 Hz   200 Hz   1000 Hz  worst unit, |a|/g−1
==================  =========  ======  =======  =======  ====================
consumer_mems       0.1911     0.2063  0.2186   0.2494   +0.175 / −0.160
industrial_mems     0.0072     0.0133  0.0164   0.0239
tactical            0.0022     0.0063  0.0073   0.0098
navigation          0.0002     0.0035  0.0038   0.0046
==================  =========  ======  =======  =======  ====================

The consumer worst unit reads 17.5 % of g: all three zero signals (√(50² + 50²
+ 80²) = 106 mg along their common direction), +3 % on every axis and +2 % in
all six cross-axis entries, with gravity along ``(1, 1, 1)/√3``. A resting unit
whose z reads 1.2 g (s = 0.22) is outside the shell at 50 and 200 Hz; at rates
whose per-sample noise term exceeds 0.026 (above about 220 Hz) per-sample F0
cannot tell it from the worst healthy unit, and only a test on window means
(the gross plausibility test) can. A unit reading 0.35 g (s = −0.44) is outside
at every rate.

Noise
-----
The noise densities are *typical* values (no datasheet states a limit); a
healthy unit may be noisier. F0's noise term uses the class figure as the
passport carries it, scaled to the stream's rate, and is not widened for a
stream that is noisier: the tolerance term already stands for the worst corner
of every limit at once, which real units are far from (the shared logs' units
rest within 1.8 % of g, a tenth of it), so a healthy unit 3× noisier than the
class figure stays inside the shell (3σ of its ``s`` is 0.036 at 200 Hz, against
the 0.19 the tolerances allow), while widening the term by the stream's noise
would let the noisier unit's 1.2 g pass (λ0 0.269 at 200 Hz). Only a unit at
the corner of every limit at once and 3× noisier would fail a sample now and
then, and F0 needs ``persist`` failing samples in a row.
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
    """Tolerances of one triad of a class (SI): the datasheet's limits (module docstring).

    Attributes
    ----------
    bias_si : (x, y, z) zero-signal limit of each axis (m/s² or rad/s).
    scale : relative scale-error limit of every axis.
    cross_axis : cross-axis figure as the document states it (relative).
    noise_density_si : white-noise density per √Hz, *typical* (no datasheet states a limit).
    per_sensor : True: ``cross_axis`` is each sensor's sensitivity to each other axis (two axes
        may lean toward each other: their cosine is up to twice it); False: an axis-to-axis figure,
        the cosine itself.
    """

    bias_si: tuple[float, float, float]
    scale: float
    cross_axis: float
    noise_density_si: float
    per_sensor: bool = False

    @property
    def cosine(self) -> float:
        """Bound of M1's non-orthogonality cosine ``δ = sᵢ·sⱼ`` (:mod:`estimators.conventions`)."""
        return 2.0 * self.cross_axis if self.per_sensor else self.cross_axis


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


def _axes(x: float, y: float | None = None, z: float | None = None) -> tuple[float, float, float]:
    """Per-axis figures; one figure for all three where the document states one."""
    return (x, x if y is None else y, x if z is None else z)


CLASS_TOLERANCES: dict[SensorClass, ClassTolerances] = {
    SensorClass.CONSUMER_MEMS: ClassTolerances(
        TriadTolerances(
            _axes(50.0 * MPS2_PER_MG, 50.0 * MPS2_PER_MG, 80.0 * MPS2_PER_MG),
            0.03,
            0.02,
            0.4 * MPS2_PER_MG,
            per_sensor=True,
        ),
        TriadTolerances(_axes(20.0 * _DEG), 0.03, 0.02, 0.005 * _DEG, per_sensor=True),
        "TDK InvenSense MPU-6000 product specification PS-MPU-6000A-00 rev. 3.4: initial tolerances, noise",
    ),
    SensorClass.INDUSTRIAL_MEMS: ClassTolerances(
        TriadTolerances(_axes(2.0 * MPS2_PER_MG), 2.0e-3, 0.1 * _DEG, 0.1 * MPS2_PER_MG),
        TriadTolerances(_axes(20.0 * RPS_PER_DPH), 2.0e-3, 0.1 * _DEG, 0.008 * _DEG),
        "Analog Devices ADIS16470 data sheet rev. C (rate noise), ADIS16475 data sheet (misalignment);"
        " bias, scale and accelerometer noise class-typical",
    ),
    SensorClass.TACTICAL: ClassTolerances(
        TriadTolerances(_axes(1.0 * MPS2_PER_MG), 3.0e-4, 2.0e-4, 0.065 * _FT * _PER_RT_HOUR),
        TriadTolerances(_axes(1.0 * RPS_PER_DPH), 3.0e-4, 2.0e-4, 0.125 * _DEG * _PER_RT_HOUR),
        "Honeywell HG1700 (AG58) brochure N61-1619-000-001, 1 sigma (bias, random walks);"
        " scale and cross-axis class-typical",
    ),
    SensorClass.NAVIGATION: ClassTolerances(
        TriadTolerances(_axes(0.025 * MPS2_PER_MG), 1.0e-4, 5.0e-5, 0.01 * MPS2_PER_MG),
        TriadTolerances(_axes(0.0035 * RPS_PER_DPH), 5.0e-6, 2.0e-5, 0.002 * _DEG * _PER_RT_HOUR),
        "Honeywell HG9900 brochure N61-1638-000-000, 1 sigma (bias, scale, angle random walk);"
        " cross-axis and accelerometer noise class-typical",
    ),
}


def nominal_passport(
    sensor_class: SensorClass,
    *,
    gravity_mps2: float = STANDARD_GRAVITY_MPS2,
    unit_id: str | None = None,
) -> Passport:
    """The nominal passport of ``sensor_class`` (module docstring): nominal errors 0, the class's tolerances.

    Parameters
    ----------
    sensor_class : the class.
    gravity_mps2 : local gravity, the accelerometers' reference, m/s².
    unit_id : identity written into the passport; default ``nominal-<class>``, which a
        checkpoint records (:meth:`service.pipeline.ImuPipeline.state_dict`): a state made
        against one class's passport is not resumed against another's.
    """
    cls = SensorClass(sensor_class)
    if not math.isfinite(gravity_mps2) or gravity_mps2 <= 0.0:
        raise ValueError(f"gravity_mps2 must be a positive number, got {gravity_mps2!r}")
    figures = CLASS_TOLERANCES[cls]
    triads = {}
    for triad in (Triad.ACCEL, Triad.GYRO):
        tol = figures.triad(triad)
        reference = gravity_mps2 if triad is Triad.ACCEL else EARTH_RATE_RPS
        tolerance = np.r_[np.array(tol.bias_si) / reference, [tol.scale] * 3, [tol.cosine] * 3]
        # A gyro whose bias tolerance exceeds Ω cannot be checked against Ω (M1): nothing is observable.
        observable = np.full(N_PARAMS, triad is Triad.ACCEL or max(tol.bias_si) < EARTH_RATE_RPS)
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
        unit_id=f"nominal-{cls.value}" if unit_id is None else unit_id,
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
        "accel_bias_mg": [b / MPS2_PER_MG for b in f.accel.bias_si],
        "accel_scale_pct": 100.0 * f.accel.scale,
        "accel_cross_axis_pct": 100.0 * f.accel.cross_axis,
        "accel_noise_ug_per_rthz": 1e3 * f.accel.noise_density_si / MPS2_PER_MG,
        "gyro_bias_dph": [b / RPS_PER_DPH for b in f.gyro.bias_si],
        "gyro_scale_pct": 100.0 * f.gyro.scale,
        "gyro_cross_axis_pct": 100.0 * f.gyro.cross_axis,
        "gyro_noise_dps_per_rthz": f.gyro.noise_density_si / _DEG,
    }
