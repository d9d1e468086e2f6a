"""What every pipeline of a service shares: :class:`PipelineOptions` (from a service configuration: :func:`pipeline_options`), the severities of the events,
the chain's thresholds (package docstring) and the static detector's thresholds for a unit (:func:`detector_config`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from estimators.conventions import (
    DEFAULT_FALSE_ALARM_PROB,
    EARTH_RATE_RPS,
    STANDARD_GRAVITY_MPS2,
    Triad,
)
from estimators.passport import Passport
from estimators.positions import PositionConfig
from estimators.static_detector import StaticDetectorConfig
from estimators.validity_limits import (
    ValidityLimits,
)
from protocols.event_kinds import (  # not protocols.events: F0's configuration needs no schemas
    Predicate,
    Severity,
)

if TYPE_CHECKING:
    from service.config import ServiceConfig

PIPELINE_STATE_VERSION = 1

SEVERITY: dict[Predicate, Severity] = {
    Predicate.F0: Severity.WARNING,
    Predicate.STALE: Severity.CRITICAL,
    Predicate.TIMEOUT: Severity.WARNING,
    Predicate.ERROR_DENSITY: Severity.WARNING,
    Predicate.CROSS_IMU: Severity.WARNING,
    Predicate.TEMPERATURE: Severity.WARNING,
    Predicate.GROSS: Severity.ERROR,
    Predicate.THRUST_AXIS: Severity.ERROR,
    Predicate.CROSS_IMU_NORM: Severity.ERROR,
}
"""MAV_SEVERITY of each predicate's event: F0 says *that* a triad failed (warning); F1…F9 name the
sensor and the cause (:data:`FINDING_SEVERITY`), as the gross test does (an accelerometer off g or a
gyro off its zero signal at rest, whatever the passport), the thrust axis against GNSS in flight and
the cross-IMU norm (a scale or zero signal moved in flight); a stuck axis is critical; recoveries are
info."""

FINDING_SEVERITY = Severity.ERROR
TRIAD_WORD = {Triad.ACCEL: "accelerometer", Triad.GYRO: "gyro"}
RECOVERED_SEVERITY = Severity.INFO
RATE_PROBE_SAMPLES = 16
"""Samples collected before the sample rate (which sets the static detector's window) is measured."""
RATE_CHECK_SAMPLES = 128
"""Sample steps in one block of the rate watch: after the probe, each block's typical step
(:func:`estimators.stream_validity.typical_step_s`) is the stream's rate again (a burst at another
spacing, or a rate changed in flight, sized the detector wrong)."""
RATE_CHECK_BLOCKS = 4
"""Blocks in a row whose rate is off by more than :data:`RATE_CHECK_TOLERANCE` before the detector is
re-sized: 512 samples, so a burst of a few hundred samples stamped closer does not re-size it twice."""
RATE_CHECK_TOLERANCE = 0.25
"""Relative difference between a block's rate and the detector's beyond which the block is off."""
TIME_JUMP_PERIODS = 10
"""Sample periods between two samples beyond which the gap is counted as a time jump."""
CLOCK_RESET_FRAMES = 3
"""Consecutive rejected frames forming a consistent new stream after which the source is taken to have restarted."""
DETECTOR_NOISE_FACTOR = 3.0
"""Static detector thresholds at least this many times the unit's white-noise window spread."""
TEMPERATURE_HYSTERESIS_C = 1.0
"""The temperature must be back this far inside the model's range before the out-of-range event recovers
(at most a quarter of the range): a unit resting at the edge would otherwise flicker in and out with the
sensor's noise and quantization, one event pair each time."""
NOMINAL_MIN_RATE_HZ = 20.0
"""Slowest IMU stream a nominal passport is applied to (:meth:`ImuPipeline.passport_at`): the static
detector's 0.5 s window must hold enough samples to tell rest from a steady turn (a 4 Hz telemetry
stream holds two)."""
F0_SHELL_LIMIT = 1.0
"""A triad whose λ0 exceeds this cannot fail F0 meaningfully (the shell is thicker than the unit
sphere: a MEMS gyro against the Earth rate); F0 is then not run for it, and the status says why."""


@dataclass(frozen=True)
class PipelineOptions:
    """What every pipeline of a service shares.

    Attributes
    ----------
    gravity_mps2 : local gravity, the accelerometers' reference, m/s².
    gravity_rel_err : bound of its relative error (enters λ0, M1's reference term).
    false_alarm_probability : per-sample F0 false-alarm probability.
    f0_persistence_s : how long F0 must fail without a break before it is declared, s
        (:func:`estimators.scalar.persistent_failure`; at least one sample). A knock rings
        for a few ms; a sensor fault stays.
    diagnosis_false_alarm_probability : per-diagnosis probability of a false F1…F9 (estimators.diagnosis).
    min_positions : positions before F1…F9 are evaluated.
    validity : stream-validity and cross-IMU limits.
    detector : static detector thresholds.
    positions : position building options.
    """

    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    gravity_rel_err: float = 3.0e-3
    false_alarm_probability: float = 1.0e-9
    f0_persistence_s: float = 0.02
    diagnosis_false_alarm_probability: float = DEFAULT_FALSE_ALARM_PROB
    min_positions: int = 9
    validity: ValidityLimits = ValidityLimits()
    detector: StaticDetectorConfig = StaticDetectorConfig()
    positions: PositionConfig = PositionConfig()

    def reference(self, triad: Triad) -> float:
        return self.gravity_mps2 if Triad(triad) is Triad.ACCEL else EARTH_RATE_RPS


def detector_config(
    options: PipelineOptions, passport: Passport | None, rate_hz: float
) -> StaticDetectorConfig:
    """The static detector's thresholds for this unit at this rate.

    A quiet window's spread is about ``√3·σ`` for per-axis white noise σ, and σ grows with the
    square root of the rate; a threshold below the unit's own noise would call a resting unit
    moving. Each triad's threshold is therefore the larger of the configured one and
    :data:`DETECTOR_NOISE_FACTOR` × the spread of the passport's noise at ``rate_hz``
    (:meth:`estimators.static_detector.StaticDetectorConfig.from_noise`).

    A gyro F0 tests against the Earth rate (λ0 within :data:`F0_SHELL_LIMIT`: a navigation-grade
    one) also bounds a static window's mean rate about the passport's zero signal, at the largest
    rate F0's shell passes, ``Ω·√(1 + 2λ0)``, plus :data:`DETECTOR_NOISE_FACTOR` σ of the window
    mean. The spread threshold, made for MEMS gyros (0.02 rad/s, about 270 Ω), let the first and
    last 0.2 s of every turn (up to 0.016 rad/s) count as rest, and F0 failed there on a healthy
    unit. A bound on the mean, not a tighter spread: a gyro whose noise grows is still at rest and
    F0 finds it, and a zero signal beyond the bound, which this hides from F0, is the gross test's
    (no gate, bound about one Ω: :mod:`estimators.gross`).
    """
    from service.pipeline.triad_check import f0_threshold, f0_threshold_bound

    base = options.detector
    if passport is None:
        return base
    noise = {}
    for triad, tp in passport.triads.items():
        noise[triad] = float(
            tp.noise_std.max() * tp.reference * math.sqrt(rate_hz / tp.sample_rate_hz)
        )
    scaled = StaticDetectorConfig.from_noise(
        accel_noise_mps2=noise.get(Triad.ACCEL),
        gyro_noise_rps=noise.get(Triad.GYRO),
        factor=DETECTOR_NOISE_FACTOR,
        base=base,
    )
    out = replace(
        base,
        accel_std_mps2=max(base.accel_std_mps2, scaled.accel_std_mps2),
        gyro_std_rps=max(base.gyro_std_rps, scaled.gyro_std_rps),
    )
    gyro = passport.triads.get(Triad.GYRO)
    # A MEMS gyro's λ0 lower bound alone exceeds the limit: its exact λ0 (scipy) is not needed here.
    if gyro is None or f0_threshold_bound(gyro, options, rate_hz) > F0_SHELL_LIMIT:
        return out
    lambda0 = f0_threshold(gyro, options, rate_hz).lambda0
    if lambda0 > F0_SHELL_LIMIT:
        return out
    window_noise = noise[Triad.GYRO] / math.sqrt(base.window_samples(rate_hz))
    zero = gyro.nominal[:3] * gyro.reference
    return replace(
        out,
        gyro_rate_rps=EARTH_RATE_RPS * math.sqrt(1.0 + 2.0 * lambda0)
        + DETECTOR_NOISE_FACTOR * window_noise,
        gyro_rate_centre_rps=(float(zero[0]), float(zero[1]), float(zero[2])),
    )


def pipeline_options(config: ServiceConfig) -> PipelineOptions:
    """The pipelines' options from the service configuration."""
    site = config.site
    # A configured gravity (measured or WGS-84 at the site) is good to ~1e-4; standard gravity to ~3e-3.
    rel_err = 1.0e-4 if (site.gravity_mps2 is not None or site.latitude_deg is not None) else 3.0e-3
    return PipelineOptions(
        gravity_mps2=site.local_gravity_mps2,
        gravity_rel_err=rel_err,
        false_alarm_probability=config.pipeline.false_alarm_probability,
        f0_persistence_s=config.pipeline.f0_persistence_s,
        diagnosis_false_alarm_probability=DEFAULT_FALSE_ALARM_PROB,
        min_positions=config.pipeline.min_positions,
        validity=config.validity,
    )
