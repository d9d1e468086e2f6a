"""Static intervals and orientation changes (methods.md M1: "what to do while the unit moves").

M1's scalar relation holds only for a static unit, and its diagnosis averages
the outputs of each fixed position. This module finds those positions.

Stationarity (moving-window variance test)
------------------------------------------
Samples are first validated: a sample with a non-finite time or value, or a
time not later than the last accepted one, is rejected and counted; the rest
are *accepted* samples. A time step larger than ``max_gap_s`` starts a new
*segment* (the unit may have moved unseen); windows and intervals never span a
segment boundary.

For the window of the last ``W = round(window_s · rate_hz)`` accepted samples
of a segment ending at sample ``k``, the *window spread* of a triad is the
root of the summed per-axis sample variances (the RMS distance of the samples
from their mean, in the triad's SI unit)::

    σ_acc(k) = sqrt(Σ_i var_i(accel[k−W+1 … k]))   (m/s²)
    σ_gyr(k) = sqrt(Σ_i var_i(gyro[k−W+1 … k]))    (rad/s)

The window is *quiet* if every triad present is within its threshold
(``accel_std_mps2``, ``gyro_std_rps``) and, when ``gyro_rate_rps`` is set,
the norm of the window's mean angular rate is within it. A variance test is
blind to a rotation at a *constant* rate about the vertical (the specific force
does not change and the rate does not vary); the mean-rate bound sees it, but
must sit above the gyros' zero signal (up to ~0.05 rad/s for a MEMS unit such
as the Xsens session), so it is off by default. A sample is *static* if some quiet
window contains it, i.e. the static set is the union of the quiet windows. A
*static run* is a maximal set of consecutive static samples of one segment; a
run at least ``min_static_s`` long (last minus first time stamp) is a *static
interval*; shorter runs are reported separately.

For white noise of per-axis standard deviation σ the window spread is about
``σ·√3``; the defaults (0.05 m/s², 0.02 rad/s over 0.5 s) are about 3× the
spread of the measured Xsens MTi session (0.015 m/s², 0.0075 rad/s, see
``shared/data/measured/xsens-multiposition``), so a quiet window is missed with
negligible probability while the hand motion between positions (window spreads
of 0.3 … 5 m/s²) is far above. Set them from a unit's noise with
:meth:`StaticDetectorConfig.from_noise`, or from the session's own noise with
:meth:`StaticDetectorConfig.from_session` (what the offline commands do).

Thresholds from the session
---------------------------
:meth:`StaticDetectorConfig.from_session` cuts each triad's samples into whole
non-overlapping windows of W samples and takes their spreads. The static
windows form the low mode of that distribution: the windows whose spread is at
most ``2 ×`` the 10th percentile of all spreads are its *quiet* windows (robust
to the moving parts as long as at least ~20 % of the session rests), and their
median spread ``s̃`` is the triad's typical static spread. Then

* spread threshold ``= 3·s̃`` (floors 1e-4 m/s², 1e-5 rad/s for noise-free
  simulations). For white noise the spread of a static window has
  ``3(W − 1)`` degrees of freedom and is within ±20 % of ``s̃`` with
  probability far above 1 − 1e-6, so 3× misses no static window; a unit ten
  times noisier gets a threshold ten times larger without a flag;
* mean-rate bound ``|ω̄ − c| ≤ max(3·s̃_gyro/√W, 0.01 rad/s)`` with ``c`` the
  per-axis median of the quiet windows' mean rates (the gyros' zero signal):
  three times the noise of a window mean, floored above the Earth rate's change
  between positions and a MEMS gyro's g-sensitivity. It is what separates a
  slow turn from rest when the noise is so large (30× a MEMS unit) that the
  spread of a turning window stays under the spread threshold.

On the measured Xsens session this gives 0.040 m/s², 0.022 rad/s and a bound of
0.01 rad/s about its zero signal: the same 38 positions as the fixed defaults.

Hand-held holds
---------------
A unit held in the hand between bench rests shakes its gyros (tremor: window spreads of
0.01–0.03 rad/s on the shared MPU-6050 session, 3–10× its bench rest's, mean rates up to
0.03 rad/s) while its specific force stays put, so the thresholds of the bench rest miss the
holds (4 of that session's 10 orientations). M1 needs of a position only that the unit does not
accelerate and its mean specific force stands still (methods.md M1: "the scalar relation holds
only for a static unit"), so a hold is a position when its means are stable within the noise:

* a *held window* is a whole window whose accelerometer spread is within its threshold and
  whose mean specific force differs from each neighbour's by at most
  ``HELD_MEAN_FACTOR · √2 · s̃_acc / √W`` (the noise of the difference of two window means,
  ``s̃_acc`` the quiet windows' typical spread): the orientation stands still;
* a *hold* is at least ``ceil(HELD_MIN_S / window_s)`` consecutive held windows (1.5 s);
* its *tremor windows* are those whose gyro spread exceeds the bench threshold while their mean
  rate turns the unit by less than ``orientation_change_deg`` within one window (a turn is
  no tremor), in a hold that trembles: at least half its windows and 1.5 s of them do (a knock
  on the bench shakes a window or two of a rest, and must not raise the thresholds of a session).

With tremor windows, the gyro spread threshold and the mean-rate bound are raised to
``factor`` times their typical (median) spread and mean rate about the zero signal: the hand's
tremor sets them as the bench's noise sets them for a rest. A session without holds that tremble
keeps its thresholds. A turn keeps being seen: about a horizontal axis it moves the specific
force (no held window); about the vertical, at any rate above the tremor's mean rates, the
mean-rate bound sees it. On the MPU-6050 session: 0.046 rad/s and 0.012 rad/s, and the 10
orientations its author's tool found (``static_intervals.csv``), each of its intervals inside one
of ours.

Orientation jumps
-----------------
Two neighbouring static samples belong to one static run only if one quiet
window holds both. In a continuous recording this is implied; where the data
jump between two samples (static parts cut out and joined, a log that lost a
whole turn with uniform time stamps) every window holding both samples has the
jump inside it and is not quiet, so the run ends at the jump even though the
samples on either side are static. A jump the noise can explain leaves some
window quiet and does not end the run. The streaming detector applies the same
rule with one comparison per sample: when the decision on sample ``j`` becomes
final (the window ending at ``j + W − 1`` seen), the quiet windows ending in
``[j, j + W − 2]`` are all known, and one of them is quiet iff the latest quiet
window before the current one ends at ``j`` or later. So a stream, however it is
cut into frames, splits its runs where the batch detector does, with or without
a time gap at the jump.

The streaming form (:class:`StreamingStaticDetector`) gives the same decisions
as the batch form (:func:`detect_static`): whether sample ``j`` is static is
final once the window ending at ``j + W − 1`` has been seen (or the segment
ended), so decisions come out ``W − 1`` samples late; ``static_now`` is the
causal verdict of the latest window.

Orientation changes
-------------------
Two consecutive static intervals belong to the same position unless the unit
turned between them: the angle between their mean specific-force directions
(:func:`direction_change_deg`) and, with gyros, the angle of the rotation
integrated from the bias-compensated gyro output between them
(:class:`RotationIntegrator`) must both stay below ``orientation_change_deg``
(:func:`is_new_orientation`). The gyro check sees turns about the vertical,
which leave the specific force unchanged but change the gyros' Earth-rate
projections. :mod:`estimators.positions` applies the rule to its positions.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.quantiles import median, quantile
from estimators.session import ImuSession, Rejections, SessionError, validate_session

SESSION_NOISE_FACTOR = 3.0
"""Thresholds from the session: this many times the typical spread of its quiet windows."""
LOW_QUANTILE = 0.1
LOW_MODE_FACTOR = 2.0
"""The quiet windows: spreads up to LOW_MODE_FACTOR times the LOW_QUANTILE quantile of all spreads."""
SPREAD_FLOOR_MPS2 = 1e-4
SPREAD_FLOOR_RPS = 1e-5
"""Smallest derived spread thresholds (a noise-free, quantized simulation has zero spread)."""
HELD_MIN_S = 1.5
"""Shortest hand-held hold whose tremor sets the gyro thresholds (module docstring, "Hand-held holds")."""
HELD_MEAN_FACTOR = 4.0
"""Neighbouring window means of a held window differ by at most this many times their noise."""
RATE_BOUND_FLOOR_RPS = 0.01
"""Smallest derived mean-rate bound: above the Earth rate's change between positions (2Ω ≈ 1.5e-4
rad/s) and a MEMS gyro's g-sensitivity (≈ 1e-3 rad/s), below any hand or fixture turn (≳ 0.1 rad/s)."""


def _block_spreads(x: FloatArray, w: int) -> tuple[FloatArray, FloatArray]:
    """Spreads (root of the summed per-axis variances) and means (K, 3) of the K whole
    non-overlapping windows of ``w`` rows of ``x`` (N, 3); non-finite windows are left out."""
    k = x.shape[0] // w
    blocks = x[: k * w].reshape(k, w, 3)
    finite = np.all(np.isfinite(blocks), axis=(1, 2))
    blocks = blocks[finite]
    return np.sqrt(blocks.var(axis=1, ddof=1).sum(axis=1)), blocks.mean(axis=1)


@dataclass(frozen=True)
class StaticDetectorConfig:
    """Thresholds of the stationarity and orientation-change detectors (physical units).

    Attributes
    ----------
    window_s : length of the moving window, s (default 0.5).
    accel_std_mps2 : largest window spread of a static accelerometer triad, m/s² (default 0.05).
    gyro_std_rps : largest window spread of a static gyro triad, rad/s (default 0.02).
    gyro_rate_rps : largest norm of a static window's mean angular rate, rad/s, or None
        (default: no bound; see the module docstring).
    gyro_rate_centre_rps : (3,) rate the mean-rate bound is centred on, rad/s (default 0:
        the bound applies to ``|ω̄|``; :meth:`from_session` centres it on the zero signal).
    min_static_s : shortest static interval, s (default 1.0); shorter runs are reported apart.
    max_gap_s : a larger time step between accepted samples starts a new segment, s
        (default None: five nominal sample periods).
    orientation_change_deg : consecutive intervals closer than this (specific-force direction
        and integrated rotation) are the same position, deg (default 1.0; see
        :mod:`estimators.positions` for what merging costs).
    """

    window_s: float = 0.5
    accel_std_mps2: float = 0.05
    gyro_std_rps: float = 0.02
    gyro_rate_rps: float | None = None
    gyro_rate_centre_rps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    min_static_s: float = 1.0
    max_gap_s: float | None = None
    orientation_change_deg: float = 1.0

    def __post_init__(self) -> None:
        for name in ("window_s", "accel_std_mps2", "gyro_std_rps", "orientation_change_deg"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")
        centre = tuple(float(v) for v in self.gyro_rate_centre_rps)
        if len(centre) != 3 or not all(math.isfinite(v) for v in centre):
            raise ValueError(
                f"gyro_rate_centre_rps must be 3 finite rates, got {self.gyro_rate_centre_rps!r}"
            )
        object.__setattr__(self, "gyro_rate_centre_rps", centre)
        if not (math.isfinite(self.min_static_s) and self.min_static_s >= 0):
            raise ValueError(f"min_static_s must be finite and >= 0, got {self.min_static_s!r}")
        if self.gyro_rate_rps is not None and not (
            math.isfinite(self.gyro_rate_rps) and self.gyro_rate_rps > 0
        ):
            raise ValueError(
                f"gyro_rate_rps must be finite and > 0 or None, got {self.gyro_rate_rps!r}"
            )
        if self.max_gap_s is not None and not (
            math.isfinite(self.max_gap_s) and self.max_gap_s > 0
        ):
            raise ValueError(f"max_gap_s must be finite and > 0 or None, got {self.max_gap_s!r}")

    @classmethod
    def from_noise(
        cls,
        *,
        accel_noise_mps2: float | None = None,
        gyro_noise_rps: float | None = None,
        factor: float = 3.0,
        base: StaticDetectorConfig | None = None,
    ) -> StaticDetectorConfig:
        """``base`` (default: the defaults) with thresholds at ``factor`` times the white-noise window spread ``σ·√3``.

        ``accel_noise_mps2``, ``gyro_noise_rps`` are per-axis, per-sample standard
        deviations (a triad left None keeps its threshold); for W ≥ 10 samples the
        spread of a static window exceeds 3× its mean with probability far below
        1e-12 (χ² with 3(W−1) degrees of freedom).
        """
        out = cls() if base is None else base
        if accel_noise_mps2 is not None:
            out = replace(out, accel_std_mps2=factor * math.sqrt(3.0) * accel_noise_mps2)
        if gyro_noise_rps is not None:
            out = replace(out, gyro_std_rps=factor * math.sqrt(3.0) * gyro_noise_rps)
        return out

    @classmethod
    def from_session(
        cls,
        session: ImuSession,
        *,
        factor: float = SESSION_NOISE_FACTOR,
        base: StaticDetectorConfig | None = None,
    ) -> StaticDetectorConfig:
        """``base`` with thresholds derived from the session's own noise (module docstring,
        "Thresholds from the session"): spreads at ``factor`` times the typical spread of the
        quiet windows, and a mean-rate bound about the gyros' zero signal. The session is
        validated first (:func:`~estimators.session.validate_session`): a non-finite value or a
        repeated time stamp would otherwise set the rate and the spreads."""
        session, rejected = validate_session(session)
        if session.n_samples < 2:
            raise SessionError(
                f"{session.n_samples} usable sample(s) left after validation, too few for a rate "
                f"(rejected: {rejected.counts})"
            )
        out = cls() if base is None else base
        w = out.window_samples(session.rate_hz)
        quiet_means = None
        rate_bound = RATE_BOUND_FLOOR_RPS
        windows: dict[bool, tuple[FloatArray, FloatArray, float]] = {}
        for x, is_gyro in ((session.accel_mps2, False), (session.gyro_rps, True)):
            if x is None:
                continue
            spread, means = _block_spreads(np.asarray(x, dtype=float), w)
            if spread.size == 0:
                continue
            low = spread <= LOW_MODE_FACTOR * quantile(spread, LOW_QUANTILE)
            typical = float(median(spread[low]))
            windows[is_gyro] = (spread, means, typical)
            if is_gyro:
                out = replace(out, gyro_std_rps=max(factor * typical, SPREAD_FLOOR_RPS))
                quiet_means = means[low]
                rate_bound = max(factor * typical / math.sqrt(w), RATE_BOUND_FLOOR_RPS)
            else:
                out = replace(out, accel_std_mps2=max(factor * typical, SPREAD_FLOOR_MPS2))
        if quiet_means is not None and quiet_means.size:
            cx, cy, cz = (float(v) for v in median(quiet_means, axis=0))
            out = replace(out, gyro_rate_rps=rate_bound, gyro_rate_centre_rps=(cx, cy, cz))
            if False in windows:
                out = out._with_tremor(windows[False], windows[True], w, factor)
        return out

    def _with_tremor(
        self,
        accel: tuple[FloatArray, FloatArray, float],
        gyro: tuple[FloatArray, FloatArray, float],
        w: int,
        factor: float,
    ) -> StaticDetectorConfig:
        """These thresholds raised to the tremor of the session's hand-held holds (module
        docstring, "Hand-held holds"); unchanged without one."""
        a_spread, a_means, a_typical = accel
        g_spread, g_means, _ = gyro
        step = np.linalg.norm(np.diff(a_means, axis=0), axis=1)
        still = step <= HELD_MEAN_FACTOR * math.sqrt(2.0) * a_typical / math.sqrt(w)
        held = a_spread <= self.accel_std_mps2
        held[1:] &= still
        held[:-1] &= still
        need = math.ceil(HELD_MIN_S / self.window_s - 1e-9)
        # Runs of held windows: the run a window belongs to is counted by the breaks before it.
        run_id = np.cumsum(~held)
        run_len = np.bincount(run_id, weights=held)[run_id]
        in_hold = held & (run_len >= need)
        rate = np.linalg.norm(g_means - np.array(self.gyro_rate_centre_rps), axis=1)
        turn_limit_rps = math.radians(self.orientation_change_deg) / self.window_s
        tremor = in_hold & (g_spread > self.gyro_std_rps) & (rate <= turn_limit_rps)
        # A hand trembles through its hold; a knock on the bench shakes a window or two of a rest.
        shaking = np.bincount(run_id, weights=tremor)[run_id]
        tremor &= (shaking >= need) & (2.0 * shaking >= run_len)
        if not np.any(tremor):
            return self
        return replace(
            self,
            gyro_std_rps=max(self.gyro_std_rps, factor * float(median(g_spread[tremor]))),
            gyro_rate_rps=max(self.gyro_rate_rps or 0.0, factor * float(median(rate[tremor]))),
        )

    def window_samples(self, rate_hz: float) -> int:
        """W, samples per window at ``rate_hz`` (at least 2)."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be finite and > 0, got {rate_hz!r}")
        return max(2, round(self.window_s * rate_hz))

    def gap_limit_s(self, rate_hz: float) -> float:
        return self.max_gap_s if self.max_gap_s is not None else 5.0 / rate_hz


@dataclass(frozen=True)
class StaticInterval:
    """A static run of samples.

    Attributes
    ----------
    start, stop : input sample indices, half-open ``[start, stop)`` (rejected samples inside are skipped).
    t_start_s, t_end_s : time stamps of the first and last static sample, s.
    n_samples : accepted samples in the run.
    """

    start: int
    stop: int
    t_start_s: float
    t_end_s: float
    n_samples: int

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s


def exact_sums(x: FloatArray) -> FloatArray:
    """``math.fsum`` down each column of the windows ``x`` (R, M, K), bit for bit: (R, K).

    ``fsum`` is the exact sum correctly rounded (half to even). Vectorized: the sequential sums
    ``sᵢ = fl(sᵢ₋₁ + xᵢ)`` (``cumsum``) and each addition's exact error ``eᵢ`` (Knuth's TwoSum:
    ``sᵢ₋₁ + xᵢ = sᵢ + eᵢ``) give ``Σx = s_M + Σe`` exactly; ``E = fl(Σe)`` is within
    ``γ_M·Σ|e|`` of ``Σe`` (Higham, *Accuracy and Stability of Numerical Algorithms*, eq. 4.4,
    any order of the additions; taken twice, plus M of the least subnormal for what underflows),
    and TwoSum of ``s_M`` and ``E`` gives ``r + t = s_M + E``. When ``t`` ± that bound lies strictly
    inside half an ulp of ``r`` on either side, the exact sum rounds to ``r``: that is ``fsum``'s
    value. Any other column (a sum of zero, a near tie, a value or sum that is not finite) is
    ``fsum``'s own, and every column where a running sum of ``x`` passes 2¹⁰²¹ (fsum's own
    partials may overflow there: its OverflowError, not a finite sum).
    """
    m = x.shape[-2]
    with np.errstate(invalid="ignore", over="ignore"):  # what overflows is fsum's to sum
        s = np.cumsum(x, axis=-2)
        prev, cur = s[:, :-1], s[:, 1:]
        part = cur - prev
        err = (prev - (cur - part)) + (x[:, 1:] - part)
        err_sum = err.sum(axis=-2)
        bound = np.abs(err).sum(axis=-2) * (2.0 * m * 2.0**-53) + m * 2.0**-1074
        last = s[:, -1]
        total: FloatArray = last + err_sum
        part = total - last
        rest = (last - (total - part)) + (err_sum - part)
        up = np.nextafter(total, np.inf) - total
        down = total - np.nextafter(total, -np.inf)
        sure = (rest + bound < 0.5 * up) & (rest - bound > -0.5 * down) & (total != 0.0)
        # fsum raises where its partial sums overflow, even when the sum itself is finite; one
        # test for all the windows (an abs and a max per column cost a fifth of the whole).
        sure &= max(s.max(initial=0.0), -s.min(initial=0.0)) < 2.0**1021
    for r, k in zip(*np.nonzero(~sure), strict=True):
        total[r, k] = math.fsum(x[r, :, k].tolist())
    return total


def _required(x: FloatArray | None, name: str) -> FloatArray:
    """The samples of a triad the detector was built with."""
    if x is None:
        raise ValueError(f"{name} is required: the detector was built with that triad")
    return x


class SwitchedRing:
    """Ring-buffer storage held as Python lists on the per-sample path and as a numpy array on the batch path.

    A list element costs a third of a numpy scalar access per sample, while the
    vectorized path needs arrays: the storage converts only when the caller
    switches paths (a stream of large frames stays an array, a stream of single
    samples stays lists), not on every frame. Values are float64 or int64 either
    way, so both paths see the same bits.
    """

    __slots__ = ("_array", "_dtype", "_lists")

    def __init__(self, values: list[Any], dtype: type = float) -> None:
        self._lists: list[Any] | None = values
        self._array: NDArray[Any] | None = None
        self._dtype = dtype

    def lists(self) -> list[Any]:
        """The values as (nested) lists, for element access; valid until :meth:`array` is called."""
        if self._lists is None:
            assert self._array is not None  # the values are held in exactly one of the two forms
            lists: list[Any] = self._array.tolist()
            self._lists, self._array = lists, None
            return lists
        return self._lists

    def array(self) -> NDArray[Any]:
        """The values as an array, modified in place; valid until :meth:`lists` is called."""
        if self._array is None:
            self._array, self._lists = np.array(self._lists, dtype=self._dtype), None
        return self._array

    def snapshot(self) -> list[Any]:
        """A copy as (nested) lists, without switching paths (checkpoints)."""
        held = self._array if self._lists is None else np.array(self._lists, dtype=self._dtype)
        assert held is not None  # the values are held in exactly one of the two forms
        copy: list[Any] = held.tolist()
        return copy


@dataclass(frozen=True)
class FinalDecisions:
    """Final static decisions of the consecutive accepted samples ``start, start + 1, …``.

    What :class:`StreamingStaticDetector` finalizes over a stretch of input, as
    arrays rather than one ``(fin_lo, fin_split, fin_hi, fin_break)`` step per
    sample (the batch paths produce thousands per frame).

    Attributes
    ----------
    start : accepted-sample number of the first decision.
    static : (K,) bool, the final static flag of each sample.
    brk : (K,) bool, a segment ends after that sample.
    """

    start: int
    static: BoolArray
    brk: BoolArray

    @classmethod
    def empty(cls, start: int) -> FinalDecisions:
        return cls(int(start), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))

    @classmethod
    def from_steps(cls, start: int, steps: list[tuple[int, int, int, bool]]) -> FinalDecisions:
        """Join the per-call outputs ``(fin_lo, fin_split, fin_hi, fin_break)`` of consecutive calls (contiguous)."""
        static: list[bool] = []
        brk: list[bool] = []
        end = int(start)
        for lo, split, hi, b in steps:
            if lo != end:
                raise ValueError(f"decision steps are not contiguous: {lo} follows {end}")
            static += [True] * (split - lo) + [False] * (hi - split)
            brk += [False] * (hi - lo - 1) + [bool(b)]
            end = hi
        return cls(int(start), np.array(static, dtype=bool), np.array(brk, dtype=bool))

    @property
    def stop(self) -> int:
        """One past the last decided sample."""
        return self.start + self.static.size

    def then(self, other: FinalDecisions) -> FinalDecisions:
        """These decisions followed by ``other`` (which must start where these stop)."""
        if other.start != self.stop:
            raise ValueError(f"decisions are not contiguous: {other.start} follows {self.stop}")
        if not other.static.size:
            return self
        if not self.static.size:
            return other
        return FinalDecisions(
            self.start,
            np.concatenate([self.static, other.static]),
            np.concatenate([self.brk, other.brk]),
        )


@dataclass(frozen=True)
class StaticDetection:
    """Result of :func:`detect_static` on a session of N samples.

    Attributes
    ----------
    static : (N,) bool, True for accepted static samples.
    accepted : (M,) int, input indices of the accepted samples (increasing).
    segment_start : (M,) bool over accepted samples, True where a segment starts.
    intervals : static intervals (runs of at least ``min_static_s``), in time order.
    short_runs : static runs shorter than ``min_static_s``.
    rejections : counts of rejected samples by reason.
    config : the thresholds used.
    rate_hz : the nominal rate used (sets W and the gap limit).
    gaps : time steps between accepted samples larger than the gap limit (each starts a segment).
    longest_gap_s : the largest of them, s (0 without gaps).
    untested_samples : accepted samples in segments shorter than a window: no window holds them,
        so they can never be found static (a rate that drops mid-session leaves every sample here).
    """

    static: BoolArray
    accepted: IntArray
    segment_start: BoolArray
    intervals: tuple[StaticInterval, ...]
    short_runs: tuple[StaticInterval, ...]
    rejections: Rejections
    config: StaticDetectorConfig
    rate_hz: float
    gaps: int = 0
    longest_gap_s: float = 0.0
    untested_samples: int = 0

    @property
    def window_samples(self) -> int:
        return self.config.window_samples(self.rate_hz)


def _accepted_mask(t: FloatArray, values: list[FloatArray]) -> tuple[FloatArray, Rejections]:
    """Accepted samples: finite time and values, time later than the last accepted one."""
    rej = Rejections()
    # A row sum is non-finite iff some entry is (or the values overflow, which is no data either).
    total = t.copy()
    for v in values:
        total += v[:, 0]
        total += v[:, 1]
        total += v[:, 2]
    finite = np.isfinite(total)
    rej.add("non_finite", int(finite.size - np.count_nonzero(finite)))
    if rej.total == 0 and t.size > 1 and np.all(t[1:] > t[:-1]):
        return finite, rej
    idx = np.flatnonzero(finite)
    tk = t[idx]
    prev_max = np.maximum.accumulate(np.concatenate([[-np.inf], tk[:-1]]))
    bad = tk <= prev_max
    rej.add("non_monotonic_time", int(np.count_nonzero(bad)))
    finite[idx[bad]] = False
    return finite, rej


_CHUNK = 16384
"""Windows per block of :func:`_window_dev2`: the block's arrays stay in cache."""


_SUM_ERR = 64.0 * float(np.finfo(float).eps)
"""Relative error allowed for a running sum of squares (it grows with the terms summed)."""


def _window_dev2(
    x: FloatArray,
    w: int,
    *,
    mean_norm2: bool = False,
    centre: FloatArray | None = None,
    resolve: float,
) -> tuple[FloatArray, FloatArray | None]:
    """(M − W + 1,) summed squared deviations from the mean of the windows of ``w`` rows of ``x`` (M, 3).

    With ``mean_norm2`` also the squared norm of each window's mean minus ``centre``
    (3,) (default 0) (else None).

    Entry ``i`` is the window of rows ``i … i + w − 1``: ``Σ_axes Σ (y − ȳ)²``
    from running sums of ``y`` and ``|y|²``. The rows are processed in blocks
    (with ``w − 1`` rows of overlap), each shifted by its first row: the running
    sums then stay small where the unit rests (no cancellation between g² and the
    noise variance) and the block's arrays stay in cache. A window whose running
    sum of squares is so large that its rounding reaches ``resolve`` (the
    smallest deviation the caller must tell apart) is summed again on its own
    rows: one finite spike (1e9 m/s² in a recorded session) left 1e18 in the
    running sum, and every later window of its block looked in motion.
    """
    m = x.shape[0]
    n_win = m - w + 1
    out = np.empty(n_win)
    mean2 = np.empty(n_win) if mean_norm2 else None
    for i0 in range(0, n_win, _CHUNK):
        i1 = min(n_win, i0 + _CHUNK)
        y = x[i0 : i1 + w - 1] - x[i0]
        c1 = np.empty((y.shape[0] + 1, 3))
        c1[0] = 0.0
        np.cumsum(y, axis=0, out=c1[1:])
        c2 = np.empty(y.shape[0] + 1)
        c2[0] = 0.0
        np.cumsum(np.einsum("ij,ij->i", y, y), out=c2[1:])
        s1 = c1[w:] - c1[:-w]
        out[i0:i1] = (c2[w:] - c2[:-w]) - np.einsum("ij,ij->i", s1, s1) / w
        lost = np.flatnonzero(_SUM_ERR * c2[w:] > resolve)
        if lost.size:
            rows = np.lib.stride_tricks.sliding_window_view(y, w, axis=0)[lost]
            dev = rows - rows.mean(axis=2, keepdims=True)
            out[i0 + lost] = np.einsum("kij,kij->k", dev, dev)
            s1[lost] = rows.sum(axis=2)
        if mean2 is not None:
            mean = s1 / w + (x[i0] if centre is None else x[i0] - centre)
            mean2[i0:i1] = np.einsum("ij,ij->i", mean, mean)
    return out, mean2


def detect_static(
    session: ImuSession,
    *,
    config: StaticDetectorConfig = StaticDetectorConfig(),
    rate_hz: float | None = None,
) -> StaticDetection:
    """Static samples and intervals of a session, vectorized (module docstring).

    Parameters
    ----------
    session : t_s (N,), accel_mps2 (N, 3) and/or gyro_rps (N, 3); the triads present are used.
    config : thresholds.
    rate_hz : nominal rate that sets W and the default gap limit (default: the
        session's median rate); pass the streaming detector's rate to compare them.
    """
    t = np.asarray(session.t_s, dtype=float)
    n = t.shape[0]
    checks = [
        (np.asarray(a, dtype=float), thr, rate)
        for a, thr, rate in (
            (session.accel_mps2, config.accel_std_mps2, None),
            (session.gyro_rps, config.gyro_std_rps, config.gyro_rate_rps),
        )
        if a is not None
    ]
    if not checks:
        raise ValueError("the session has neither accelerometer nor gyro samples")
    if t.ndim != 1:
        raise ValueError(f"t_s must be 1-D, got shape {t.shape}")
    for a, _, _ in checks:
        if a.shape != (n, 3):
            raise ValueError(f"triad arrays must have shape ({n}, 3), got {a.shape}")
    if rate_hz is None:
        rate_hz = session.rate_hz
    w = config.window_samples(rate_hz)
    accepted_mask, rej = _accepted_mask(t, [a for a, _, _ in checks])
    everything = rej.total == 0
    acc = np.arange(n) if everything else np.flatnonzero(accepted_mask)
    m = acc.size
    tk = t if everything else t[acc]
    step_s = tk[1:] - tk[:-1]
    seg_start = np.ones(m, dtype=bool)
    if m > 1:
        np.greater(step_s, config.gap_limit_s(rate_hz), out=seg_start[1:])
    starts = np.flatnonzero(seg_start)
    lengths = np.diff(np.append(starts, m))

    quiet = np.zeros(m, dtype=bool)
    if m >= w:
        ok = np.ones(m - w + 1, dtype=bool)
        for a, thr, rate in checks:
            dev2, mean2 = _window_dev2(
                a if everything else a[acc],
                w,
                mean_norm2=rate is not None,
                centre=np.asarray(config.gyro_rate_centre_rps),
                resolve=1e-3 * thr * thr * (w - 1),
            )
            ok &= dev2 <= thr * thr * (w - 1)
            if rate is not None:
                assert mean2 is not None  # asked for with mean_norm2
                ok &= mean2 <= rate * rate
        quiet[w - 1 :] = ok
        # A window must lie in one segment: the first W − 1 samples of each segment end no full window.
        for s0, ln in zip(starts[1:].tolist(), lengths[1:].tolist(), strict=True):
            quiet[s0 : s0 + min(ln, w - 1)] = False
    # Union of quiet windows: sample j is static iff a quiet window ends in [j, j + W − 1].
    cq = np.empty(m + w, dtype=np.int64)
    cq[0] = 0
    np.cumsum(quiet, out=cq[1 : m + 1])
    cq[m + 1 :] = cq[m]
    static_k = cq[w : m + w] > cq[:m]
    # Neighbouring static samples j, j + 1 are one run only if a quiet window holds both, i.e.
    # ends in [j + 1, j + W − 1]: else the data jump between them (module docstring).
    linked = np.zeros(m, dtype=bool)
    if m > 1:
        linked[:-1] = cq[w : m + w - 1] > cq[1:m]

    prev = np.zeros(m, dtype=bool)
    prev[1:] = static_k[:-1]
    nxt = np.zeros(m, dtype=bool)
    nxt[:-1] = static_k[1:]
    nxt_break = np.ones(m, dtype=bool)
    nxt_break[:-1] = seg_start[1:]
    jump_before = np.zeros(m, dtype=bool)
    jump_before[1:] = ~linked[:-1]
    firsts = np.flatnonzero(static_k & (~prev | seg_start | jump_before))
    lasts = np.flatnonzero(static_k & (~nxt | nxt_break | ~linked))
    intervals: list[StaticInterval] = []
    short_runs: list[StaticInterval] = []
    for f, last in zip(firsts.tolist(), lasts.tolist(), strict=True):
        iv = StaticInterval(
            int(acc[f]), int(acc[last]) + 1, float(tk[f]), float(tk[last]), last - f + 1
        )
        (intervals if iv.duration_s >= config.min_static_s else short_runs).append(iv)
    static = np.zeros(n, dtype=bool)
    static[acc] = static_k
    return StaticDetection(
        static,
        acc,
        seg_start,
        tuple(intervals),
        tuple(short_runs),
        rej,
        config,
        float(rate_hz),
        gaps=starts.size - 1 if m else 0,
        longest_gap_s=float(step_s[seg_start[1:]].max()) if starts.size > 1 else 0.0,
        untested_samples=int(lengths[lengths < w].sum()),
    )


class StreamingStaticDetector:
    """The stationarity detector one sample at a time: O(1), ring buffers and running sums.

    ``update(t_s, ax, ay, az, gx, gy, gz)`` takes one sample (values of a triad
    the detector does not use are ignored) and returns the static interval that
    closed with it, if any (only intervals of at least ``min_static_s``). After
    each call:

    * ``static_now`` — the latest window is quiet (causal verdict: use the value
      *before* feeding a sample as that sample's static flag for F0);
    * ``fin_lo``, ``fin_split``, ``fin_hi`` — accepted-sample numbers whose
      decision became final in this call: ``[fin_lo, fin_split)`` static,
      ``[fin_split, fin_hi)`` not;
    * ``fin_break`` — a segment ended after those samples (gap, or :meth:`finish`);
    * ``fin_jump`` — the data jump just before ``fin_lo`` (a static sample): the run
      that held the sample before it closed there, and a new run starts at ``fin_lo``;
    * ``closed_run`` — the static run that closed in this call (any length) or None,
      and ``closed_run_short`` whether it is shorter than ``min_static_s``.

    Decisions equal :func:`detect_static`'s on the same samples; call
    :meth:`finish` at the end of the data to finalize the last ``W − 1``.
    Rejected samples (non-finite, time not increasing) are counted in
    ``rejections`` and leave the state untouched.
    """

    def __init__(
        self,
        config: StaticDetectorConfig = StaticDetectorConfig(),
        *,
        rate_hz: float,
        has_accel: bool = True,
        has_gyro: bool = True,
    ) -> None:
        if not (has_accel or has_gyro):
            raise ValueError("the detector needs at least one triad (has_accel or has_gyro)")
        self.config = config
        self.rate_hz = float(rate_hz)
        self.has_accel = bool(has_accel)
        self.has_gyro = bool(has_gyro)
        w = config.window_samples(rate_hz)
        self.window_samples = w
        self._gap_s = config.gap_limit_s(rate_hz)
        self._lim_a = config.accel_std_mps2**2 * (w - 1)
        self._lim_g = config.gyro_std_rps**2 * (w - 1)
        self._lim_rate = None if config.gyro_rate_rps is None else (config.gyro_rate_rps * w) ** 2
        self._rate_c = [w * c for c in config.gyro_rate_centre_rps]
        self.rejections = Rejections()
        self._buf = SwitchedRing([[0.0] * w for _ in range(6)])
        self._t = SwitchedRing([0.0] * w)
        self._idx = SwitchedRing([0] * w, int)
        self._s = [0.0] * 6
        self._q = [0.0] * 6
        self._x0 = [0.0] * 6
        self._last_t: float | None = None
        self._seg_open = False
        self.n_input = 0
        self.n_accepted = 0
        self._seg_first = 0
        self._last_quiet = -1
        self._next_final = 0
        self._run_open = False
        self._run_first_idx = 0
        self._run_first_t = 0.0
        self._run_last_idx = 0
        self._run_last_t = 0.0
        self._run_n = 0
        self.static_now = False
        self._clear_outputs()

    def _clear_outputs(self) -> None:
        self.fin_lo = self.fin_split = self.fin_hi = self._next_final
        self.fin_break = self.fin_jump = False
        self.closed_run: StaticInterval | None = None
        self.closed_run_short = False

    def update(
        self, t_s: float, ax: float, ay: float, az: float, gx: float, gy: float, gz: float
    ) -> StaticInterval | None:
        self.fin_lo = self.fin_split = self.fin_hi = self._next_final
        self.fin_break = self.fin_jump = self.closed_run_short = False
        self.closed_run = None
        self.n_input += 1
        ha, hg = self.has_accel, self.has_gyro
        chk = t_s + (ax + ay + az if ha else 0.0) + (gx + gy + gz if hg else 0.0)
        if not math.isfinite(chk):
            self.rejections.add("non_finite", 1)
            return None
        last_t = self._last_t
        if last_t is not None and not t_s > last_t:
            self.rejections.add("non_monotonic_time", 1)
            return None
        if not self._seg_open or last_t is None or t_s - last_t > self._gap_s:
            if self._seg_open:
                self._end_segment()
            self._start_segment(
                (ax, ay, az) if ha else (0.0, 0.0, 0.0), (gx, gy, gz) if hg else (0.0, 0.0, 0.0)
            )
        self._last_t = t_s
        c = self.n_accepted
        self.n_accepted = c + 1
        w = self.window_samples
        pos = c % w
        t_ring, idx_ring, buf = self._t.lists(), self._idx.lists(), self._buf.lists()
        t_ring[pos] = t_s
        idx_ring[pos] = self.n_input - 1
        n_before = c - self._seg_first  # samples of this segment already in the window
        full = n_before + 1 >= w
        pop = n_before >= w
        s, q, x0 = self._s, self._q, self._x0
        quiet = True
        # The two triads are written out rather than looped over: this is the hot path.
        if ha:
            b0, b1, b2 = buf[0], buf[1], buf[2]
            y0, y1, y2 = ax - x0[0], ay - x0[1], az - x0[2]
            if pop:
                p0, p1, p2 = b0[pos], b1[pos], b2[pos]
            else:
                p0 = p1 = p2 = 0.0
            b0[pos] = y0
            b1[pos] = y1
            b2[pos] = y2
            s0 = s[0] = s[0] + y0 - p0
            s1 = s[1] = s[1] + y1 - p1
            s2 = s[2] = s[2] + y2 - p2
            q0 = q[0] = q[0] + y0 * y0 - p0 * p0
            q1 = q[1] = q[1] + y1 * y1 - p1 * p1
            q2 = q[2] = q[2] + y2 * y2 - p2 * p2
            quiet = (q0 + q1 + q2) - (s0 * s0 + s1 * s1 + s2 * s2) / w <= self._lim_a
        if hg:
            b0, b1, b2 = buf[3], buf[4], buf[5]
            y0, y1, y2 = gx - x0[3], gy - x0[4], gz - x0[5]
            if pop:
                p0, p1, p2 = b0[pos], b1[pos], b2[pos]
            else:
                p0 = p1 = p2 = 0.0
            b0[pos] = y0
            b1[pos] = y1
            b2[pos] = y2
            s0 = s[3] = s[3] + y0 - p0
            s1 = s[4] = s[4] + y1 - p1
            s2 = s[5] = s[5] + y2 - p2
            q0 = q[3] = q[3] + y0 * y0 - p0 * p0
            q1 = q[4] = q[4] + y1 * y1 - p1 * p1
            q2 = q[5] = q[5] + y2 * y2 - p2 * p2
            quiet = quiet and (q0 + q1 + q2) - (s0 * s0 + s1 * s1 + s2 * s2) / w <= self._lim_g
            if self._lim_rate is not None and full:
                # Window sum of the rates about the centre, unshifted: Σ(ω − c) = Σy + W·x0 − W·c.
                rc = self._rate_c
                r0 = s0 + w * x0[3] - rc[0]
                r1 = s1 + w * x0[4] - rc[1]
                r2 = s2 + w * x0[5] - rc[2]
                quiet = quiet and r0 * r0 + r1 * r1 + r2 * r2 <= self._lim_rate
        if not full:
            # A run closed by a time gap comes out here.
            return (
                self.closed_run
                if (self.closed_run is not None and not self.closed_run_short)
                else None
            )
        if pos == w - 1:
            self._resum()
        self.static_now = quiet
        quiet_before = self._last_quiet
        if quiet:
            self._last_quiet = c
        j = c - w + 1
        self.fin_lo = j
        self.fin_hi = self._next_final = j + 1
        if self._last_quiet >= j:
            self.fin_split = j + 1
            if self._run_open and quiet_before < j:
                # No quiet window holds both j − 1 and j: the data jump between them.
                self._run_close()
                self.fin_jump = True
                self._run_add(j)
                return None if self.closed_run_short else self.closed_run
            if self._run_open:
                jp = j % w
                self._run_last_idx = idx_ring[jp]
                self._run_last_t = t_ring[jp]
                self._run_n += 1
            else:
                self._run_add(j)
            return None
        self.fin_split = j
        if self._run_open:
            self._run_close()
            if not self.closed_run_short:
                return self.closed_run
        return None

    @property
    def next_final(self) -> int:
        """Accepted-sample number of the next decision to become final."""
        return self._next_final

    def last_step(self) -> FinalDecisions:
        """The decisions finalized by the last call (``fin_lo`` … ``fin_hi``; empty when none)."""
        if self.fin_hi == self.fin_lo:
            return FinalDecisions.empty(self._next_final)
        return FinalDecisions.from_steps(
            self.fin_lo, [(self.fin_lo, self.fin_split, self.fin_hi, self.fin_break)]
        )

    def steady(self) -> bool:
        """A segment is open and its window full: the next clean sample finalizes exactly one decision."""
        return self._seg_open and self.n_accepted - self._seg_first >= self.window_samples

    def clean_batch(
        self, t_s: FloatArray, accel_mps2: FloatArray | None, gyro_rps: FloatArray | None
    ) -> bool:
        """Whether every sample of the batch would be accepted into the open segment (no rejection, no gap).

        The finiteness check is :meth:`update`'s (``t + Σaccel + Σgyro`` finite), elementwise in the same order.
        """
        if t_s.size == 0 or self._last_t is None:
            return False
        chk = t_s.copy()
        if self.has_accel:
            a = _required(accel_mps2, "accel_mps2")
            chk += (a[:, 0] + a[:, 1]) + a[:, 2]
        else:
            chk += 0.0
        if self.has_gyro:
            g = _required(gyro_rps, "gyro_rps")
            chk += (g[:, 0] + g[:, 1]) + g[:, 2]
        else:
            chk += 0.0
        if not np.all(np.isfinite(chk)):
            return False
        dt = np.diff(t_s, prepend=self._last_t)
        return bool(np.all(dt > 0.0) and not np.any(dt > self._gap_s))

    def update_batch(
        self, t_s: FloatArray, accel_mps2: FloatArray | None, gyro_rps: FloatArray | None
    ) -> tuple[BoolArray, dict[int, tuple[StaticInterval, bool]]]:
        """:meth:`update` over a clean batch in the steady state (:meth:`steady`, :meth:`clean_batch`), vectorized.

        Returns ``(static (N,) bool, closes)``: sample ``i`` finalizes the decision of
        accepted sample ``n_accepted₀ − W + 1 + i`` (static or not), and ``closes`` maps
        ``i`` to ``(run, short)`` for the runs that closed at sample ``i`` (where
        ``static[i]``, at a jump: a new run starts with that decision). The state,
        counters and per-call outputs after the batch are those :meth:`update` leaves.
        The running sums are rebuilt with the same additions in the same order
        (sequential ``cumsum`` of the interleaved ``+y, −p`` terms, restarted at
        each ``fsum`` re-summation), so every bit agrees.
        """
        n = t_s.shape[0]
        w = self.window_samples
        c0 = self.n_accepted
        i_res = (w - 1 - c0 % w) % w  # first sample whose ring position is W − 1 (re-summation)
        res_at = np.arange(i_res, n, w)
        old_pos = np.arange(c0 - w, c0) % w
        chans = ([0, 1, 2] if self.has_accel else []) + ([3, 4, 5] if self.has_gyro else [])
        nc = len(chans)
        x = np.column_stack(
            [
                _required(v, name)
                for v, name, present in (
                    (accel_mps2, "accel_mps2", self.has_accel),
                    (gyro_rps, "gyro_rps", self.has_gyro),
                )
                if present
            ]
        )
        y = x - np.asarray(self._x0)[chans]
        # y of the accepted samples c0 − W … c0 + n − 1 (the ring, then the batch), and their squares.
        buf = self._buf.array()
        ext = np.concatenate([buf[chans][:, old_pos].T, y])
        ext2 = ext * ext
        res = res_at.tolist()
        starts = np.empty((2 * nc, len(res) + 1))
        starts[:nc, 0] = np.asarray(self._s)[chans]
        starts[nc:, 0] = np.asarray(self._q)[chans]
        if res:
            # The windows re-summed, one after the other: _resum's fsum of each (exact_sums).
            whole = slice(i_res + 1, i_res + 1 + len(res) * w)
            starts[:nc, 1:] = exact_sums(ext[whole].reshape(len(res), w, nc)).T
            starts[nc:, 1:] = exact_sums(ext2[whole].reshape(len(res), w, nc)).T
        # Each stretch between re-summations: start, +y, −p, +y, −p, … added in update's order,
        # written into the terms straight from ext and ext2 (no joined copies of +y and −p).
        sums = np.empty((2 * nc, n))
        cuts = [0, *(i + 1 for i in res if i + 1 < n), n]
        for r, (a, b) in enumerate(itertools.pairwise(cuts)):
            z = np.empty((2 * nc, 2 * (b - a) + 1))
            z[:, 0] = starts[:, r]
            z[:nc, 1::2] = ext[w + a : w + b].T
            z[nc:, 1::2] = ext2[w + a : w + b].T
            np.negative(ext[a:b].T, out=z[:nc, 2::2])
            np.negative(ext2[a:b].T, out=z[nc:, 2::2])
            np.cumsum(z, axis=1, out=z)
            sums[:, a:b] = z[:, 2::2]
        quiet = np.ones(n, dtype=bool)
        lims = ([self._lim_a] if self.has_accel else []) + ([self._lim_g] if self.has_gyro else [])
        for k, lim in enumerate(lims):
            s0, s1, s2 = sums[3 * k : 3 * k + 3]
            q0, q1, q2 = sums[nc + 3 * k : nc + 3 * k + 3]
            quiet &= (q0 + q1 + q2) - (s0 * s0 + s1 * s1 + s2 * s2) / w <= lim
        if self.has_gyro and self._lim_rate is not None:
            s0, s1, s2 = sums[nc - 3 : nc]
            x0, rc = self._x0, self._rate_c
            r0 = s0 + w * x0[3] - rc[0]
            r1 = s1 + w * x0[4] - rc[1]
            r2 = s2 + w * x0[5] - rc[2]
            quiet &= r0 * r0 + r1 * r1 + r2 * r2 <= self._lim_rate
        final = starts[:, -1] if res and res[-1] == n - 1 else sums[:, -1]
        s_arr, q_arr = np.asarray(self._s), np.asarray(self._q)
        s_arr[chans], q_arr[chans] = final[:nc], final[nc:]
        self._s, self._q = s_arr.tolist(), q_arr.tolist()
        tail = np.arange(max(0, n - w), n)
        tail_pos = (c0 + tail) % w
        buf[np.ix_(np.asarray(chans), tail_pos)] = y[tail].T

        c = c0 + np.arange(n)
        j = c - w + 1
        last_quiet = np.maximum.accumulate(np.where(quiet, c, -1))
        np.maximum(last_quiet, self._last_quiet, out=last_quiet)
        static = last_quiet >= j
        # update's jump rule: no quiet window before the current one ends at j or later, while the run is open.
        quiet_before = np.empty_like(last_quiet)
        quiet_before[0] = self._last_quiet
        quiet_before[1:] = last_quiet[:-1]
        run_before = np.empty(n, dtype=bool)
        run_before[0] = self._run_open
        run_before[1:] = static[:-1]
        jump = static & run_before & (quiet_before < j)
        # Times and input indices of the accepted samples c0 − W … (ring, then the batch).
        t_ring, idx_ring = self._t.array(), self._idx.array()
        t_ext = np.concatenate([t_ring[old_pos], t_s])
        idx_new = self.n_input + np.arange(n)
        idx_ext = np.concatenate([idx_ring[old_pos], idx_new])
        closes: dict[int, tuple[StaticInterval, bool]] = {}
        edges = np.flatnonzero((static[1:] != static[:-1]) | jump[1:]) + 1
        bounds = [0, *edges.tolist(), n]
        for a, b in itertools.pairwise(bounds):
            if static[a]:
                if jump[a]:
                    self._run_close()
                    closed = self.closed_run
                    assert closed is not None  # the open run was just closed
                    closes[a] = (closed, self.closed_run_short)
                if not self._run_open:
                    # Sample j of batch sample a sits at a + 1 in the extended arrays.
                    self._run_open = True
                    self._run_first_idx = int(idx_ext[a + 1])
                    self._run_first_t = float(t_ext[a + 1])
                    self._run_n = 0
                self._run_last_idx = int(idx_ext[b])
                self._run_last_t = float(t_ext[b])
                self._run_n += b - a
            elif self._run_open:
                self._run_close()
                closed = self.closed_run
                assert closed is not None  # the open run was just closed
                closes[a] = (closed, self.closed_run_short)

        t_ring[tail_pos], idx_ring[tail_pos] = t_s[tail], idx_new[tail]
        self.n_input += n
        self.n_accepted += n
        self._last_t = float(t_s[-1])
        self._last_quiet = int(last_quiet[-1])
        self.static_now = bool(quiet[-1])
        jl = int(j[-1])
        self.fin_lo = jl
        self.fin_hi = self._next_final = jl + 1
        self.fin_split = jl + 1 if static[-1] else jl
        self.fin_break = False
        self.fin_jump = bool(jump[-1])
        last_close = closes.get(n - 1)
        self.closed_run, self.closed_run_short = (
            last_close if last_close is not None else (None, False)
        )
        return static, closes

    def _resum(self) -> None:
        """Recompute the running sums from the ring (once per W samples) so rounding cannot accumulate."""
        buf = self._buf.lists()
        for ch in range(6):
            b = buf[ch]
            self._s[ch] = math.fsum(b)
            self._q[ch] = math.fsum(v * v for v in b)

    def _start_segment(self, accel0: Sequence[float], gyro0: Sequence[float]) -> None:
        self._seg_open = True
        self._seg_first = self.n_accepted
        self._x0 = [float(v) for v in (*accel0, *gyro0)]
        self._s = [0.0] * 6
        self._q = [0.0] * 6
        self.static_now = False

    def _end_segment(self) -> None:
        """Finalize the pending samples of the segment (static iff a quiet window reached them) and close the run."""
        lo = self._next_final
        hi = self.n_accepted
        split = min(hi, max(lo, self._last_quiet + 1))
        for j in range(lo, split):
            self._run_add(j)
        self._run_close()
        self.fin_lo, self.fin_split, self.fin_hi = lo, split, hi
        self.fin_break = True
        self._next_final = hi

    def _run_add(self, j: int) -> None:
        pos = j % self.window_samples
        t_ring, idx_ring = self._t.lists(), self._idx.lists()
        if not self._run_open:
            self._run_open = True
            self._run_first_idx = idx_ring[pos]
            self._run_first_t = t_ring[pos]
            self._run_n = 0
        self._run_last_idx = idx_ring[pos]
        self._run_last_t = t_ring[pos]
        self._run_n += 1

    def _run_close(self) -> None:
        if not self._run_open:
            return
        self._run_open = False
        iv = StaticInterval(
            self._run_first_idx,
            self._run_last_idx + 1,
            self._run_first_t,
            self._run_last_t,
            self._run_n,
        )
        self.closed_run = iv
        self.closed_run_short = iv.duration_s < self.config.min_static_s

    def finish(self) -> StaticInterval | None:
        """End of data: finalize the pending decisions; returns the interval that closed, if any.

        The detector stays usable: the next sample starts a new segment.
        """
        self._clear_outputs()
        if self._seg_open:
            self._end_segment()
            self._seg_open = False
        self.static_now = False
        return (
            self.closed_run if (self.closed_run is not None and not self.closed_run_short) else None
        )

    def state_dict(self) -> dict[str, Any]:
        """Plain JSON-able state (config, rate and everything of the window) for checkpoints."""
        return {
            "config": asdict(self.config),
            "rate_hz": self.rate_hz,
            "has_accel": self.has_accel,
            "has_gyro": self.has_gyro,
            "buf": self._buf.snapshot(),
            "t": self._t.snapshot(),
            "idx": self._idx.snapshot(),
            "s": list(self._s),
            "q": list(self._q),
            "x0": list(self._x0),
            "last_t": self._last_t,
            "seg_open": self._seg_open,
            "n_input": self.n_input,
            "n_accepted": self.n_accepted,
            "seg_first": self._seg_first,
            "last_quiet": self._last_quiet,
            "next_final": self._next_final,
            "run": [
                self._run_open,
                self._run_first_idx,
                self._run_first_t,
                self._run_last_idx,
                self._run_last_t,
                self._run_n,
            ],
            "static_now": self.static_now,
            "rejections": dict(self.rejections.counts),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> StreamingStaticDetector:
        try:
            det = cls(
                StaticDetectorConfig(**state["config"]),
                rate_hz=float(state["rate_hz"]),
                has_accel=bool(state["has_accel"]),
                has_gyro=bool(state["has_gyro"]),
            )
            w = det.window_samples
            buf = [[float(v) for v in b] for b in state["buf"]]
            t = [float(v) for v in state["t"]]
            idx = [int(v) for v in state["idx"]]
            if len(buf) != 6 or any(len(b) != w for b in buf) or len(t) != w or len(idx) != w:
                raise ValueError(f"ring buffers must hold 6 channels of {w} samples")
            det._buf, det._t, det._idx = SwitchedRing(buf), SwitchedRing(t), SwitchedRing(idx, int)
            det._s = [float(v) for v in state["s"]]
            det._q = [float(v) for v in state["q"]]
            det._x0 = [float(v) for v in state["x0"]]
            det._last_t = None if state["last_t"] is None else float(state["last_t"])
            det._seg_open = bool(state["seg_open"])
            for name in ("n_input", "n_accepted"):
                setattr(det, name, int(state[name]))
            det._seg_first = int(state["seg_first"])
            det._last_quiet = int(state["last_quiet"])
            det._next_final = int(state["next_final"])
            ro, rfi, rft, rli, rlt, rn = state["run"]
            det._run_open, det._run_first_idx, det._run_first_t = bool(ro), int(rfi), float(rft)
            det._run_last_idx, det._run_last_t, det._run_n = int(rli), float(rlt), int(rn)
            det.static_now = bool(state["static_now"])
            det.rejections = Rejections({str(k): int(v) for k, v in state["rejections"].items()})
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"invalid StreamingStaticDetector state: {exc}") from None
        if len(det._s) != 6 or len(det._q) != 6 or len(det._x0) != 6:
            raise ValueError("invalid StreamingStaticDetector state: sums must have 6 channels")
        det._clear_outputs()
        return det


def direction_change_deg(mean_a: FloatArray, mean_b: FloatArray) -> float:
    """Angle between two mean specific-force vectors (3,), deg (atan2 form: exact at small angles)."""
    a = np.asarray(mean_a, dtype=float)
    b = np.asarray(mean_b, dtype=float)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


class RotationIntegrator:
    """Attitude change from a gyro stream, O(1) per sample (unit quaternion, plain floats).

    ``add(wx, wy, wz, dt_s)`` composes the rotation ``exp(½ (ω − bias) dt)``
    (body rate in rad/s held over ``dt_s``) on the right; ``angle_deg`` is the
    angle of the accumulated rotation. ``bias_rps`` is removed first: the mean
    gyro output of the last static position (zero signal plus Earth rate).
    """

    __slots__ = ("bias_rps", "mark", "q")

    def __init__(self, bias_rps: Iterable[float] = (0.0, 0.0, 0.0)) -> None:
        self.reset(bias_rps)

    def reset(self, bias_rps: Iterable[float] = (0.0, 0.0, 0.0)) -> None:
        self.bias_rps = tuple(float(v) for v in bias_rps)
        self.q = (1.0, 0.0, 0.0, 0.0)
        self.mark = self.q

    def add(self, wx: float, wy: float, wz: float, dt_s: float) -> None:
        bx, by, bz = self.bias_rps
        rx, ry, rz = (wx - bx) * dt_s, (wy - by) * dt_s, (wz - bz) * dt_s
        th = math.sqrt(rx * rx + ry * ry + rz * rz)
        half = 0.5 * th
        # sin(θ/2)/θ by its series below 1e-4 rad, where the division would lose digits.
        k = math.sin(half) / th if th > 1e-4 else 0.5 - th * th / 48.0
        self._compose((math.cos(half),), (rx * k,), (ry * k,), (rz * k,))

    def add_many(self, rates_rps: FloatArray, dts_s: FloatArray) -> None:
        """:meth:`add` for each row ``(wx, wy, wz)`` of ``rates_rps`` (N, 3) held over the matching ``dts_s`` (N,), in order.

        The increments are :meth:`add`'s operations on arrays: element by element the same
        IEEE operations (square root included), with sine and cosine from :mod:`math` as
        :meth:`add` takes them (numpy's may differ in the last bit), so the rotation agrees
        to the bit; only the composition stays a loop.
        """
        r = np.asarray(rates_rps, dtype=float).reshape(-1, 3) - np.asarray(self.bias_rps)
        dt = np.asarray(dts_s, dtype=float)
        if dt.shape != r.shape[:1]:
            raise ValueError(f"{r.shape[0]} rates but {dt.size} time steps")
        rx, ry, rz = r[:, 0] * dt, r[:, 1] * dt, r[:, 2] * dt
        th = np.sqrt(rx * rx + ry * ry + rz * rz)
        half = (0.5 * th).tolist()
        big = th > 1e-4
        k = 0.5 - th * th / 48.0
        # The sine only where it is taken (at rest θ is mostly below 1e-4 rad), the cosine as the loop asks.
        n_big = int(np.count_nonzero(big))
        k[big] = (
            np.fromiter(map(math.sin, itertools.compress(half, big.tolist())), float, n_big)
            / th[big]
        )
        self._compose(map(math.cos, half), (rx * k).tolist(), (ry * k).tolist(), (rz * k).tolist())

    def _compose(
        self, dws: Iterable[float], dxs: Iterable[float], dys: Iterable[float], dzs: Iterable[float]
    ) -> None:
        """Compose the increments ``(dw, dx, dy, dz)`` on the right, in order."""
        w, x, y, z = self.q
        # Plain names, not a tuple built and unpacked per sample: the same products and sums.
        for dw, dx, dy, dz in zip(dws, dxs, dys, dzs, strict=True):
            w1 = w * dw - x * dx - y * dy - z * dz
            x1 = w * dx + x * dw + y * dz - z * dy
            y1 = w * dy - x * dz + y * dw + z * dx
            z = w * dz + x * dy - y * dx + z * dw
            w, x, y = w1, x1, y1
        self.q = (w, x, y, z)

    def set_mark(self) -> None:
        """Remember the rotation so far (the start of the next static run)."""
        self.mark = self.q

    @staticmethod
    def quaternion_angle_deg(q: Sequence[float]) -> float:
        w, x, y, z = q
        return math.degrees(2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(w)))

    @property
    def angle_deg(self) -> float:
        return self.quaternion_angle_deg(self.q)

    @property
    def mark_angle_deg(self) -> float:
        return self.quaternion_angle_deg(self.mark)

    def state_dict(self) -> dict[str, Any]:
        return {"bias_rps": list(self.bias_rps), "q": list(self.q), "mark": list(self.mark)}

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> RotationIntegrator:
        try:
            r = cls(state["bias_rps"])
            q = tuple(float(v) for v in state["q"])
            mark = tuple(float(v) for v in state["mark"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"invalid RotationIntegrator state: {exc}") from None
        if len(q) != 4 or len(mark) != 4 or len(r.bias_rps) != 3:
            raise ValueError(
                "invalid RotationIntegrator state: q and mark need 4 numbers, bias_rps 3"
            )
        r.q = (q[0], q[1], q[2], q[3])
        r.mark = (mark[0], mark[1], mark[2], mark[3])
        return r


def is_new_orientation(
    config: StaticDetectorConfig, *, direction_deg: float | None, rotation_deg: float | None
) -> bool:
    """Whether a static interval is a new position (module docstring, "Orientation changes").

    ``direction_deg`` : angle between the mean specific forces (None without accelerometers);
    ``rotation_deg`` : integrated rotation between the intervals (None without gyros, or
    unknown across a time gap). With neither measure the interval is a new position.
    """
    measures = [v for v in (direction_deg, rotation_deg) if v is not None]
    if not measures:
        return True
    return any(not v < config.orientation_change_deg for v in measures)
