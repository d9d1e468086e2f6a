"""Stream validity of one IMU and consistency between the IMUs of a vehicle.

Not a method of ``docs/methods.md``: these are the checks the autopilots run
before any model-based test, and the scalar checks (M1) are only meaningful on
a stream that passes them.

* **Timeout**: no sample for ``timeout_s`` (PX4 ``DataValidator`` timeout).
* **Stale axis**: a run of ``stale_run_samples`` identical consecutive values on
  one axis — the "stuck gyro" of real ICM42688 and MPU6000 failures; with
  sensor noise of a few LSB a healthy axis never repeats that long (PX4's
  ``VALUE_EQUAL_COUNT`` is 100).
* **Error density**: the fraction of bad samples (rejected, non-finite,
  duplicated or out of order) among the last ``error_window_samples``.
* **Cross-IMU consistency**: the time-binned mean specific force and angular
  rate of each IMU against the others; ArduPilot blocks arming above
  0.75 m/s² and 5 °/s, PX4 above 0.7 m/s² (``COM_ARM_IMU_ACC``). With three or
  more IMUs the outlier is the one far from the per-axis median; with two
  the pair is reported and the scalar diagnosis of each says which is wrong.

Everything here is pure: times are passed in (``arrival_s`` for the timeout,
sample time ``t_s`` for the bins), state is small and fixed-size, and
``state_dict`` / ``from_state`` round-trip it for checkpoints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.conventions import AXES, Triad
from estimators.validity_limits import ValidityLimits as ValidityLimits


def typical_step_s(steps_s: FloatArray) -> float:
    """The interquartile mean of sample steps ``steps_s`` (s, at least one): the mean of the middle half.

    Gaps and bunched samples (up to a quarter of the steps on either side) do not move it; unlike
    the median, it does not flip between the two values of time stamps quantized to a coarser tick
    (400 Hz stamped in whole ms steps 2 and 3 ms: 2.5 ms here, 333 or 500 Hz by the median). Over
    a few steps of two rates (a stream changing rate) the median keeps the more frequent one.
    """
    steps = np.sort(np.asarray(steps_s, dtype=float).reshape(-1))
    quarter = steps.size // 4
    return float(steps[quarter : steps.size - quarter].mean())


def typical_steps_s(blocks_s: FloatArray) -> FloatArray:
    """:func:`typical_step_s` of each row of ``blocks_s`` (K, M), s: (K,), the same bits (each row's
    middle half sorted and summed as one row, divided by its count)."""
    steps = np.sort(np.asarray(blocks_s, dtype=float), axis=1)
    quarter = steps.shape[1] // 4
    means: FloatArray = steps[:, quarter : steps.shape[1] - quarter].mean(axis=1)
    return means


def plausible_rate_hz(t_s: FloatArray, limits: ValidityLimits) -> float | None:
    """The sample rate of increasing time stamps, Hz, or None when it is not plausible.

    The median spacing, so a few gaps or bunched samples do not move it (a stream that starts
    at another rate, as a real tlog does, keeps its more frequent one); None when it lies outside
    ``[limits.min_rate_hz, limits.max_rate_hz]`` or there are fewer than two stamps.
    """
    t = np.asarray(t_s, dtype=float).reshape(-1)
    if t.size < 2:
        return None
    spacing_s = float(np.median(np.diff(t)))
    if not (np.isfinite(spacing_s) and spacing_s > 0):
        return None
    rate_hz = 1.0 / spacing_s
    return rate_hz if limits.min_rate_hz <= rate_hz <= limits.max_rate_hz else None


@dataclass(frozen=True)
class StaleAxis:
    """An axis whose output repeated the same value ``run_samples`` times in a row."""

    triad: Triad
    axis: str
    run_samples: int
    value: float


@dataclass(frozen=True)
class StaleChange:
    """An axis that became stale (``stale`` True: its run reached the limit) or stopped being stale.

    ``run_samples`` is the run length at that sample (the limit when it became stale, the length
    the run ended with when it stopped), ``value`` the repeated value, ``t_s`` the sample's time
    (None when the caller gave no times). Every change inside a batch is reported, in time order,
    so the changes do not depend on how the stream was cut into batches.
    """

    triad: Triad
    axis: str
    stale: bool
    run_samples: int
    value: float
    t_s: float | None = None


@dataclass(frozen=True)
class ValidityReport:
    """The stream's condition after one batch.

    Attributes
    ----------
    stale : axes stale at the end of the batch (run still going).
    changes : every :class:`StaleChange` inside the batch, in time order.
    error_density : bad fraction of the last ``error_window_samples`` samples, at the end of the batch.
    peak_error_density : its maximum over the batch.
    error_dense : ``peak_error_density > error_density_max``.
    """

    stale: tuple[StaleAxis, ...]
    changes: tuple[StaleChange, ...]
    error_density: float
    peak_error_density: float
    error_dense: bool


def _axis_names() -> list[tuple[Triad, str]]:
    return [(Triad.ACCEL, a) for a in AXES] + [(Triad.GYRO, a) for a in AXES]


def run_lengths(values: FloatArray, prev_value: FloatArray, prev_run: IntArray) -> IntArray:
    """Length of the run of identical values ending at each sample, per column.

    Parameters
    ----------
    values : (N, K) samples.
    prev_value : (K,) the last value before this batch (NaN if none).
    prev_run : (K,) the length of the run that ended at ``prev_value`` (0 if none).

    Returns
    -------
    (N, K) integer run lengths (1 for a value different from its predecessor).
    """
    # Column by column along contiguous rows (the transpose), each column's running maximum
    # over its own samples: a batch of 16,384 took 0.7 ms down the (N, K) columns, 0.5 ms so.
    v = np.asarray(values, dtype=float).T
    n = v.shape[1]
    if n == 0:
        return np.zeros((0, v.shape[0]), dtype=np.int64)
    reset = np.empty(v.shape, dtype=bool)
    np.not_equal(v[:, 0], prev_value, out=reset[:, 0])
    np.not_equal(v[:, 1:], v[:, :-1], out=reset[:, 1:])
    idx = np.arange(n, dtype=np.int64)
    last_reset = np.where(reset, idx, -1)
    np.maximum.accumulate(last_reset, axis=1, out=last_reset)
    runs: IntArray = np.where(
        last_reset >= 0, idx - last_reset + 1, np.asarray(prev_run, np.int64)[:, None] + idx + 1
    ).T
    return runs


class StreamValidity:
    """Timeout, stale axes and error density of one IMU stream (PX4-style).

    State: the last value and run length of each of the six axes, a ring of
    ``error_window_samples`` bad-sample flags, the last arrival time.
    """

    def __init__(self, *, limits: ValidityLimits = ValidityLimits()) -> None:
        self.limits = limits
        self._last_value = np.full(6, np.nan)
        self._run = np.zeros(6, dtype=np.int64)
        self._ring = np.zeros(limits.error_window_samples, dtype=bool)  # oldest first
        self._last_arrival_s: float | None = None

    def update(
        self,
        *,
        accel_mps2: FloatArray,
        gyro_rps: FloatArray,
        bad: BoolArray,
        arrival_s: float,
        t_s: FloatArray | None = None,
    ) -> ValidityReport:
        """Account one batch.

        Parameters
        ----------
        accel_mps2, gyro_rps : (N, 3) samples, m/s² and rad/s; rows flagged ``bad`` are ignored
            for the stale check (a NaN neither extends nor breaks a run).
        bad : (N,) bool, samples the caller rejected (non-finite, duplicated, out of order).
        arrival_s : when the batch arrived (the caller's monotonic clock), s.
        t_s : (N,) sample times, s (optional): then each change carries the time of its sample.
        """
        bad = np.asarray(bad, dtype=bool).reshape(-1)
        values = np.hstack(
            [
                np.asarray(accel_mps2, float).reshape(-1, 3),
                np.asarray(gyro_rps, float).reshape(-1, 3),
            ]
        )
        if values.shape[0] != bad.size:
            raise ValueError(f"bad has {bad.size} flags for {values.shape[0]} samples")
        self._last_arrival_s = float(arrival_s)
        limit = self.limits.stale_run_samples
        good = values[~bad]
        changes: list[tuple[int, int, StaleChange]] = []
        if good.shape[0]:
            runs = run_lengths(good, self._last_value, self._run)
            over = runs >= limit
            before = np.vstack([(self._run >= limit)[None, :], over[:-1]])
            flips = np.nonzero(over != before)
            if flips[0].size:
                names = _axis_names()
                t_good = None if t_s is None else np.asarray(t_s, float).reshape(-1)[~bad]
                prev_run = np.vstack([self._run[None, :], runs[:-1]])
                prev_val = np.vstack([self._last_value[None, :], good[:-1]])
            for k, ax in zip(*flips, strict=True):
                rising = bool(over[k, ax])
                run = int(runs[k, ax]) if rising else int(prev_run[k, ax])
                value = float(good[k, ax]) if rising else float(prev_val[k, ax])
                t = None if t_good is None else float(t_good[k])
                changes.append(
                    (
                        int(k),
                        int(ax),
                        StaleChange(names[ax][0], names[ax][1], rising, run, value, t),
                    )
                )
            self._last_value = good[-1].copy()
            self._run = runs[-1].copy()
        density, peak = self._push_errors(bad)
        return ValidityReport(
            stale=self.stale_axes(),
            changes=tuple(c for _, _, c in sorted(changes, key=lambda c: (c[0], c[1]))),
            error_density=density,
            peak_error_density=peak,
            error_dense=peak > self.limits.error_density_max,
        )

    def record_rejected(self, n_samples: int) -> ValidityReport:
        """Account ``n_samples`` samples lost in frames the decoder rejected (they count as errors)."""
        flags = np.ones(int(n_samples), dtype=bool)
        density, peak = self._push_errors(flags)
        return ValidityReport(
            self.stale_axes(), (), density, peak, peak > self.limits.error_density_max
        )

    def _push_errors(self, bad: BoolArray) -> tuple[float, float]:
        w = self.limits.error_window_samples
        if bad.size == 0:
            d = float(self._ring.sum()) / w
            return d, d
        if not bad.any() and not self._ring.any():
            return 0.0, 0.0  # a clean batch after a clean window: the ring stays all good
        # Window sums at each new sample over the old ring followed by the batch.
        history = np.concatenate([self._ring, bad])
        csum = np.concatenate([[0], np.cumsum(history)])
        end = np.arange(w, history.size) + 1
        counts = csum[end] - csum[end - w]
        # Before the window has filled, unseen samples count as good (no start-up alarm on one bad sample).
        dens = counts / w
        self._ring = history[-w:].copy()
        return float(dens[-1]), float(dens.max())

    def stale_axes(self) -> tuple[StaleAxis, ...]:
        names = _axis_names()
        return tuple(
            StaleAxis(names[k][0], names[k][1], int(self._run[k]), float(self._last_value[k]))
            for k in np.flatnonzero(self._run >= self.limits.stale_run_samples)
        )

    def timed_out(self, now_s: float) -> bool:
        """True when no batch arrived within ``timeout_s`` before ``now_s`` (False before the first)."""
        return (
            self._last_arrival_s is not None
            and now_s - self._last_arrival_s > self.limits.timeout_s
        )

    def state_dict(self) -> dict[str, Any]:
        return {
            "last_value": self._last_value.copy(),
            "run": self._run.copy(),
            "ring": self._ring.copy(),
        }

    @classmethod
    def from_state(
        cls, state: dict[str, Any], *, limits: ValidityLimits = ValidityLimits()
    ) -> StreamValidity:
        """Restore from :meth:`state_dict` (a ring of another window length restarts the density count)."""
        out = cls(limits=limits)
        out._last_value = np.asarray(state["last_value"], float).reshape(6).copy()
        out._run = np.asarray(state["run"], np.int64).reshape(6).copy()
        ring = np.asarray(state["ring"], bool).reshape(-1)
        if ring.size == limits.error_window_samples:
            out._ring = ring.copy()
        return out


@dataclass(frozen=True)
class CrossImuVerdict:
    """One compared time bin.

    Attributes
    ----------
    bin_start_s : start of the bin (sample time), s.
    imus : IMU indices compared, ascending.
    accel_dev_mps2 : (K,) each IMU's largest per-axis distance from the reference, m/s².
    gyro_dev_rps : (K,) the same for angular rate, rad/s.
    disagreeing : IMUs beyond a limit in this bin. With three or more IMUs the reference is the
        per-axis median, so only the outlier is listed; with two it is the other IMU, and both are.
    """

    bin_start_s: float
    imus: tuple[int, ...]
    accel_dev_mps2: FloatArray
    gyro_dev_rps: FloatArray
    disagreeing: tuple[int, ...]


def compare_imus(
    imus: tuple[int, ...],
    accel_mean_mps2: FloatArray,
    gyro_mean_rps: FloatArray,
    *,
    limits: ValidityLimits,
    bin_start_s: float = 0.0,
) -> CrossImuVerdict:
    """Cross-IMU consistency of one time bin.

    Parameters
    ----------
    imus : (K,) IMU indices, K >= 2.
    accel_mean_mps2, gyro_mean_rps : (K, 3) mean outputs over the same bin, SI, body axes.
    """
    a = np.asarray(accel_mean_mps2, float).reshape(-1, 3)
    g = np.asarray(gyro_mean_rps, float).reshape(-1, 3)
    k = len(imus)
    if k < 2 or a.shape[0] != k or g.shape[0] != k:
        raise ValueError(
            f"need K >= 2 IMUs with (K, 3) means, got {k} indices, {a.shape} and {g.shape}"
        )
    if k == 2:
        da = np.full(2, np.abs(a[0] - a[1]).max())
        dg = np.full(2, np.abs(g[0] - g[1]).max())
    else:
        da = np.abs(a - np.median(a, axis=0)).max(axis=1)
        dg = np.abs(g - np.median(g, axis=0)).max(axis=1)
    bad = (da > limits.cross_imu_accel_mps2) | (dg > limits.cross_imu_gyro_rps)
    return CrossImuVerdict(
        float(bin_start_s),
        tuple(int(i) for i in imus),
        da,
        dg,
        tuple(int(imus[i]) for i in np.flatnonzero(bad)),
    )


@dataclass(frozen=True)
class CrossImuReport:
    """An IMU that disagreed with the others for ``persist`` consecutive bins (or stopped doing so)."""

    imu: int
    others: tuple[int, ...]
    accel_dev_mps2: float
    gyro_dev_rps: float
    bin_start_s: float
    consistent: bool


def best_clock_offset(
    measured: tuple[FloatArray, FloatArray],
    reference: tuple[FloatArray, FloatArray],
    *,
    lowest_s: float,
    highest_s: float,
) -> float | None:
    """The offset of one IMU's clock against another's, from the rotation both measured.

    Each is ``(t_s[N], gyro_rps[N, 3])`` on its own clock; the offset ``c`` (``t_measured −
    t_reference`` for one instant) is searched in ``[lowest_s, highest_s]`` on a grid of the
    reference's median sample step, minimizing the mean squared difference of the angular rates
    (each axis less its mean over the overlap: a bias or a fault of one IMU does not move it)
    with the measured IMU's interpolated at ``t_reference + c``. This is the lag of largest
    cross-correlation of the two rate records (the time-offset calibration of Furgale et al.,
    Kalibr, by correlation). None when the records do not overlap by half the reference's span at
    every candidate, or when they do not tell one offset: the best is not below half the worst
    (a vehicle at rest turns at the Earth rate only: every offset fits as well).
    """
    tm, gm = measured
    tr, gr = reference
    if tm.size < 2 or tr.size < 2 or not highest_s >= lowest_s:
        return None
    step = float(np.median(np.diff(tr)))
    if not step > 0:
        return None
    candidates = np.arange(lowest_s, highest_s + step, step)
    costs = np.full(candidates.size, np.inf)
    for k, c in enumerate(candidates):
        inside = (tr + c >= tm[0]) & (tr + c <= tm[-1])
        if inside.sum() * 2 < tr.size:
            return None
        moved = np.column_stack([np.interp(tr[inside] + c, tm, gm[:, j]) for j in range(3)])
        diff = (moved - moved.mean(axis=0)) - (gr[inside] - gr[inside].mean(axis=0))
        costs[k] = float(np.mean(diff**2))
    best = int(np.argmin(costs))
    if not costs[best] < 0.5 * costs.max():
        return None
    return float(candidates[best])


CROSS_IMU_STATE_VERSION = 2
"""Version of :meth:`CrossImuMonitor.state_dict` (2 adds the clock offsets, the offsets being measured
and the agreeing streaks; version 1 is read with none; a state of another version is not resumed)."""

CLOCK_BASE_MIN_S = 600.0
"""Two IMUs whose newest sample times differ by more than this are taken to stamp time on different
clocks (one Unix time, one since boot; or a clock that restarted) rather than to lag: no queue of
the service holds ten minutes of an IMU's frames, and a clock base differs by far more (a boot
counter from a Unix time by 1.7e9 s; an uptime from another by the time between boots)."""
REFERENCE_SILENT_FRAMES = 64
"""Frames of the other IMUs since the reference IMU's last after which the next IMU to send becomes
the reference (a reference that stopped would otherwise make every other IMU's clock look far off)."""
CLOCK_FRAMES = 8
"""Frames of an IMU on another clock, and of the reference, measured before its offset is taken: each
of its frames bounds the offset from above (its newest time minus the reference's newest), each of
the reference's from below; steady when each bound's spread lies within the lag the comparison waits
for anyway. The offset is the middle of the tightest bounds."""
CLOCK_SAMPLES_MAX = 4096
"""Samples of each IMU kept while an offset is measured, for :func:`best_clock_offset` (a few seconds
at the rates served; 4096 x 4 floats x 8 bytes = 128 KiB per IMU, and only while measuring)."""
CLOCK_ERROR_WINDOWS = 0.25
"""Largest uncertainty of a measured offset (half the gap between the bounds), in bins: beyond it a
moving vehicle's bins would be compared a good part of a bin apart."""


@dataclass
class _OpenBin:
    """The bin an IMU is still filling: its index, samples so far and their sums (SI)."""

    index: int
    n: int
    accel_sum: FloatArray
    gyro_sum: FloatArray


class CrossImuMonitor:
    """Bins each IMU's samples by sample time and compares complete bins across IMUs.

    A bin is compared once every live IMU has moved past it. An IMU is live
    while its open bin lags the newest by at most two bins plus the span of the
    longest last frame of any IMU: frames of one IMU after another (a replayed
    4 Hz log comes in 25 s frames per IMU) still meet bin for bin, while an IMU
    that stopped sending holds the others back by that much at most (its timeout
    is reported by :class:`StreamValidity`). State: per IMU one open bin (sums
    and count) and the closed bin means not compared yet.

    A report of disagreement needs ``cross_imu_persist_windows`` disagreeing bins in a row, and so
    does its recovery in agreeing bins: a disagreement near the limit (or two IMUs slightly skewed
    in time while the vehicle moves) does not flap between the two.

    Clocks: the first IMU added is the reference (until it falls silent,
    :data:`REFERENCE_SILENT_FRAMES`). Another whose newest sample time differs from the
    reference's by more than :data:`CLOCK_BASE_MIN_S` when its frame comes stamps time on another
    clock. Its offset is measured over :data:`CLOCK_FRAMES` frames of each (bounds from both
    sides); when steady and known to :data:`CLOCK_ERROR_WINDOWS` of a bin its samples are
    compared at its time minus the offset. Until then, or when the offset does not hold still or
    cannot be told closely enough (long frames), it is not compared, and
    :meth:`not_compared` says why (and why an IMU on the same clock that lags the others is not).
    """

    def __init__(self, *, limits: ValidityLimits = ValidityLimits()) -> None:
        self.limits = limits
        self._open: dict[int, _OpenBin] = {}
        self._span: dict[int, int] = {}  # imu -> bins its last frame spanned
        self._closed: dict[int, dict[int, tuple[FloatArray, FloatArray]]] = {}
        self._streak: dict[int, int] = {}
        self._flagged: set[int] = set()
        self._agree: dict[int, int] = {}
        self._last_compared = -(2**62)
        self._ref: int | None = None
        self._ref_silent = 0  # frames of other IMUs since the reference's last
        self._newest_s: dict[int, float] = {}  # imu -> newest sample time on its own clock
        self._offset_s: dict[int, float] = {}  # imu -> its clock minus the reference's
        # imu -> the offsets its frames and the reference's bound it by, while measured
        self._measured: dict[int, tuple[list[float], list[float]]] = {}
        self._why_not: dict[int, str] = {}
        # imu -> its last frames' times and angular rates while an offset is measured
        self._recent: dict[int, tuple[list[FloatArray], list[FloatArray]]] = {}

    def add(
        self, imu: int, t_s: FloatArray, accel_mps2: FloatArray, gyro_rps: FloatArray
    ) -> list[CrossImuReport]:
        """Add one IMU's good samples (sample time, SI); returns the reports of newly compared bins."""
        a = np.asarray(accel_mps2, float).reshape(-1, 3)
        g = np.asarray(gyro_rps, float).reshape(-1, 3)
        t = self._aligned(imu, np.asarray(t_s, float).reshape(-1), g)
        if t is None:
            return []
        w = self.limits.cross_imu_window_s
        bins = np.floor(t / w).astype(np.int64)
        # Samples are in time order (the pipeline guarantees it), so bins are sorted.
        starts = np.flatnonzero(np.concatenate([[True], bins[1:] != bins[:-1]]))
        sums_a = np.add.reduceat(a, starts, axis=0)
        sums_g = np.add.reduceat(g, starts, axis=0)
        counts = np.diff(np.concatenate([starts, [t.size]]))
        closed = self._closed.setdefault(imu, {})
        cur = self._open.get(imu)
        for j, b in enumerate(bins[starts]):
            b = int(b)
            if cur is not None and cur.index == b:
                cur.n += int(counts[j])
                cur.accel_sum = cur.accel_sum + sums_a[j]
                cur.gyro_sum = cur.gyro_sum + sums_g[j]
                continue
            if cur is not None and cur.index < b:
                closed[cur.index] = (cur.accel_sum / cur.n, cur.gyro_sum / cur.n)
            cur = _OpenBin(b, int(counts[j]), sums_a[j].copy(), sums_g[j].copy())
        # t is not empty: the loop ran at least once and left a bin open.
        assert cur is not None
        self._open[imu] = cur
        self._span[imu] = int(bins[-1] - bins[0]) + 1
        oldest_kept = cur.index - self._lag_bins() - 2
        for old in [k for k in closed if k < oldest_kept]:
            del closed[old]
        return self._compare_ready()

    def _aligned(self, imu: int, t: FloatArray, gyro_rps: FloatArray) -> FloatArray | None:
        """``t`` on the reference's clock; None (nothing to compare) when empty, or while the IMU's
        clock is not aligned (class docstring)."""
        if t.size == 0:
            return None
        if self._ref is None or self._ref_silent > REFERENCE_SILENT_FRAMES:
            self._rebase(imu)
        self._newest_s[imu] = float(t[-1])
        ref = self._ref
        if self._measured:
            self._keep_recent(imu, t, gyro_rps)
        if ref is None or imu == ref:
            self._ref_silent = 0
            # The IMUs being measured had their newest samples before these: lower bounds.
            for other, (_, lower) in self._measured.items():
                lower.append(self._newest_s[other] - float(t[-1]))
                del lower[:-CLOCK_FRAMES]
            return t
        self._ref_silent += 1
        offset = self._offset_s.get(imu, 0.0)
        measured = float(t[-1]) - self._newest_s[ref]
        if abs(measured - offset) <= CLOCK_BASE_MIN_S and imu not in self._measured:
            self._why_not.pop(imu, None)
            return t - offset if offset else t
        self._forget(imu)
        if imu not in self._measured:
            self._keep_recent(imu, t, gyro_rps)
        upper, lower = self._measured.setdefault(imu, ([], []))
        upper.append(measured)
        del upper[:-CLOCK_FRAMES]
        self._offset_s.pop(imu, None)
        waited_s = self._lag_bins() * self.limits.cross_imu_window_s
        why = f"IMU{imu} stamps time on another clock than IMU{ref} (offset {measured:.6g} s): "
        if len(upper) < CLOCK_FRAMES or len(lower) < CLOCK_FRAMES:
            why += f"measuring the offset ({min(len(upper), len(lower))} of {CLOCK_FRAMES} frames)"
            self._why_not[imu] = why
            return None
        spread = max(max(upper) - min(upper), max(lower) - min(lower))
        # The offset lies between what the IMU's frames and the reference's bound it by, when
        # both streams take as long to arrive: within half their gap.
        error = abs(min(upper) - max(lower)) / 2
        best = None
        if spread <= waited_s:
            # Arrival tells it to half a frame at best: the rotation both IMUs saw tells it to a
            # sample, if they saw one.
            margin = self.limits.cross_imu_window_s * CLOCK_ERROR_WINDOWS
            best = best_clock_offset(
                self._recent_of(imu),
                self._recent_of(ref),
                lowest_s=min(min(upper), max(lower)) - margin,
                highest_s=max(min(upper), max(lower)) + margin,
            )
        if best is not None:
            self._offset_s[imu] = best
            self._measuring_done(imu)
            return t - best
        if spread > waited_s:
            why += f"offset not steady ({spread:.3g} s over {CLOCK_FRAMES} frames, more than {waited_s:.3g} s)"
        elif error > self.limits.cross_imu_window_s * CLOCK_ERROR_WINDOWS:
            why += (
                f"offset known to ±{error:.3g} s only, more than {CLOCK_ERROR_WINDOWS:g} of the "
                f"{self.limits.cross_imu_window_s:g} s bins (shorter frames tell it better)"
            )
        else:
            self._offset_s[imu] = (min(upper) + max(lower)) / 2
            self._measuring_done(imu)
            return t - self._offset_s[imu]
        self._why_not[imu] = why
        return None

    def _keep_recent(self, imu: int, t: FloatArray, gyro_rps: FloatArray) -> None:
        """The IMU's last samples while an offset is measured (at most CLOCK_SAMPLES_MAX)."""
        times, rates = self._recent.setdefault(imu, ([], []))
        times.append(t.copy())
        rates.append(gyro_rps.copy())
        while sum(len(x) for x in times) - len(times[0]) >= CLOCK_SAMPLES_MAX:
            del times[0], rates[0]

    def _recent_of(self, imu: int) -> tuple[FloatArray, FloatArray]:
        """The kept samples (none after a restart: they are not checkpointed)."""
        times, rates = self._recent.get(imu, ([], []))
        if not times:
            return np.empty(0), np.empty((0, 3))
        return np.concatenate(times), np.concatenate(rates)

    def _measuring_done(self, imu: int) -> None:
        del self._measured[imu]
        self._why_not.pop(imu, None)
        if not self._measured:
            self._recent.clear()

    def _rebase(self, imu: int) -> None:
        """``imu`` the reference from now on (the first IMU, or the reference fell silent): the
        offsets taken against the old one are kept, made relative to the new one."""
        base = self._offset_s.pop(imu, 0.0)
        self._offset_s = {i: o - base for i, o in self._offset_s.items()}
        self._measured.clear()
        self._recent.clear()
        self._ref, self._ref_silent = imu, 0

    def _forget(self, imu: int) -> None:
        """An IMU's bins on a time base no longer its own: they are compared with nothing."""
        self._open.pop(imu, None)
        self._span.pop(imu, None)
        self._closed.pop(imu, None)

    def not_compared(self, imu: int) -> str | None:
        """Why the IMU's samples are not compared now (its clock, or it lags the others), or None."""
        why = self._why_not.get(imu)
        own = self._open.get(imu)
        if why is None and own is not None and len(self._open) >= 2:
            newest = max(o.index for o in self._open.values())
            lag = newest - own.index
            if lag > self._lag_bins():
                w = self.limits.cross_imu_window_s
                why = (
                    f"IMU{imu} lags the newest IMU by {lag * w:.3g} s, beyond the "
                    f"{self._lag_bins() * w:.3g} s the comparison waits for"
                )
        return why

    def clock_unaligned(self, imu: int) -> str | None:
        """Why the IMU's clock is not aligned with the reference's yet (another clock, its offset
        still measured or not steady), or None: its samples, less its offset, are on the reference's."""
        return self._why_not.get(imu)

    @property
    def clock_offsets_s(self) -> dict[int, float]:
        """The offsets in use: an IMU's clock minus the reference IMU's, s (IMUs on another clock only)."""
        return dict(self._offset_s)

    def _lag_bins(self) -> int:
        """How many bins an IMU may lag the newest and still be waited for (class docstring)."""
        return 2 + max(self._span.values(), default=0)

    def _compare_ready(self) -> list[CrossImuReport]:
        if len(self._open) < 2:
            return []
        newest = max(o.index for o in self._open.values())
        live = [i for i, o in self._open.items() if o.index >= newest - self._lag_bins()]
        # Every live IMU has closed the bins before the horizon.
        horizon = min(self._open[i].index for i in live)
        reports: list[CrossImuReport] = []
        candidates = sorted(
            {b for i in live for b in self._closed.get(i, {}) if self._last_compared < b < horizon}
        )
        for b in candidates:
            have = [i for i in sorted(live) if b in self._closed.get(i, {})]
            self._last_compared = b
            if len(have) < 2:
                continue
            verdict = compare_imus(
                tuple(have),
                np.array([self._closed[i][b][0] for i in have]),
                np.array([self._closed[i][b][1] for i in have]),
                limits=self.limits,
                bin_start_s=b * self.limits.cross_imu_window_s,
            )
            reports.extend(self._persist(verdict))
        for closed in self._closed.values():
            for done in [k for k in closed if k <= self._last_compared]:
                del closed[done]
        return reports

    def _persist(self, v: CrossImuVerdict) -> list[CrossImuReport]:
        out = []
        for j, imu in enumerate(v.imus):
            others = tuple(i for i in v.imus if i != imu)
            if imu in v.disagreeing:
                self._agree.pop(imu, None)
                self._streak[imu] = self._streak.get(imu, 0) + 1
                if (
                    self._streak[imu] >= self.limits.cross_imu_persist_windows
                    and imu not in self._flagged
                ):
                    self._flagged.add(imu)
                    out.append(
                        CrossImuReport(
                            imu,
                            others,
                            float(v.accel_dev_mps2[j]),
                            float(v.gyro_dev_rps[j]),
                            v.bin_start_s,
                            False,
                        )
                    )
            else:
                self._streak[imu] = 0
                if imu not in self._flagged:
                    continue
                self._agree[imu] = self._agree.get(imu, 0) + 1
                if self._agree[imu] >= self.limits.cross_imu_persist_windows:
                    self._flagged.discard(imu)
                    self._agree.pop(imu)
                    out.append(
                        CrossImuReport(
                            imu,
                            others,
                            float(v.accel_dev_mps2[j]),
                            float(v.gyro_dev_rps[j]),
                            v.bin_start_s,
                            True,
                        )
                    )
        return out

    @property
    def flagged(self) -> frozenset[int]:
        """IMUs currently reported as disagreeing."""
        return frozenset(self._flagged)

    def state_dict(self) -> dict[str, Any]:
        """Everything :meth:`from_state` needs to go on exactly where this monitor is (for checkpoints).

        The reported disagreements (``flagged``) and the streaks are in it, so a restarted
        monitor does not report again what it already did; the open and pending bins, so
        it compares the same bins with the same means.
        """
        return {
            "version": CROSS_IMU_STATE_VERSION,
            "open": [
                [imu, o.index, o.n, o.accel_sum.copy(), o.gyro_sum.copy()]
                for imu, o in sorted(self._open.items())
            ],
            "span": sorted([imu, n] for imu, n in self._span.items()),
            "closed": [
                [imu, b, means[0].copy(), means[1].copy()]
                for imu, bins in sorted(self._closed.items())
                for b, means in sorted(bins.items())
            ],
            "streak": sorted([imu, n] for imu, n in self._streak.items()),
            "flagged": sorted(self._flagged),
            "last_compared": self._last_compared,
            "agree": sorted([imu, n] for imu, n in self._agree.items()),
            "reference": self._ref,
            "reference_silent": self._ref_silent,
            "newest": sorted([imu, t] for imu, t in self._newest_s.items()),
            "offsets": sorted([imu, o] for imu, o in self._offset_s.items()),
            "measuring": sorted(
                [imu, list(u), list(lo)] for imu, (u, lo) in self._measured.items()
            ),
        }

    @classmethod
    def from_state(
        cls, state: dict[str, Any], *, limits: ValidityLimits = ValidityLimits()
    ) -> CrossImuMonitor:
        """Restore from :meth:`state_dict`; ``ValueError`` for another version or a malformed state."""
        if not isinstance(state, dict) or state.get("version") not in (1, CROSS_IMU_STATE_VERSION):
            version = state.get("version") if isinstance(state, dict) else None
            raise ValueError(
                f"cross-IMU state version {version!r} is not 1 or {CROSS_IMU_STATE_VERSION}"
            )
        out = cls(limits=limits)
        try:
            for imu, index, n, accel_sum, gyro_sum in state["open"]:
                out._open[int(imu)] = _OpenBin(
                    int(index), int(n), _vec3(accel_sum), _vec3(gyro_sum)
                )
                out._closed.setdefault(int(imu), {})
            out._span = {int(imu): int(n) for imu, n in state["span"]}
            for imu, b, accel_mean, gyro_mean in state["closed"]:
                out._closed.setdefault(int(imu), {})[int(b)] = (
                    _vec3(accel_mean),
                    _vec3(gyro_mean),
                )
            out._streak = {int(imu): int(n) for imu, n in state["streak"]}
            out._flagged = {int(imu) for imu in state["flagged"]}
            out._last_compared = int(state["last_compared"])
            if state["version"] >= 2:
                out._agree = {int(imu): int(n) for imu, n in state["agree"]}
                ref = state["reference"]
                out._ref = None if ref is None else int(ref)
                out._ref_silent = int(state["reference_silent"])
                out._newest_s = {int(imu): float(t) for imu, t in state["newest"]}
                out._offset_s = {int(imu): float(o) for imu, o in state["offsets"]}
                out._measured = {
                    int(imu): ([float(x) for x in u], [float(x) for x in lo])
                    for imu, u, lo in state["measuring"]
                }
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"cross-IMU state is malformed: {type(exc).__name__}: {exc}") from None
        return out


def _vec3(values: Any) -> FloatArray:
    """A (3,) float array of a checkpointed vector; ``ValueError`` if it is not three numbers."""
    out: FloatArray = np.array(values, dtype=float).reshape(3)
    return out
