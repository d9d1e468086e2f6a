"""Summaries of the health figures an autopilot logs itself, judged by the firmware's own thresholds.

An autopilot measures vibration and clipping on its sensors' own samples (kHz), where a log's IMU
messages hold a few tens to hundreds of Hz: the firmware's figures see what a recomputation from
the logged samples cannot (:mod:`estimators.log_health`). Pure functions on arrays, SI.

* ArduPilot ``VIBE`` (DataFlash) and MAVLink ``VIBRATION``: per axis, the square root of the
  2 Hz low-passed square of the accelerometer's difference from its 5 Hz low-pass, m/s²
  (``AP_InertialSensor::calc_vibration_and_clipping``); clip counters grow by one at each
  accelerometer sample at the end of its range. Thresholds: ArduPilot wiki, *Measuring
  Vibration* (:data:`ARDUPILOT_VIBE_SOURCE`).
* PX4 ``vehicle_imu_status``: ``accel_vibration_metric`` ``m ← 0.99·m + 0.01·|x_k − x_{k−1}|`` at
  the IMU's integration rate (``VehicleIMU::UpdateAccelVibrationMetrics``), on the delta velocity
  (m/s) in releases whose topic has ``gyro_coning_vibration``, on the acceleration (m/s²) in
  those with ``delta_angle_coning_metric``; the gyro metric likewise (rad or rad/s); coning
  ``|Δθ_k × Δθ_{k−1}|`` filtered (rad²); ``accel_clipping``/``gyro_clipping`` cumulative per axis.
  Thresholds: PX4 Flight Review's vibration plot (:data:`PX4_VIBE_SOURCE`); PX4 states none for
  the gyro and coning metrics.
* ArduPilot batch sampler (``ISBH``/``ISBD``): blocks of a sensor's raw samples at its sample rate
  (int16 ``value × mul``): noise from the first difference ``rms(x_k − x_{k−1})/√2`` (σ for white
  noise), Welch spectra within each block, and samples at the int16 limit (saturated).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators._typing import FloatArray

ARDUPILOT_VIBE_LIMITS_MPS2 = (30.0, 60.0)
ARDUPILOT_VIBE_SOURCE = (
    "ArduPilot wiki, Measuring Vibration: VIBE below 30 m/s² is normally acceptable, "
    "above 30 may give problems, above 60 nearly always does"
)
ARDUPILOT_CLIP_SOURCE = (
    "ArduPilot wiki, Measuring Vibration: clip counters should stay at zero; fewer than 100 "
    "are likely fine at hard landings, a count that keeps growing is a serious vibration problem"
)
PX4_ACCEL_VIBE_LIMITS = {"m/s": (0.02, 0.04), "m/s^2": (4.905, 9.81)}
"""The orange and red limits of PX4 Flight Review's vibration plot (``app/plot_app/configured_plots.py``,
``add_horizontal_background_boxes``): 4.905 and 9.81 m/s² for the acceleration metric; 0.02 and
0.04 m/s for the delta-velocity metric of earlier releases (its plot of ``estimator_status.vibe[2]``,
the same filtered |Δv_k − Δv_{k−1}|)."""
PX4_VIBE_SOURCE = "PX4 Flight Review, vibration metrics plot (green, orange, red)"
BATCH_SATURATED = 32767
"""An ``ISBD`` sample at the int16 limit (either sign): the value times ``mul`` did not fit, the sensor
or the log saturated."""


@dataclass(frozen=True)
class LevelSummary:
    """A logged level over the log: median and maximum, per axis when it has axes; ``above``: the
    messages above each limit; ``not_finite``: messages left out for a NaN or infinite value
    (:func:`level_summary`)."""

    n: int
    median: list[float]
    max: list[float]
    above: dict[str, int]
    not_finite: int = 0


def level_summary(values: FloatArray, limits: tuple[float, ...] = ()) -> LevelSummary:
    """Median and maximum of ``values`` ((N,) or (N, axes)) and how many rows exceed each limit on
    any axis; rows with a value that is not finite are left out and counted."""
    v = np.asarray(values, dtype=float)
    v2 = v.reshape(v.shape[0], -1)
    finite = np.isfinite(v2).all(axis=1)
    v2 = v2[finite]
    worst = v2.max(axis=1) if v2.size else np.zeros(0)
    return LevelSummary(
        not_finite=int((~finite).sum()),
        n=int(v2.shape[0]),
        median=[float(x) for x in np.median(v2, axis=0)] if v2.size else [],
        max=[float(x) for x in v2.max(axis=0)] if v2.size else [],
        above={f"{limit:g}": int((worst > limit).sum()) for limit in limits},
    )


def counter_growth(values: FloatArray) -> int:
    """How much a cumulative counter grew over the log, from its first value (which may hold counts
    from before the log). A value lower than the one before is a counter cleared since (a reboot):
    it counts from zero there."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]  # a value that is no count says nothing of the growth
    if v.size < 2:
        return 0
    step = np.diff(v)
    return int(np.where(step >= 0.0, step, v[1:]).sum())


def counter_start(values: FloatArray) -> int:
    """A cumulative counter's first value: what it had counted before the log began (since the
    autopilot booted; a ground station's log starts when it connects). 0 without a finite value."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return int(v[0]) if v.size else 0


@dataclass(frozen=True)
class BatchStream:
    """One sensor's batch-sampler data (:class:`BatchStreamAccumulator`): samples, blocks, rate, noise
    per axis, the Welch spectrum averaged over the blocks, and the samples at the int16 limit."""

    samples: int
    blocks: int
    unusable_blocks: int
    rate_hz: float
    noise: list[float]
    freq_hz: FloatArray
    psd: FloatArray
    saturated: int


class BatchStreamAccumulator:
    """Noise and spectra of a sensor's batch-sampler blocks, block by block (bounded memory).

    :meth:`add` takes one block: samples (n, 3) in SI at ``rate_hz``, and how many of its raw values
    were at the int16 limit; a block of fewer than two samples, no finite positive rate or a value
    that is not finite (a multiplier of 0) gives no noise or spectrum and is counted unusable. Noise: the first difference within each block (module docstring),
    pooled over the blocks; spectra: Welch's average of Hann-windowed periodograms of ``nfft``
    samples within each block (none crosses the gap between two blocks), averaged over the blocks
    of ``nfft`` samples or more; one-sided PSD (unit²/Hz).
    """

    def __init__(self, nfft: int = 256) -> None:
        self.nfft = nfft
        self._samples = 0
        self._blocks = 0
        self._saturated = 0
        self._unusable = 0
        self._rates: list[float] = []
        self._diff_sq = np.zeros(3)
        self._diff_n = 0
        self._psd_sum: FloatArray | None = None
        self._psd_n = 0
        self._freq = np.zeros(0)

    def add(self, x: FloatArray, rate_hz: float, saturated: int) -> None:
        self._samples += x.shape[0]
        self._blocks += 1
        self._saturated += saturated
        if x.shape[0] < 2 or not 0.0 < rate_hz < math.inf or not np.isfinite(x).all():
            self._unusable += 1
            return
        self._rates.append(rate_hz)
        d = np.diff(x, axis=0)
        self._diff_sq += (d**2).sum(axis=0)
        self._diff_n += d.shape[0]
        if x.shape[0] >= self.nfft:
            # Only a log with batch-sampler blocks pays for scipy.signal (0.46 s of CPU to import).
            from scipy.signal import welch

            self._freq, p = welch(x, fs=rate_hz, window="hann", nperseg=self.nfft, axis=0)
            self._psd_sum = p if self._psd_sum is None else self._psd_sum + p
            self._psd_n += 1

    def result(self) -> BatchStream:
        noise = np.sqrt(self._diff_sq / max(self._diff_n, 1) / 2.0) if self._diff_n else None
        return BatchStream(
            samples=self._samples,
            blocks=self._blocks,
            unusable_blocks=self._unusable,
            rate_hz=float(np.median(self._rates)) if self._rates else 0.0,
            noise=[] if noise is None else [float(v) for v in noise],
            freq_hz=self._freq,
            psd=np.zeros((0, 3)) if self._psd_sum is None else self._psd_sum / self._psd_n,
            saturated=self._saturated,
        )
