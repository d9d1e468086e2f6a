"""Health figures of a logged IMU, streamed in bounded memory: rate, gaps, rest, noise, vibration, spectra.

What a log analyst reads from a flight review, computed batch by batch so a
one-hour 1 kHz log needs no more memory than a minute of it
(:class:`ImuHealthAccumulator`; SI in, SI out, :mod:`estimators.conventions`).

Blocks and rest
---------------
Samples are grouped into blocks of ``block_s`` (0.5 s, the static detector's
window) on the log's absolute time grid (block ``k`` is ``[k·B, (k+1)·B)``), so
the blocks of two IMUs line up. A block is *at rest* when it is full (at least
80 % of the samples the median rate gives, and at least :data:`MIN_REST_SAMPLES`) and quiet by the static detector's
test (:mod:`estimators.static_detector`): its window spread
``sqrt(Σᵢ varᵢ)`` within ``accel_rest_mps2`` and ``gyro_rest_rps``. Per block
the accumulator keeps the means, variances and vibration levels; everything
else is derived from that table.

Figures
-------
* noise per axis: at rest, the pooled within-block standard deviation
  ``sqrt(Σ(n−1)var / Σ(n−1))`` (M1's per-sample noise) of the settled blocks: a block
  at rest whose standard deviation on any axis is more than :data:`SETTLING_SPREAD_RATIO`
  times the median rest block's is still settling (the ringing after a landing or a knock,
  within the detector's spread) and does not enter it (``settling_blocks``); on an output
  quantized below its noise the median is at least half a step (the smallest change between
  consecutive samples): one count's flip is no ringing; with no rest, from the
  first difference (a high-pass): ``rms(x_k − x_{k−1}) / √2``, equal to σ for
  white noise; ``noise_method`` says which.
* at rest: ``gravity_residual_mps2`` = |mean a| − g per block (median and the
  largest magnitude; the quantity F0 bounds, methods.md M1) and
  ``gyro_bias_rps``, the mean gyro output.
* vibration, as ArduPilot's VIBE defines it
  (``libraries/AP_InertialSensor/AP_InertialSensor.cpp``,
  ``calc_vibration_and_clipping`` and ``get_vibration_levels``): the
  accelerometer is low-passed at 5 Hz (the "vibe floor"), the squared
  difference from it is low-passed at 2 Hz, the level is its square root,
  per axis, m/s² (first-order low-passes, ``α = dt/(dt + 1/(2π f_c))``).
* vibration, as PX4 defines it (``src/modules/sensors/vehicle_imu/VehicleIMU.cpp``,
  ``UpdateAccelVibrationMetrics``/``UpdateGyroVibrationMetrics``):
  ``m ← 0.99·m + 0.01·|Δv_k − Δv_{k−1}|`` with ``Δv = a·dt`` (m/s; gyro:
  ``Δθ = ω·dt``, rad), here at the log's rate (PX4 runs it at the IMU's
  integration rate).
  Vibration figures are taken over the blocks not at rest (in flight): median
  and maximum of the block means.
* spectra: Welch's average of Hann-windowed, mean-removed periodograms of
  ``nfft`` samples over the whole log, one-sided power spectral density per
  axis ((m/s²)²/Hz, (rad/s)²/Hz).
* rate: the median sample interval (µs resolution); gaps: intervals longer
  than 1.5 median intervals (count and the longest).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.first_order_filter import first_order_filter

VIBE_FLOOR_HZ = 5.0
VIBE_FILTER_HZ = 2.0
PX4_VIBE_ALPHA = 0.01
GAP_PERIODS = 1.5
FULL_BLOCK = 0.8
SETTLING_SPREAD_RATIO = 2.0
"""A block at rest with a standard deviation this many times the median rest block's, on any axis, is
settling, not noise: for white noise the sample standard deviation of a block of ``MIN_REST_SAMPLES``
(7 degrees of freedom) exceeds twice σ with probability 2·10⁻⁴ (χ²₇ > 28), of 100 samples never."""
MIN_REST_SAMPLES = 8
"""Fewest samples a block needs to be judged at rest: a variance of two or three samples says nothing
(a 4 Hz telemetry log in a steady turn would pass)."""
PASS_SAMPLES = 4096
"""Samples of consecutive frames taken in one pass (:meth:`ImuHealthAccumulator.update`): the
filters, block tables and periodograms carry their state sample to sample, so one pass over the
frames gives what a pass per frame gives, with a tenth of the calls on 100-sample frames."""
RUN_START_SAMPLES = 100
"""A run's first samples whose median step sets the filters' sample interval, and the blocks of the
first difference's sum of squares, counted from the run's start: the figures then do not depend on
how the samples are cut into frames (these are the frames of 100 that replay handed the report
before it took larger ones, so its figures stay those it gave)."""
PSD_GROUP_SAMPLES = -(-PASS_SAMPLES // RUN_START_SAMPLES) * RUN_START_SAMPLES
"""The periodograms are summed in groups, the group's sum then added to the total: those a run
completes in its first :data:`RUN_START_SAMPLES` samples, then in each ``PSD_GROUP_SAMPLES`` after.
These are the passes its frames of 100 made (one, then :data:`PASS_SAMPLES` of them queued), so
the spectra keep the bits they had then, whatever the framing and the passes now."""
_BLOCK_FIELDS = 27  # k, n, mean a(3), mean g(3), var a(3), var g(3), vibe(3), vibe max(3), px4 a, px4 g, temp min, max, t first, t last, run


@dataclass(frozen=True)
class HealthConfig:
    """Block length and rest thresholds (module docstring); ``nfft`` samples per periodogram."""

    block_s: float = 0.5
    accel_rest_mps2: float = 0.05
    gyro_rest_rps: float = 0.02
    nfft: int = 256

    def __post_init__(self) -> None:
        for name in ("block_s", "accel_rest_mps2", "gyro_rest_rps"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                raise ValueError(f"HealthConfig.{name} must be positive, got {value!r}")
        if self.nfft < 8:
            raise ValueError(f"HealthConfig.nfft must be at least 8, got {self.nfft!r}")


@dataclass(frozen=True)
class Blocks:
    """The block table of one IMU (module docstring); arrays of K blocks, SI."""

    k: FloatArray
    n: FloatArray
    accel_mean: FloatArray
    gyro_mean: FloatArray
    accel_var: FloatArray
    gyro_var: FloatArray
    vibe_mean: FloatArray
    vibe_max: FloatArray
    px4_accel: FloatArray
    px4_gyro: FloatArray
    temp_min: FloatArray
    temp_max: FloatArray
    full: BoolArray
    """Blocks with samples enough to be judged at rest or not (``FULL_BLOCK`` of a block, at least ``MIN_REST_SAMPLES``)."""
    rest: BoolArray
    run: IntArray
    """The run of each block: 0, and one more each time the clock started again (``k`` repeats across runs)."""


@dataclass(frozen=True)
class ImuHealth:
    """Health figures of one IMU (module docstring); ``to_dict`` gives the report's plain form."""

    n_samples: int
    runs: int
    rate_hz: float
    duration_s: float
    gap_count: int
    longest_gap_s: float
    rest_s: float
    settling_blocks: int
    noise_method: str
    accel_noise_mps2: FloatArray
    gyro_noise_rps: FloatArray
    gravity_residual_median_mps2: float | None
    gravity_residual_max_abs_mps2: float | None
    gyro_bias_rps: FloatArray | None
    vibe_median_mps2: FloatArray | None
    vibe_max_mps2: FloatArray | None
    px4_accel_vibration_median_mps: float | None
    px4_accel_vibration_max_mps: float | None
    px4_gyro_vibration_median_rad: float | None
    px4_gyro_vibration_max_rad: float | None
    temp_min_c: float | None
    temp_max_c: float | None
    freq_hz: FloatArray
    accel_psd: FloatArray
    gyro_psd: FloatArray
    blocks: Blocks
    config: HealthConfig

    def to_dict(self) -> dict[str, Any]:
        def vec(v: FloatArray | None) -> list[float] | None:
            return None if v is None else [float(x) for x in v]

        return {
            "n_samples": self.n_samples,
            "runs": self.runs,
            "rate_hz": self.rate_hz,
            "duration_s": self.duration_s,
            "gaps": {"count": self.gap_count, "longest_s": self.longest_gap_s},
            "rest_s": self.rest_s,
            "rest_test": {
                "block_s": self.config.block_s,
                "accel_spread_mps2": self.config.accel_rest_mps2,
                "gyro_spread_rps": self.config.gyro_rest_rps,
                "settling_spread_ratio": SETTLING_SPREAD_RATIO,
            },
            "settling_blocks": self.settling_blocks,
            "noise_method": self.noise_method,
            "accel_noise_mps2": vec(self.accel_noise_mps2),
            "gyro_noise_rps": vec(self.gyro_noise_rps),
            "gravity_residual_mps2": None
            if self.gravity_residual_median_mps2 is None
            else {
                "median": self.gravity_residual_median_mps2,
                "max_abs": self.gravity_residual_max_abs_mps2,
            },
            "gyro_bias_rps": vec(self.gyro_bias_rps),
            "vibration": {
                "ardupilot_vibe_mps2": None
                if self.vibe_median_mps2 is None
                else {"median": vec(self.vibe_median_mps2), "max": vec(self.vibe_max_mps2)},
                "px4_accel_vibration_metric_mps": None
                if self.px4_accel_vibration_median_mps is None
                else {
                    "median": self.px4_accel_vibration_median_mps,
                    "max": self.px4_accel_vibration_max_mps,
                },
                "px4_gyro_vibration_metric_rad": None
                if self.px4_gyro_vibration_median_rad is None
                else {
                    "median": self.px4_gyro_vibration_median_rad,
                    "max": self.px4_gyro_vibration_max_rad,
                },
            },
            "temperature_c": None
            if self.temp_min_c is None
            else {"min": self.temp_min_c, "max": self.temp_max_c},
        }


@dataclass
class _Carry:
    t: FloatArray = field(default_factory=lambda: np.zeros(0))
    a: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    g: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    temp: FloatArray = field(default_factory=lambda: np.zeros(0))
    vibe: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    px4a: FloatArray = field(default_factory=lambda: np.zeros(0))
    px4g: FloatArray = field(default_factory=lambda: np.zeros(0))


class ImuHealthAccumulator:
    """Streams one IMU's samples into its health figures (module docstring).

    :meth:`update` takes consecutive samples in time order (``t_s`` (N,) increasing, ``accel_mps2``
    and ``gyro_rps`` (N, 3), ``temp_c`` (N,) or None); :meth:`result` gives :class:`ImuHealth`.
    Samples that start at or before the last one are a clock that started again (an autopilot
    reboot, logs joined): a new run, whose blocks, intervals and filters start afresh.
    Memory: the block table (about 200 bytes per ``block_s``), one periodogram per axis and the
    frames waiting for their pass (:data:`PASS_SAMPLES`).
    """

    def __init__(self, config: HealthConfig = HealthConfig()) -> None:
        self.config = config
        self.n_samples = 0
        self._run = 0
        self._runs_s = 0.0
        """The duration of the runs before this one, s."""
        self._t_first: float | None = None
        self._t_last: float | None = None
        self._last_a: FloatArray | None = None
        self._last_g: FloatArray | None = None
        self._dt_us: dict[int, int] = {}
        self._dt_s: float | None = None
        self._zi: dict[str, FloatArray] = {}
        self._carry = _Carry()
        self._tables: list[FloatArray] = []
        self._welch_buf: list[FloatArray] = []
        self._welch_n = 0
        self._welch_segs = 0
        """Periodogram segments the run has completed."""
        self._psd_sum: FloatArray | None = None
        self._psd_open: FloatArray | None = None
        """The sum of the periodograms of the group (:data:`PSD_GROUP_SAMPLES`) not yet complete."""
        self._psd_group = 0
        self._psd_count = 0
        self._diff_sq = np.zeros(6)
        self._diff_open = np.zeros(6)
        """The sum of squares of the run's block of :data:`RUN_START_SAMPLES` not yet complete."""
        self._diff_open_n = 0
        self._diff_n = 0
        self._step = np.full(6, np.inf)
        """The smallest change between consecutive samples per axis: the output's step, if quantized."""
        self._pending: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None = None
        self._queue: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]] = []
        self._queued = 0

    def update(
        self,
        t_s: FloatArray,
        accel_mps2: FloatArray,
        gyro_rps: FloatArray,
        temp_c: FloatArray | None = None,
    ) -> None:
        t = np.asarray(t_s, dtype=float)
        a = np.asarray(accel_mps2, dtype=float).reshape(-1, 3)
        g = np.asarray(gyro_rps, dtype=float).reshape(-1, 3)
        temp = np.full(t.size, np.nan) if temp_c is None else np.asarray(temp_c, dtype=float)
        if self._t_last is not None and self._pending is None:
            if t.size == 0:
                return
            last = self._queue[-1][0][-1] if self._queue else self._t_last
            if t[0] > last:  # the run goes on: the frame waits for the pass
                self._queue.append((t, a, g, temp))
                self._queued += t.size
                if self._queued >= PASS_SAMPLES:
                    self._flush()
                return
        self._flush()
        if self._pending is not None:
            pt, pa, pg, ptemp = self._pending
            self._pending = None
            if t.size and t[0] <= pt[-1] and pt.size >= 2:
                # A run shorter than RUN_START_SAMPLES, ended by a restart: taken on its own.
                self._begin(pt, pa, pg, ptemp)
            elif t.size and t[0] <= pt[-1]:
                # A run of one sample, ended by a restart: no interval to start the filters on,
                # and joined to the next run it would be a step back in its time.
                self.n_samples += 1
                self._run += 1
            else:
                t, a, g, temp = (
                    np.concatenate([pt, t]), np.vstack([pa, a]), np.vstack([pg, g]), np.concatenate([ptemp, temp]),
                )  # fmt: skip
        if t.size == 0:
            return
        if self._t_last is not None and t[0] <= self._t_last:
            self._restart()
        if self._t_last is None:
            if t.size < RUN_START_SAMPLES:
                # The sample interval the filters need is the median of the run's first samples: wait for them.
                self._pending = (t, a, g, temp)
                return
            self._begin(t, a, g, temp)
            return
        dt = np.diff(t, prepend=self._t_last)
        self._pass(t, a, g, temp, dt, dt)

    def _begin(self, t: FloatArray, a: FloatArray, g: FloatArray, temp: FloatArray) -> None:
        """A run's first samples (two at least): the filters start on them."""
        self._start(t, a)
        dt = np.diff(t, prepend=t[0])
        self._pass(t, a, g, temp, dt, dt[1:])

    def _flush(self) -> None:
        """The queued frames in one pass (:data:`PASS_SAMPLES`)."""
        if not self._queue:
            return
        frames, self._queue, self._queued = self._queue, [], 0
        assert self._t_last is not None  # frames wait only once the run has started
        t = np.concatenate([f[0] for f in frames])
        dt = np.diff(t, prepend=self._t_last)
        a, g = np.vstack([f[1] for f in frames]), np.vstack([f[2] for f in frames])
        self._pass(t, a, g, np.concatenate([f[3] for f in frames]), dt, dt)

    def _pass(
        self,
        t: FloatArray,
        a: FloatArray,
        g: FloatArray,
        temp: FloatArray,
        dt: FloatArray,
        intervals: FloatArray,
    ) -> None:
        """Consecutive samples of one run, after the last sample taken."""
        us, counts = np.unique(np.round(intervals * 1e6).astype(np.int64), return_counts=True)
        for u, c in zip(us.tolist(), counts.tolist(), strict=True):
            self._dt_us[u] = self._dt_us.get(u, 0) + c
        self._t_last = float(t[-1])
        self.n_samples += t.size
        vibe, px4a, px4g = self._vibration(a, g, dt)
        self._welch(np.hstack([a, g]))
        c = self._carry
        self._blocks(
            np.concatenate([c.t, t]),
            np.vstack([c.a, a]),
            np.vstack([c.g, g]),
            np.concatenate([c.temp, temp]),
            np.vstack([c.vibe, vibe]),
            np.concatenate([c.px4a, px4a]),
            np.concatenate([c.px4g, px4g]),
            final=False,
        )

    def _restart(self) -> None:
        """The clock started again: the old run's blocks end, the next run starts as the log did."""
        c = self._carry
        self._blocks(c.t, c.a, c.g, c.temp, c.vibe, c.px4a, c.px4g, final=True)
        self._diff_sq += self._diff_open
        self._diff_open, self._diff_open_n = np.zeros(6), 0
        assert self._t_first is not None and self._t_last is not None
        self._runs_s += self._t_last - self._t_first
        self._run += 1
        self._t_last = None
        self._last_a = self._last_g = None
        # A periodogram segment across the restart would hold the step between two clocks.
        self._welch_buf, self._welch_n, self._welch_segs = [], 0, 0
        self._close_psd()

    def _start(self, t: FloatArray, a: FloatArray) -> None:
        self._t_first = float(t[0])
        self._dt_s = float(np.median(np.diff(t[:RUN_START_SAMPLES])))
        # The filters start settled on the first sample (no start-up transient in the figures):
        # a first-order low-pass y = α·x + (1 − α)·y₋₁ fed a constant x₀ has the state (1 − α)·x₀.
        self._zi = {
            "floor": a[:1] * (1.0 - self._alpha(VIBE_FLOOR_HZ)),
            "vibe": np.zeros((1, 3)),
            "px4": np.zeros((1, 2)),  # accel, gyro
        }

    def _alpha(self, fc_hz: float) -> float:
        """ArduPilot's first-order low-pass gain at the log's sample interval (module docstring)."""
        assert self._dt_s is not None
        return self._dt_s / (self._dt_s + 1.0 / (2.0 * math.pi * fc_hz))

    def _vibration(
        self, a: FloatArray, g: FloatArray, dt: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per sample: ArduPilot's VIBE (N, 3), PX4's accel and gyro vibration metrics (N,) (module
        docstring). The squared differences are summed in blocks of :data:`RUN_START_SAMPLES`
        from the run's start, then the blocks' sums in turn: the same additions however the
        samples are framed."""
        # A square that overflows is refused by first_order_filter with its reason (ValueError),
        # not left to numpy's RuntimeWarning on the user's terminal.
        with np.errstate(over="ignore"):
            a5, a2 = self._alpha(VIBE_FLOOR_HZ), self._alpha(VIBE_FILTER_HZ)
            floor, self._zi["floor"] = first_order_filter(a5, a5 - 1.0, a, self._zi["floor"])
            level, self._zi["vibe"] = first_order_filter(
                a2, a2 - 1.0, (a - floor) ** 2, self._zi["vibe"]
            )
            last_a = a[:1] if self._last_a is None else self._last_a[None, :]
            last_g = g[:1] if self._last_g is None else self._last_g[None, :]
            diff = np.hstack(
                [np.diff(a, axis=0, prepend=last_a), np.diff(g, axis=0, prepend=last_g)]
            )
            sq = diff**2
            # |Δa|, |Δg| added as np.linalg.norm adds them, (x² + y²) + z², a tenth of its time.
            steps = np.sqrt(
                np.column_stack(
                    [(sq[:, 0] + sq[:, 1]) + sq[:, 2], (sq[:, 3] + sq[:, 4]) + sq[:, 5]]
                )
            )
            px4, self._zi["px4"] = first_order_filter(
                PX4_VIBE_ALPHA, PX4_VIBE_ALPHA - 1.0, steps * dt[:, None], self._zi["px4"]
            )
        # Sums over axis 0 and cumsum add the rows in turn (add.reduceat does not, to the bit).
        head = min(sq.shape[0], RUN_START_SAMPLES - self._diff_open_n)
        self._diff_open = np.vstack([self._diff_open, sq[:head]]).sum(axis=0)
        self._diff_open_n += head
        if self._diff_open_n == RUN_START_SAMPLES:
            m = (sq.shape[0] - head) // RUN_START_SAMPLES
            whole = sq[head : head + m * RUN_START_SAMPLES].reshape(m, RUN_START_SAMPLES, 6)
            sums = np.vstack([self._diff_sq, self._diff_open, whole.sum(axis=1)])
            self._diff_sq = sums.cumsum(axis=0)[-1]
            rest = sq[head + m * RUN_START_SAMPLES :]
            self._diff_open, self._diff_open_n = rest.sum(axis=0), rest.shape[0]
        moved = np.abs(diff)
        moved[moved == 0.0] = np.inf
        # The least along the contiguous axis: a tenth of the time down the strided one, and a
        # minimum is the same in any order.
        self._step = np.fmin(self._step, np.ascontiguousarray(moved.T).min(axis=1))
        self._diff_n += diff.shape[0] - (1 if self._last_a is None else 0)
        self._last_a, self._last_g = a[-1], g[-1]
        return np.sqrt(np.maximum(level, 0.0)), px4[:, 0], px4[:, 1]

    def _welch(self, x: FloatArray) -> None:
        nfft = self.config.nfft
        self._welch_buf.append(x)
        self._welch_n += x.shape[0]
        if self._welch_n < nfft:
            return
        data = np.vstack(self._welch_buf)
        m = data.shape[0] // nfft
        segs = data[: m * nfft].reshape(m, nfft, 6)
        rest = data[m * nfft :]
        self._welch_buf, self._welch_n = ([rest] if rest.size else []), rest.shape[0]
        w = np.hanning(nfft)
        segs = (segs - segs.mean(axis=1, keepdims=True)) * w[None, :, None]
        power = np.abs(np.fft.rfft(segs, axis=1)) ** 2
        ends = (self._welch_segs + np.arange(1, m + 1)) * nfft
        groups = -(-(ends - RUN_START_SAMPLES) // PSD_GROUP_SAMPLES)
        self._welch_segs += m
        self._psd_count += m
        cuts = np.flatnonzero(np.diff(groups)) + 1
        # Sums over axis 0 add the rows in turn: a group's segments are added in order, the
        # group's open sum first, across passes as within one.
        for part, group in zip(np.split(power, cuts), groups[np.r_[0, cuts]].tolist(), strict=True):
            if self._psd_open is not None and group == self._psd_group:
                part = np.concatenate([self._psd_open[None], part])
            else:
                self._close_psd()
            self._psd_open, self._psd_group = part.sum(axis=0), group

    def _close_psd(self) -> None:
        """The open group's sum added to the total (:data:`PSD_GROUP_SAMPLES`)."""
        if self._psd_open is not None:
            s, self._psd_open = self._psd_open, None
            self._psd_sum = s if self._psd_sum is None else self._psd_sum + s

    def _blocks(
        self,
        t: FloatArray,
        a: FloatArray,
        g: FloatArray,
        temp: FloatArray,
        vibe: FloatArray,
        px4a: FloatArray,
        px4g: FloatArray,
        *,
        final: bool,
    ) -> None:
        if t.size == 0:
            return
        ids = np.floor(t / self.config.block_s).astype(np.int64)
        cut = t.size if final else int(np.searchsorted(ids, ids[-1]))
        self._carry = _Carry(
            t[cut:], a[cut:], g[cut:], temp[cut:], vibe[cut:], px4a[cut:], px4g[cut:]
        )
        if cut == 0:
            return
        ids = ids[:cut]
        starts = np.flatnonzero(np.diff(ids, prepend=ids[0] - 1))
        n = np.diff(np.append(starts, cut))

        def mean(x: FloatArray) -> FloatArray:
            s = np.add.reduceat(x[:cut], starts, axis=0)
            return s / (n if s.ndim == 1 else n[:, None])

        ma, mg = mean(a), mean(g)
        idx = np.repeat(np.arange(starts.size), n)
        va = (
            np.add.reduceat((a[:cut] - ma[idx]) ** 2, starts, axis=0)
            / np.maximum(n - 1, 1)[:, None]
        )
        vg = (
            np.add.reduceat((g[:cut] - mg[idx]) ** 2, starts, axis=0)
            / np.maximum(n - 1, 1)[:, None]
        )
        with np.errstate(all="ignore"):
            tmin = np.fmin.reduceat(temp[:cut], starts)
            tmax = np.fmax.reduceat(temp[:cut], starts)
        table = np.column_stack(
            [
                ids[starts], n, ma, mg, va, vg, mean(vibe), np.maximum.reduceat(vibe[:cut], starts, axis=0),
                mean(px4a), mean(px4g), tmin, tmax, t[starts], t[np.append(starts[1:], cut) - 1],
                np.full(starts.size, self._run),
            ]
        )  # fmt: skip
        self._tables.append(table)

    def result(self, gravity_mps2: float) -> ImuHealth:
        """The figures (module docstring); ``gravity_mps2`` is the local gravity the residual refers to."""
        self._flush()
        if self._pending is not None:
            if self._pending[0].size >= 2:
                self._begin(*self._pending)
            else:
                self.n_samples += 1
            self._pending = None
        self._close_psd()
        c = self._carry
        self._blocks(c.t, c.a, c.g, c.temp, c.vibe, c.px4a, c.px4g, final=True)
        table = np.vstack(self._tables) if self._tables else np.zeros((0, _BLOCK_FIELDS))
        self._tables = [table]
        dts = np.array(sorted(self._dt_us.items()), dtype=float).reshape(-1, 2)
        if dts.size:
            cum = np.cumsum(dts[:, 1])
            med_us = float(dts[np.searchsorted(cum, 0.5 * cum[-1]), 0])
        else:
            med_us = 0.0
        rate = 1e6 / med_us if med_us > 0 else 0.0
        gaps = dts[dts[:, 0] > GAP_PERIODS * med_us] if med_us > 0 else dts[:0]
        blocks = self._block_view(table, rate)
        rest = blocks.rest
        dof = np.maximum(blocks.n - 1, 0)[:, None]
        settled = rest & _settled(blocks, rest, self._step)
        if rest.any():
            method = "rest"
            w = dof[settled]
            noise_a = np.sqrt((blocks.accel_var[settled] * w).sum(axis=0) / w.sum())
            noise_g = np.sqrt((blocks.gyro_var[settled] * w).sum(axis=0) / w.sum())
            wn = blocks.n[rest][:, None]
            resid = np.linalg.norm(blocks.accel_mean[rest], axis=1) - gravity_mps2
            grav: tuple[float | None, float | None] = (
                float(np.median(resid)),
                float(np.abs(resid).max()),
            )
            bias = (blocks.gyro_mean[rest] * wn).sum(axis=0) / wn.sum()
        else:
            method = "first_difference"
            rms = np.sqrt((self._diff_sq + self._diff_open) / max(self._diff_n, 1) / 2.0)
            noise_a, noise_g = rms[:3], rms[3:]
            grav, bias = (None, None), None
        flight = ~rest
        fly = flight.any()
        temps = table[:, 22:24]
        finite = np.isfinite(temps)
        psd, freq = self._spectra(rate)
        this_run_s = (
            0.0 if self._t_first is None or self._t_last is None else self._t_last - self._t_first
        )
        return ImuHealth(
            n_samples=self.n_samples,
            runs=self._run + 1,
            rate_hz=rate,
            duration_s=self._runs_s + this_run_s,
            gap_count=int(gaps[:, 1].sum()),
            longest_gap_s=float(gaps[:, 0].max() * 1e-6) if gaps.size else 0.0,
            rest_s=float(blocks.n[rest].sum() / rate) if rate else 0.0,
            settling_blocks=int(rest.sum() - settled.sum()),
            noise_method=method,
            accel_noise_mps2=noise_a,
            gyro_noise_rps=noise_g,
            gravity_residual_median_mps2=grav[0],
            gravity_residual_max_abs_mps2=grav[1],
            gyro_bias_rps=bias,
            vibe_median_mps2=np.median(blocks.vibe_mean[flight], axis=0) if fly else None,
            vibe_max_mps2=blocks.vibe_max[flight].max(axis=0) if fly else None,
            px4_accel_vibration_median_mps=float(np.median(blocks.px4_accel[flight]))
            if fly
            else None,
            px4_accel_vibration_max_mps=float(blocks.px4_accel[flight].max()) if fly else None,
            px4_gyro_vibration_median_rad=float(np.median(blocks.px4_gyro[flight]))
            if fly
            else None,
            px4_gyro_vibration_max_rad=float(blocks.px4_gyro[flight].max()) if fly else None,
            temp_min_c=float(temps[:, 0][finite[:, 0]].min()) if finite[:, 0].any() else None,
            temp_max_c=float(temps[:, 1][finite[:, 1]].max()) if finite[:, 1].any() else None,
            freq_hz=freq,
            accel_psd=psd[:, :3],
            gyro_psd=psd[:, 3:],
            blocks=blocks,
            config=self.config,
        )

    def _spectra(self, rate: float) -> tuple[FloatArray, FloatArray]:
        nfft = self.config.nfft
        freq = np.asarray(
            np.fft.rfftfreq(nfft, d=1.0 / rate) if rate else np.zeros(nfft // 2 + 1),
            dtype=np.float64,
        )
        if self._psd_sum is None or not rate:
            return np.zeros((0, 6)), freq[:0]
        w = np.hanning(nfft)
        psd: FloatArray = self._psd_sum / self._psd_count / (rate * (w**2).sum())
        psd[1:-1] *= 2.0  # one-sided
        return psd, freq

    def _block_view(self, table: FloatArray, rate: float) -> Blocks:
        cfg = self.config
        n = table[:, 1]
        spread_a = np.sqrt(table[:, 8:11].sum(axis=1))
        spread_g = np.sqrt(table[:, 11:14].sum(axis=1))
        full = n >= max(FULL_BLOCK * cfg.block_s * rate, MIN_REST_SAMPLES)
        rest = full & (spread_a <= cfg.accel_rest_mps2) & (spread_g <= cfg.gyro_rest_rps)
        return Blocks(
            k=table[:, 0].astype(np.int64),
            n=n,
            accel_mean=table[:, 2:5],
            gyro_mean=table[:, 5:8],
            accel_var=table[:, 8:11],
            gyro_var=table[:, 11:14],
            vibe_mean=table[:, 14:17],
            vibe_max=table[:, 17:20],
            px4_accel=table[:, 20],
            px4_gyro=table[:, 21],
            temp_min=table[:, 22],
            temp_max=table[:, 23],
            full=full,
            rest=rest,
            run=table[:, 26].astype(np.intp),
        )


def _settled(blocks: Blocks, rest: BoolArray, step: FloatArray) -> BoolArray:
    """Blocks whose standard deviation on every axis is within :data:`SETTLING_SPREAD_RATIO` times the
    median rest block's, or half the output's ``step`` per axis where more (module docstring); the
    median rest block is always settled."""
    spread = np.sqrt(np.hstack([blocks.accel_var, blocks.gyro_var]))
    if not rest.any():
        return np.zeros(rest.shape, dtype=bool)
    # Quantized below its noise, most blocks never change a count and one flip (a spread of up to
    # half a step) would double the median's: no ringing is told from less.
    typical = np.maximum(
        np.median(spread[rest], axis=0), 0.5 * np.where(np.isfinite(step), step, 0.0)
    )
    settled: BoolArray = np.all(spread <= SETTLING_SPREAD_RATIO * typical, axis=1)
    return settled


@dataclass(frozen=True)
class PairDifference:
    """Disagreement of two IMUs on common blocks: accel (m/s²) and gyro (rad/s) norms of the block-mean
    differences; ``run``: the run of each block (:attr:`Blocks.run`), ``t_s`` on that run's clock."""

    imus: tuple[int, int]
    t_s: FloatArray
    accel_mps2: FloatArray
    gyro_rps: FloatArray
    rest: BoolArray
    run: IntArray

    def to_dict(self) -> dict[str, Any]:
        def stats(x: FloatArray) -> dict[str, float] | None:
            return (
                None if not x.size else {"p99": float(np.percentile(x, 99)), "max": float(x.max())}
            )

        flight = ~self.rest
        return {
            "imus": list(self.imus),
            "common_blocks": int(self.t_s.size),
            "accel_mps2": {
                "flight": stats(self.accel_mps2[flight]),
                "rest": stats(self.accel_mps2[self.rest]),
            },
            "gyro_rps": {
                "flight": stats(self.gyro_rps[flight]),
                "rest": stats(self.gyro_rps[self.rest]),
            },
        }


def pair_difference(imus: tuple[int, int], a: Blocks, b: Blocks, block_s: float) -> PairDifference:
    """The disagreement of two IMUs (``a``, ``b`` their block tables) on the blocks both have: the
    same block of the same run (a block index repeats after the clock started again)."""

    def keys(x: Blocks) -> np.ndarray[Any, Any]:
        out = np.empty(x.k.size, dtype=[("run", np.intp), ("k", np.intp)])
        out["run"], out["k"] = x.run, x.k
        return out

    common, ia, ib = np.intersect1d(keys(a), keys(b), return_indices=True)
    return PairDifference(
        imus,
        (common["k"] + 0.5) * block_s,
        np.linalg.norm(a.accel_mean[ia] - b.accel_mean[ib], axis=1),
        np.linalg.norm(a.gyro_mean[ia] - b.gyro_mean[ib], axis=1),
        a.rest[ia] & b.rest[ib],
        common["run"].astype(np.intp),
    )


def pair_differences(blocks: Mapping[int, Blocks], block_s: float) -> list[PairDifference]:
    """Every pair of IMUs (in index order)."""
    keys = sorted(blocks)
    return [
        pair_difference((i, j), blocks[i], blocks[j], block_s)
        for n, i in enumerate(keys)
        for j in keys[n + 1 :]
    ]
