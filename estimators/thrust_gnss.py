"""The thrust axis against GNSS: the accelerometer's magnitude in flight checked without attitude.

The scalar method's invariance (methods.md M1: a magnitude does not depend on the
orientation) carried into flight. The specific force is ``f_n = a_n − g_n``; its
magnitude needs no attitude, so the accelerometer's ``|f̃_b|`` can be compared with
``|a_n − g_n|`` from GNSS velocity alone (raw receiver velocity: the EKF's is built
from this accelerometer and would agree with its fault).

Matching kernel. With ``V(t) = ∫v`` (GNSS, navigation frame ENU) and
``G(t) = ∫∫ C_rb f̃_b`` (accelerometer rotated into a gyro-integrated reference
frame ``r``), the end-averaged velocity difference over a window ``L`` with
end averages of ``E`` seconds is the same trapezoidal kernel ``k`` applied to
the acceleration on both sides::

    ā_L(t) = [V(t) − V(t−E) − V(t−L) + V(t−L−E)] / (E·L)           (GNSS)
    f̄_L(t) = [G(t') − G(t'−E) − G(t'−L) + G(t'−L−E)] / (E·L),  t' = t − τ   (IMU)
    D_L(t) = |f̄_L(t)| − |ā_L(t) + g₀·ẑ|

``τ`` is the GNSS latency (its velocity stamped ``t`` is the vehicle's at
``t − τ``), fitted in the learning period as the grid value that minimizes the
mean square of ``D`` in the shortest window. The frame ``r`` is the body's at the
start integrated by the gyro, its zero signal from the last rest removed: the norm
of a mean is invariant under the fixed rotation ``C_nr``, so the attitude is never
needed, and a rotation inside the window is followed sample by sample (a body-frame
mean would shrink under it). ``g₀`` is the unit's own ``|f̃|`` at the last rest on
the ground (the per-unit baseline: real units sit −0.18…+0.13 m/s² off normal
gravity), so ``D`` is zero for a healthy unit in flight whatever its calibration.

What ``D`` sees. A zero-signal change ``δ`` or a scale change ``s`` on body axis
``i`` moves ``D`` by ``u_i·δ`` or ``s·f_i·u_i``, ``u = f̃/|f̃|``. On a multicopter
the specific force stays within a few degrees of the thrust axis, so ``u_z ≈ 1`` and
``u_x, u_y ≈ 0``: the z axis is tested, x and y are **not observable** this way
(their share ``rms(u_i)`` is measured, and an axis below
:data:`OBSERVABLE_SHARE` is stated as not observable).

Noise. ``D_L`` has three parts: the GNSS velocity's white noise through the
velocity difference (∝ 1/L²), white accelerometer noise and kernel mismatch (∝ 1/L),
and an offset that does not average out (vibration rectification, the lever arm's
mean centripetal term): ``var D_L = α/L² + β/L + γ``. The three are fitted
(non-negative least squares) on the mean squares of ``D_L`` in the learning period,
the first :attr:`ThrustAxisConfig.learn_s` seconds of tested flight, so a fault
present from take-off hides in the noise: it is the check of a fault that appears
in flight. After it each epoch is judged with the larger of the learned ``σ_L`` and a running one
(``D_L²`` winsorized at ``3σ_L``, memory :attr:`ThrustAxisConfig.noise_memory_s`, read
:attr:`ThrustAxisConfig.noise_lag_s` behind the epoch so a fault does not raise the σ it is judged
with): the noise of a manoeuvre the learning did not see (the unit's own x, y errors under a
larger tilt) is then no alarm.

Detector: a generalized likelihood ratio for a step of unknown size, its onset
maximized over the windows ``L`` (a step ``δ`` that started ``t`` seconds ago gives
``D_L = δ·min(t, L)/L``)::

    z(t) = max_L |D_L(t)| / σ_L,   alarm when z(t) > h

The threshold comes from a false-alarm rate ``λ`` per flight hour: at the GNSS rate
``r`` there are ``3600·r`` epochs an hour and ``W`` windows each; counting every test
as independent (Bonferroni: conservative, the windows and epochs overlap) the
per-test probability is ``p = λ / (3600·r·W)`` and ``h = Φ⁻¹(1 − p/2)`` (two-sided);
``λ = 0.001 /h`` at 10 Hz over five windows gives ``h = 5.83`` (5.71 at 5 Hz): at 0.01 /h
(``h = 5.43``) 100 simulated flight hours at 10 Hz held one alarm, as that rate expects.

Minimum detectable fault (MDF), a step on the thrust axis detected with probability
95 % within ``t`` seconds of its onset::

    MDF(t) = min_L (h + 1.645)·σ_L / κ_L(t − τ)

``κ_L(t)`` the share of the window's kernel within the last ``t`` seconds
(:func:`kernel_fraction`: ``min(t, L)/L`` but for the end averages), ``σ_L`` the mean of those
the epochs were judged with (the learned one, or the running one where larger).

Excluded: rest (the vehicle still: ``D`` is zero by construction and says nothing of
flight; a rest period ≥ :attr:`ThrustAxisConfig.min_rest_s` sets the baseline),
windows within :attr:`ThrustAxisConfig.transient_s` of take-off or touch-down, windows
holding a clipped accelerometer sample or a gap in either stream. Each exclusion is
counted by reason.

Take-off and touch-down. Rest is declared once the averaged spread has decayed, which after an
impact takes seconds (a 50 m/s² spike in ``|f̃|²`` needs ``τ·ln(10⁴) ≈ 4.6 τ``); motion is
declared as soon as the spread rises. So a take-off is dated when motion is declared, and a
touch-down at the raw signal's last loud sample before the rest (a sample with
``|ω̃| ≥`` :attr:`ThrustAxisConfig.rest_gyro_rps` or ``|f̃|`` off the previous sample's by
:attr:`ThrustAxisConfig.rest_accel_sd_mps2` or more): the impact is then inside the excluded
neighbourhood. An epoch is judged once the accelerometer has passed it by ``transient_s`` and,
unless the vehicle is at rest, once a loud sample has come that late: while the signal is quiet a
rest may be declared and dated back over it.

GNSS outliers. A receiver's velocity can jump where the vehicle's cannot (a vertical taken from
altitude differences turns a 0.5 m altitude step into a 2.5 m/s pulse): every IMU of the vehicle
would then disagree with it at once and the accelerometer be blamed. The GNSS is therefore gated
against its own noise, without the accelerometer under test: the second difference
``Δ²v_k = v_k − 2v_{k−1} + v_{k−2}`` (the innovation of a constant-acceleration prediction) is an
outlier on an axis where ``|Δ²v_k| > c·s_{k−1}``, ``c`` = :attr:`ThrustAxisConfig.gnss_outlier_sigmas`,
``s`` the axis's running rms of ``Δ²v`` (memory :attr:`ThrustAxisConfig.gnss_memory_s`, each term
winsorized at ``c·s`` so an outlier does not widen its own gate, floored at
:attr:`ThrustAxisConfig.gnss_noise_floor_mps`). A window holding an outlier epoch is not judged.
An accelerometer fault does not move the GNSS, so the gate costs no detection, only the windows
around the outlier (counted).

One monitor serves both paths: :func:`thrust_axis_batch` feeds a whole flight in one
call (every step vectorized over the samples); the daemon calls
:meth:`ThrustAxisMonitor.update_imu` and :meth:`ThrustAxisMonitor.update_gnss` per
frame, and the two give the same evaluations.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from statistics import NormalDist
from typing import Any

import numpy as np

# scipy (optimize, spatial.transform, and the strapdown module through it; linalg in the
# low-passes) is imported where it is used: together about a second to import, and the daemon and
# replay import this module for every run, GNSS or not.
from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.conventions import Triad
from estimators.coverage import IN_FLIGHT_WITHIN_S, OBSERVABLE_SHARE, Check, CheckCoverage
from estimators.first_order_filter import first_order_filter

DETECTION_QUANTILE = NormalDist().inv_cdf(0.95)
"""The MDF's margin above the threshold: a step at the MDF is detected with probability 95 %."""

THRUST_AXIS = 2
"""The body axis the specific force follows on a multicopter: z."""

MAX_SPEED_MPS = 515.0
"""The largest GNSS velocity component a reader hands the check, m/s: a civil receiver reports none
above 1,000 knots (the COCOM export limit), so a larger one is a damaged value. The check must not
take one: its velocity integral ``V`` carries it, and the differences of ``V`` that make ``ā_L``
are lost to rounding (1e17 m/s alarmed on a sound unit; 1e15 m/s was harmless). The readers leave
such epochs out and count them: :mod:`protocols.gnss_logs` (replay) and the daemon's intake."""


class Exclusion(IntEnum):
    """Why an epoch was not tested (0: tested)."""

    TESTED = 0
    HISTORY = 1
    NO_BASELINE = 2
    REST = 3
    TRANSIENT = 4
    CLIPPED = 5
    GAP = 6
    GNSS_OUTLIER = 7


@dataclass(frozen=True)
class ThrustAxisConfig:
    """Settings of the thrust-axis check (SI; the reasons are in the module docstring).

    Attributes
    ----------
    windows_s : the velocity-difference windows ``L``, s, shortest first.
    end_s : the end averages ``E``, s.
    latency_grid_s : GNSS latencies tried, s.
    learn_s : tested flight time that learns the noise and the latency, s.
    noise_memory_s, noise_lag_s : the running noise estimate's memory and how far behind the
        epoch it judges it is read, s.
    false_alarms_per_hour : ``λ``, the design rate of false alarms per flight hour.
    rest_accel_sd_mps2, rest_gyro_rps : rest is a spread of ``|f̃|`` and a mean ``|ω̃|``
        below these (exponential averages of ``rest_tau_s``).
    min_rest_s : a rest this long sets the ground baseline, s.
    transient_s : windows this close to a rest ↔ motion change are excluded, s.
    clip_mps2 : an accelerometer axis at or beyond this is clipped.
    gnss_outlier_sigmas, gnss_memory_s, gnss_noise_floor_mps : the GNSS outlier gate's ``c``, its
        running rms's memory (s) and that rms's floor (m/s) (module docstring).
    max_gap_s : a step between samples of either stream longer than this is a gap, s.
    gnss_late_s : GNSS epochs this far behind the IMU are not judged (its history is let go), s.
    sigma_floor_mps2 : the smallest ``σ_L`` trusted.
    """

    windows_s: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0)
    end_s: float = 1.0
    latency_grid_s: tuple[float, ...] = tuple(np.round(np.arange(0.0, 0.401, 0.02), 3))
    learn_s: float = 60.0
    noise_memory_s: float = 120.0
    noise_lag_s: float = 20.0
    false_alarms_per_hour: float = 0.001
    rest_accel_sd_mps2: float = 0.15
    rest_gyro_rps: float = 0.05
    rest_tau_s: float = 0.5
    min_rest_s: float = 2.0
    transient_s: float = 2.0
    clip_mps2: float = 150.0
    gnss_outlier_sigmas: float = 6.0
    gnss_memory_s: float = 60.0
    gnss_noise_floor_mps: float = 0.02
    max_gap_s: float = 0.5
    gnss_late_s: float = 60.0
    sigma_floor_mps2: float = 0.002

    def __post_init__(self) -> None:
        w = np.asarray(self.windows_s, float)
        if w.ndim != 1 or w.size == 0 or np.any(w <= 0) or np.any(np.diff(w) <= 0):
            raise ValueError(
                f"windows_s must be increasing positive lengths, got {self.windows_s!r}"
            )
        grid = np.asarray(self.latency_grid_s, float)
        if grid.ndim != 1 or grid.size == 0 or np.any(grid < 0):
            raise ValueError(f"latency_grid_s must be non-negative, got {self.latency_grid_s!r}")
        for name in (
            "end_s",
            "learn_s",
            "false_alarms_per_hour",
            "rest_tau_s",
            "max_gap_s",
            "gnss_outlier_sigmas",
            "gnss_memory_s",
            "gnss_noise_floor_mps",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value!r}")

    @property
    def span_s(self) -> float:
        """How far back an epoch's window reaches, latency included, s."""
        return max(self.windows_s) + self.end_s + max(self.latency_grid_s)


def threshold(false_alarms_per_hour: float, gnss_rate_hz: float, n_windows: int) -> float:
    """``h = Φ⁻¹(1 − p/2)``, ``p = λ / (3600·r·W)`` (the module docstring's derivation)."""
    p = false_alarms_per_hour / (3600.0 * gnss_rate_hz * n_windows)
    return NormalDist().inv_cdf(1.0 - 0.5 * p)


@dataclass(frozen=True)
class NoiseModel:
    """``σ_L`` of each window and what they were learned from."""

    latency_s: float
    sigma_mps2: FloatArray
    coefficients: FloatArray
    epochs: int


@dataclass(frozen=True)
class Evaluations:
    """The epochs judged by one update (``M`` epochs, ``W`` windows).

    ``d_mps2`` (M, W) is ``D_L`` of the tested epochs at the fitted latency (at zero latency while
    learning; NaN where excluded);
    ``z`` (M,) is ``max_L |D_L|/σ_L`` (NaN before the noise is learned or when excluded);
    ``excluded`` (M,) the :class:`Exclusion` code.
    """

    t_s: FloatArray
    d_mps2: FloatArray
    z: FloatArray
    excluded: IntArray
    alarm: BoolArray

    @staticmethod
    def empty(n_windows: int) -> Evaluations:
        return Evaluations(
            np.empty(0),
            np.empty((0, n_windows)),
            np.empty(0),
            np.empty(0, np.intp),
            np.empty(0, bool),
        )

    @staticmethod
    def concatenate(parts: list[Evaluations], n_windows: int) -> Evaluations:
        if not parts:
            return Evaluations.empty(n_windows)
        return Evaluations(
            np.concatenate([p.t_s for p in parts]),
            np.concatenate([p.d_mps2 for p in parts]),
            np.concatenate([p.z for p in parts]),
            np.concatenate([p.excluded for p in parts]),
            np.concatenate([p.alarm for p in parts]),
        )


@dataclass(frozen=True)
class Summary:
    """What the check tested over the samples seen so far (for the coverage statement).

    ``share`` (3,) is the rms of ``f̃_i/|f̃|`` in flight per body axis; ``observable`` (3,) says
    which axes reach :data:`OBSERVABLE_SHARE`; ``mdf_10s_mps2`` is ``MDF(10 s)`` on the thrust
    axis (None until the noise is learned); ``exclusions`` counts epochs per :class:`Exclusion`.
    """

    tested_epochs: int
    exclusions: dict[str, int]
    flight_s: float
    share: FloatArray
    observable: BoolArray
    latency_s: float | None
    baseline_mps2: float | None
    threshold: float
    false_alarms_per_hour: float
    mdf_10s_mps2: float | None
    alarms: int
    first_alarm_t_s: float | None


def _carry_integral(
    start: FloatArray, first: FloatArray, values: FloatArray, dt: FloatArray
) -> FloatArray:
    """(N, 3) trapezoid integral of ``values`` continuing from ``start``, the integral at the sample
    before them, whose value was ``first`` (``dt[0]`` the step from it)."""
    y = np.concatenate([first[None], values])
    out: FloatArray = start + np.cumsum(0.5 * (y[1:] + y[:-1]) * dt[:, None], axis=0)
    return out


def _count_between(t: FloatArray, counts: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """Events counted in ``counts`` (cumulative, with a leading base) at samples in ``[lo, hi]``."""
    out: FloatArray = (
        counts[np.searchsorted(t, hi, "right")] - counts[np.searchsorted(t, lo, "left")]
    )
    return out


def _interp3(x: FloatArray, t: FloatArray, y: FloatArray) -> FloatArray:
    """(…, 3) ``y`` (N, 3) at the times ``x`` (…), linearly."""
    return np.stack([np.interp(x, t, y[:, k]) for k in range(3)], axis=-1)


def _kernel_means(
    x: FloatArray, t: FloatArray, integral: FloatArray, end_s: float, windows_s: FloatArray
) -> FloatArray:
    """(…, W, 3) ``[I(x) − I(x−E) − I(x−L) + I(x−L−E)]/(E·L)`` of a double integral ``I``."""
    xw = x[..., None]
    total = (
        _interp3(xw, t, integral)
        - _interp3(xw - end_s, t, integral)
        - _interp3(xw - windows_s, t, integral)
        + _interp3(xw - windows_s - end_s, t, integral)
    )
    out: FloatArray = total / (end_s * windows_s)[:, None]
    return out


def up_velocity_from_altitude(t_s: FloatArray, alt_m: FloatArray) -> FloatArray:
    """(M,) vertical velocity, m/s, from altitudes: the centred difference
    ``(h_{k+1} − h_{k−1})/(t_{k+1} − t_{k−1})`` (one-sided at the ends), the mean velocity over
    the neighbouring epochs, for a receiver that reports no vertical velocity (GPS_RAW_INT)."""
    t = np.asarray(t_s, float)
    h = np.asarray(alt_m, float)
    if t.ndim != 1 or h.shape != t.shape or t.size < 2 or np.any(np.diff(t) <= 0):
        raise ValueError(
            f"need (M,) increasing times and (M,) altitudes, M >= 2; got {t.shape}, {h.shape}"
        )
    out: FloatArray = np.gradient(h, t) if t.size < 3 else np.empty(t.size)
    if t.size >= 3:
        out[1:-1] = (h[2:] - h[:-2]) / (t[2:] - t[:-2])
        out[0] = (h[1] - h[0]) / (t[1] - t[0])
        out[-1] = (h[-1] - h[-2]) / (t[-1] - t[-2])
    return out


def kernel_fraction(t_s: float, end_s: float, windows_s: FloatArray) -> FloatArray:
    """(W,) the share of each window's trapezoidal kernel within the last ``t_s`` seconds: how
    much of a step ``t_s`` old ``D_L`` shows (``box_L ∗ box_E``, rising over ``min(E, L)``)."""
    windows = np.asarray(windows_s, float)
    s = np.linspace(0.0, 1.0, 2001)[:, None] * (windows + end_s)
    k = np.clip(np.minimum(s, windows + end_s - s), 0.0, np.minimum(end_s, windows))
    out: FloatArray = np.sum(k * (s <= max(t_s, 0.0)), axis=0) / np.sum(k, axis=0)
    return out


def _parabola_minimum(x: FloatArray, ms: FloatArray, best: int) -> tuple[float, FloatArray]:
    """The latency at the vertex of the parabola through the shortest window's grid minimum
    ``best`` and its neighbours, and every window's mean square there.

    A latency error ``δτ`` adds ``δτ·J`` to ``D`` (``J`` the kernel-smoothed jerk), so the mean
    square is a parabola in ``τ``: interpolating it is exact, not an approximation. At an end of
    the grid, or where the three points are not convex, the grid point itself.
    """
    if best == 0 or best == x.size - 1:
        return float(x[best]), ms[best]
    xs, ys = x[best - 1 : best + 2], ms[best - 1 : best + 2]
    coef = np.polyfit(xs - xs[1], ys, 2)
    if coef[0, 0] <= 0:
        return float(x[best]), ms[best]
    step = float(np.clip(-0.5 * coef[1, 0] / coef[0, 0], xs[0] - xs[1], xs[2] - xs[1]))
    at: FloatArray = np.maximum(coef[0] * step**2 + coef[1] * step + coef[2], 0.0)
    return float(xs[1] + step), at


@dataclass
class _Imu:
    """The integrated accelerometer stream, trimmed to the span the epochs still need.

    ``f_int`` is ``∫ C_rb f̃`` (N, 3); ``g0`` (N,) the ground baseline each sample flies with (NaN
    before any); ``rest`` and ``clip`` and ``gap`` are cumulative counts with a leading base.
    """

    t_s: FloatArray = field(default_factory=lambda: np.empty(0))
    f_int: FloatArray = field(default_factory=lambda: np.empty((0, 3)))
    g0: FloatArray = field(default_factory=lambda: np.empty(0))
    counts: FloatArray = field(default_factory=lambda: np.zeros((1, 3)))
    quat_rb: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    f_r: FloatArray = field(default_factory=lambda: np.zeros(3))
    int_f_r: FloatArray = field(default_factory=lambda: np.zeros(3))
    gyro_rps: FloatArray = field(default_factory=lambda: np.zeros(3))
    filter_state: FloatArray | None = None
    filter_a: float = 0.0
    resting: bool = False
    last_loud_s: float = -np.inf
    last_mag_mps2: float = np.nan
    rest_start_s: float = np.nan
    rest_sums: FloatArray = field(default_factory=lambda: np.zeros(5))
    transitions_s: list[float] = field(default_factory=list)


@dataclass
class _Gnss:
    t_s: FloatArray = field(default_factory=lambda: np.empty(0))
    v_int: FloatArray = field(default_factory=lambda: np.empty((0, 3)))
    gaps: FloatArray = field(default_factory=lambda: np.zeros(1))
    outliers: FloatArray = field(default_factory=lambda: np.zeros(1))
    last_vel: FloatArray = field(default_factory=lambda: np.zeros(3))
    recent_vel: FloatArray = field(default_factory=lambda: np.empty((0, 3)))
    """The last two velocities (the second difference's history)."""
    jerk_ms: list[float] = field(default_factory=list)
    """The running mean square of ``Δ²v`` per axis (empty before the first second difference)."""
    pending: int = 0
    """How many of the newest epochs still wait for the accelerometer to pass them."""


_REST, _CLIP, _GAP = 0, 1, 2


class ThrustAxisMonitor:
    """The thrust-axis check of one IMU against one GNSS receiver (module docstring).

    Feed both streams in time order, in frames of any size; each update returns the epochs it
    could judge (:class:`Evaluations`). An epoch is judged once the accelerometer has passed it
    by ``transient_s`` (and, in motion, a loud sample has come that late: module docstring).
    """

    def __init__(self, config: ThrustAxisConfig | None = None, *, gnss_rate_hz: float = 10.0):
        if not (np.isfinite(gnss_rate_hz) and gnss_rate_hz > 0):
            raise ValueError(f"gnss_rate_hz must be positive, got {gnss_rate_hz!r}")
        self.config = config or ThrustAxisConfig()
        self.gnss_rate_hz = float(gnss_rate_hz)
        self._windows = np.asarray(self.config.windows_s, float)
        self._latencies = np.asarray(self.config.latency_grid_s, float)
        self.threshold = threshold(
            self.config.false_alarms_per_hour, self.gnss_rate_hz, self._windows.size
        )
        self.baseline_mps2: float | None = None
        self.gyro_bias_rps = np.zeros(3)
        self.noise: NoiseModel | None = None
        self.exclusions = np.zeros(len(Exclusion), np.int64)
        self.alarms = 0
        self.first_alarm_t_s: float | None = None
        self._flight_samples = 0
        self._share_sums = np.zeros(3)
        self._imu = _Imu()
        self._gnss = _Gnss()
        self._learn_sq = np.zeros((self._latencies.size, self._windows.size))
        self._learn_n = 0
        self._running_state: FloatArray | None = None
        self._running_lagged = np.empty((0, self._windows.size))
        self._sigma_sums = np.zeros(self._windows.size)
        self._sigma_n = 0
        self._learn_target = max(1, round(self.config.learn_s * self.gnss_rate_hz))

    # --- inputs ----------------------------------------------------------------------

    def update_imu(
        self, t_s: FloatArray, accel_mps2: FloatArray, gyro_rps: FloatArray
    ) -> Evaluations:
        """Take IMU samples (SI, body axes, finite; ``t_s`` increasing past the last one)."""
        t = np.asarray(t_s, float)
        # Copies: scipy's rotations refuse a read-only buffer (a frame's arrays are frozen).
        f = np.array(accel_mps2, dtype=float)
        w = np.array(gyro_rps, dtype=float)
        if t.ndim != 1 or f.shape != (t.size, 3) or w.shape != (t.size, 3):
            raise ValueError(
                f"t_s (N,), accel_mps2 and gyro_rps (N, 3) expected, got {t.shape}, {f.shape}, {w.shape}"
            )
        if t.size and not (
            np.all(np.isfinite(t)) and np.all(np.isfinite(f)) and np.all(np.isfinite(w))
        ):
            raise ValueError("IMU samples must be finite")
        last = self._imu.t_s[-1] if self._imu.t_s.size else -np.inf
        if t.size and (t[0] <= last or np.any(np.diff(t) <= 0)):
            raise ValueError(f"IMU times must increase (last {last}, got {t[0]} first)")
        if t.size:
            rest, loud = self._rest_mask(t, f, w)
            loud_t = np.maximum.accumulate(np.r_[self._imu.last_loud_s, np.where(loud, t, -np.inf)])
            bias, g0 = self._baselines(t, f, w, rest, loud_t[:-1])
            self._imu.last_loud_s = float(loud_t[-1])
            self._integrate(t, f, w - bias, rest, g0)
        out = self._evaluate_ready()
        self._trim()
        return out

    def update_gnss(self, t_s: FloatArray, vel_enu_mps: FloatArray) -> Evaluations:
        """Take GNSS velocity epochs (m/s, East-North-Up, the receiver's own: not a filter's; each
        component at most :data:`MAX_SPEED_MPS`, which the readers see to)."""
        t = np.asarray(t_s, float)
        v = np.asarray(vel_enu_mps, float)
        if t.ndim != 1 or v.shape != (t.size, 3):
            raise ValueError(f"t_s (M,) and vel_enu_mps (M, 3) expected, got {t.shape}, {v.shape}")
        if t.size and not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
            raise ValueError("GNSS epochs must be finite")
        g = self._gnss
        have_prev = g.t_s.size > 0
        last = g.t_s[-1] if have_prev else -np.inf
        if t.size and (t[0] <= last or np.any(np.diff(t) <= 0)):
            raise ValueError(f"GNSS times must increase (last {last}, got {t[0]} first)")
        if t.size:
            t_prev = np.concatenate([[g.t_s[-1] if have_prev else t[0]], t])
            dt = np.diff(t_prev)
            start = g.v_int[-1] if have_prev else np.zeros(3)
            g.v_int = np.concatenate(
                [g.v_int, _carry_integral(start, g.last_vel if have_prev else v[0], v, dt)]
            )
            g.gaps = np.concatenate([g.gaps, g.gaps[-1] + np.cumsum(dt > self.config.max_gap_s)])
            g.outliers = np.concatenate([g.outliers, g.outliers[-1] + np.cumsum(self._outliers(v))])
            g.t_s = np.concatenate([g.t_s, t])
            g.last_vel = v[-1]
            g.pending += t.size
        out = self._evaluate_ready()
        self._trim()
        return out

    def _outliers(self, v: FloatArray) -> BoolArray:
        """(M,) the new epochs whose velocity is a GNSS outlier (module docstring: ``Δ²v`` against
        its own running rms). The rms is a recursion (the winsorizing depends on the rms so far),
        run on plain floats: numpy per epoch cost a microsecond per IMU sample."""
        g, cfg = self._gnss, self.config
        c2 = cfg.gnss_outlier_sigmas**2
        a = float(np.exp(-1.0 / (self.gnss_rate_hz * cfg.gnss_memory_s)))
        floor = cfg.gnss_noise_floor_mps**2
        history = np.concatenate([g.recent_vel, v])
        g.recent_vel = history[-2:]
        jerk_sq = (np.diff(history, n=2, axis=0) ** 2).tolist()
        out = np.zeros(v.shape[0], bool)
        ms = g.jerk_ms
        first = v.shape[0] - len(jerk_sq)
        for k, sq in enumerate(jerk_sq, start=first):
            ms = [max(m, floor) for m in ms] if ms else [floor] * 3
            out[k] = any(q > c2 * m for q, m in zip(sq, ms, strict=True))
            ms = [a * m + (1.0 - a) * min(q, c2 * m) for q, m in zip(sq, ms, strict=True)]
        g.jerk_ms = ms
        return out

    # --- the accelerometer's integration -----------------------------------------------

    def _rest_mask(
        self, t: FloatArray, f: FloatArray, w: FloatArray
    ) -> tuple[BoolArray, BoolArray]:
        """Rest: the exponential averages of ``|f̃|``, ``|f̃|²`` and ``|ω̃|`` quiet (carried across
        frames); and the loud samples (module docstring: the raw signal not quiet)."""
        imu = self._imu
        mag = np.linalg.norm(f, axis=1)
        x = np.stack([mag, mag * mag, np.linalg.norm(w, axis=1)])
        if imu.filter_state is None:
            # The coefficient is fixed by the first frame's step, so every framing filters alike.
            step = float(np.median(np.diff(t))) if t.size > 1 else 0.01
            imu.filter_a = float(np.exp(-step / self.config.rest_tau_s))
            imu.filter_state = imu.filter_a * x[:, :1]
        a = imu.filter_a
        # lfilter([1 − a], [1, −a], x, axis=1)'s numbers (its inputs, magnitudes, are not negative).
        y, state = first_order_filter(1.0 - a, -a, x.T, imu.filter_state.T)
        y, imu.filter_state = y.T, state.T
        spread = np.sqrt(np.maximum(y[1] - y[0] ** 2, 0.0))
        rest: BoolArray = (spread < self.config.rest_accel_sd_mps2) & (
            y[2] < self.config.rest_gyro_rps
        )
        # Against the previous sample, not the average: the average still carries the impact.
        step = np.abs(np.diff(np.r_[imu.last_mag_mps2, mag]))
        imu.last_mag_mps2 = float(mag[-1])
        loud: BoolArray = (step >= self.config.rest_accel_sd_mps2) | (
            x[2] >= self.config.rest_gyro_rps
        )
        return rest, loud

    def _baselines(
        self, t: FloatArray, f: FloatArray, w: FloatArray, rest: BoolArray, loud_before: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Per sample, the gyro zero signal it is integrated with and the ground baseline ``g₀``.

        A rest of ``min_rest_s`` or more sets ``g₀`` (its mean ``|f̃|``) and the gyro zero
        signal (its mean ``ω̃``) for the flight that follows; each rest ↔ motion change is a
        transition whose neighbourhood is excluded, a rest's start dated back to the last loud
        sample before it (``loud_before``, the time of the last loud sample before each sample).
        """
        imu = self._imu
        bias = np.empty((t.size, 3))
        g0 = np.empty(t.size)
        mag = np.linalg.norm(f, axis=1)
        edges = np.flatnonzero(np.diff(rest.astype(np.int8))) + 1
        for a, b in zip(np.r_[0, edges], np.r_[edges, t.size], strict=True):
            if rest[a]:
                if not imu.resting:
                    quiet_from = loud_before[a] if np.isfinite(loud_before[a]) else t[a]
                    last = imu.transitions_s[-1] if imu.transitions_s else -np.inf
                    imu.transitions_s.append(float(max(quiet_from, last)))
                    imu.rest_start_s = float(t[a])
                    imu.rest_sums[:] = 0.0
                    imu.resting = True
                imu.rest_sums += np.r_[b - a, mag[a:b].sum(), w[a:b].sum(axis=0)]
                if t[b - 1] - imu.rest_start_s >= self.config.min_rest_s:
                    self.baseline_mps2 = float(imu.rest_sums[1] / imu.rest_sums[0])
                    self.gyro_bias_rps = imu.rest_sums[2:] / imu.rest_sums[0]
            elif imu.resting:
                imu.transitions_s.append(float(t[a]))
                imu.resting = False
            bias[a:b] = self.gyro_bias_rps
            # A rest is never judged: its samples carry no baseline, so both paths agree on them.
            g0[a:b] = np.nan if rest[a] or self.baseline_mps2 is None else self.baseline_mps2
        moving = ~rest
        self._flight_samples += int(moving.sum())
        self._share_sums += ((f[moving] / mag[moving, None]) ** 2).sum(axis=0)
        return bias, g0

    def _integrate(
        self, t: FloatArray, f: FloatArray, w: FloatArray, rest: BoolArray, g0: FloatArray
    ) -> None:
        """Append ``∫ C_rb f̃`` at the new samples (trapezoids; the carries make frames seamless)."""
        from scipy.spatial.transform import Rotation

        from estimators.strapdown import cumulative_product, quat_from_rotvec

        imu = self._imu
        have_prev = imu.t_s.size > 0
        if not have_prev:
            imu.gyro_rps = w[0]
        dt = np.diff(np.r_[imu.t_s[-1] if have_prev else t[0], t])
        steps = quat_from_rotvec(0.5 * (np.vstack([imu.gyro_rps, w[:-1]]) + w) * dt[:, None])
        q = cumulative_product(np.vstack([imu.quat_rb, steps]))[1:]
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        f_r = Rotation.from_quat(q).apply(f)
        int_f = _carry_integral(imu.int_f_r, imu.f_r if have_prev else f_r[0], f_r, dt)
        flags = np.column_stack(
            [rest, np.any(np.abs(f) >= self.config.clip_mps2, axis=1), dt > self.config.max_gap_s]
        )
        imu.counts = np.vstack([imu.counts, imu.counts[-1] + np.cumsum(flags, axis=0)])
        imu.t_s = np.r_[imu.t_s, t]
        imu.f_int = np.vstack([imu.f_int, int_f])
        imu.g0 = np.r_[imu.g0, g0]
        imu.quat_rb, imu.f_r, imu.int_f_r, imu.gyro_rps = q[-1], f_r[-1], int_f[-1], w[-1]

    # --- the epochs ---------------------------------------------------------------------

    def _exclusions(self, tk: FloatArray) -> IntArray:
        imu, g, cfg = self._imu, self._gnss, self.config
        lo = tk - cfg.span_s
        code = np.zeros(tk.size, np.intp)
        history = (lo < imu.t_s[0]) | (lo < g.t_s[0])
        g0 = np.interp(tk, imu.t_s, imu.g0)
        counts = [_count_between(imu.t_s, imu.counts[:, k], lo, tk) for k in range(3)]
        trans = np.asarray(imu.transitions_s, float)
        near = np.zeros(tk.size, bool)
        if trans.size:
            first_after = np.searchsorted(trans, lo - cfg.transient_s, "left")
            near = (first_after < trans.size) & (
                trans[np.minimum(first_after, trans.size - 1)] <= tk + cfg.transient_s
            )
        gnss_gaps = _count_between(g.t_s, g.gaps, lo, tk)
        outliers = _count_between(g.t_s, g.outliers, lo, tk)
        # The last reason that applies is the one counted: a window too early for its span is
        # history whatever it holds, and one holding rest has no baseline by construction.
        for reason, mask in (
            (Exclusion.GNSS_OUTLIER, outliers > 0),
            (Exclusion.GAP, (counts[_GAP] > 0) | (gnss_gaps > 0)),
            (Exclusion.CLIPPED, counts[_CLIP] > 0),
            (Exclusion.TRANSIENT, near),
            (Exclusion.NO_BASELINE, ~np.isfinite(g0)),
            (Exclusion.REST, counts[_REST] > 0),
            (Exclusion.HISTORY, history),
        ):
            code[mask] = reason
        return code

    def _residuals(self, tk: FloatArray, latency_s: FloatArray) -> FloatArray:
        """(M, T, W) ``D_L`` of the epochs ``tk`` (M,) at the latencies (T,).

        The IMU side goes through the GNSS side's own operator: ``∫ C_rb f̃`` taken at the kept
        epochs' times less the latency, integrated over the epochs by the same trapezoids as the
        velocity, then the same kernel. The GNSS's sampling of a fast manoeuvre (a 10 Hz
        trapezoid misses ``dt²/12`` of the acceleration's change) is then made on both sides
        alike; only the differences over the span are used, so the integral's start is free.
        """
        imu, g, cfg = self._imu, self._gnss, self.config
        a_n = _kernel_means(tk, g.t_s, g.v_int, cfg.end_s, self._windows)
        a_n[..., 2] += np.interp(tk, imu.t_s, imu.g0)[:, None]
        at_epochs = _interp3(g.t_s[:, None] - latency_s, imu.t_s, imu.f_int)
        steps = 0.5 * (at_epochs[1:] + at_epochs[:-1]) * np.diff(g.t_s)[:, None, None]
        w_int = np.concatenate([np.zeros((1, *at_epochs.shape[1:])), np.cumsum(steps, axis=0)])
        f_r = np.stack(
            [
                _kernel_means(tk, g.t_s, w_int[:, j], cfg.end_s, self._windows)
                for j in range(latency_s.size)
            ],
            axis=1,
        )
        out: FloatArray = np.linalg.norm(f_r, axis=-1) - np.linalg.norm(a_n, axis=-1)[:, None, :]
        return out

    def _learn(self, tk: FloatArray) -> int:
        """Accumulate the learning epochs among ``tk`` (all tested); the index where learning ended."""
        from scipy.optimize import nnls

        need = self._learn_target - self._learn_n
        take = tk[:need]
        self._learn_sq += (self._residuals(take, self._latencies) ** 2).sum(axis=0)
        self._learn_n += take.size
        if self._learn_n >= self._learn_target:
            ms = self._learn_sq / self._learn_n
            best = int(np.argmin(ms[:, 0]))
            latency, at_latency = _parabola_minimum(self._latencies, ms, best)
            design = np.column_stack(
                [self._windows**-2, 1.0 / self._windows, np.ones(self._windows.size)]
            )
            # Weights 1/(the standard error of each mean square): ms·√(windows of L in learn_s).
            n_eff = np.maximum(self.config.learn_s / (self._windows + self.config.end_s), 1.0)
            ms_floor = np.maximum(at_latency, self.config.sigma_floor_mps2**2)
            weight = np.sqrt(n_eff) / ms_floor
            coef, _ = nnls(design * weight[:, None], weight * ms_floor)
            var = np.maximum(design @ coef, self.config.sigma_floor_mps2**2)
            self.noise = NoiseModel(latency, np.sqrt(var), coef, self._learn_n)
        return take.size

    def _running_sigma(self, d: FloatArray) -> FloatArray:
        """(M, W) the ``σ_L`` each scored epoch is judged with: the learned one, or the running
        one if larger.

        The running mean square (exponential, memory ``noise_memory_s``) takes each ``D_L²``
        winsorized at ``(3σ_L)²`` and is read ``noise_lag_s`` behind the epoch it judges: it
        catches noise that grows after the learning period (a manoeuvre the learning did not see),
        and a fault is judged against the noise from before it (read at once, a step's own ramp
        raised σ by a third within the 10 s it had to be found in).
        """
        assert self.noise is not None
        learned = self.noise.sigma_mps2
        a = float(np.exp(-1.0 / (self.gnss_rate_hz * self.config.noise_memory_s)))
        if self._running_state is None:
            self._running_state = a * learned**2
            lag = max(1, round(self.config.noise_lag_s * self.gnss_rate_hz))
            self._running_lagged = np.tile(learned**2, (lag, 1))
        x = np.minimum(d**2, 9.0 * learned**2)
        y, state = first_order_filter(1.0 - a, -a, x, self._running_state[None])
        self._running_state = state[0]
        lagged = np.vstack([self._running_lagged, y])
        self._running_lagged = lagged[d.shape[0] :]
        out: FloatArray = np.maximum(learned, np.sqrt(lagged[: d.shape[0]]))
        return out

    def _evaluate_ready(self) -> Evaluations:
        imu, g, cfg = self._imu, self._gnss, self.config
        if not (g.pending and imu.t_s.size):
            return Evaluations.empty(self._windows.size)
        waiting = g.t_s[g.t_s.size - g.pending :]
        known = imu.t_s[-1] if imu.resting else min(imu.t_s[-1], imu.last_loud_s)
        tk = waiting[waiting + cfg.transient_s <= known]
        if not tk.size:
            return Evaluations.empty(self._windows.size)
        g.pending -= tk.size
        code = self._exclusions(tk)
        tested = code == Exclusion.TESTED
        scored = tested.copy()
        if self.noise is None:
            learned = self._learn(tk[tested])
            scored[np.flatnonzero(tested)[:learned]] = False
        latency = np.array([0.0 if self.noise is None else self.noise.latency_s])
        d = np.full((tk.size, self._windows.size), np.nan)
        if tested.any():
            d[tested] = self._residuals(tk[tested], latency)[:, 0, :]
        z = np.full(tk.size, np.nan)
        if self.noise is not None and scored.any():
            sigma = self._running_sigma(d[scored])
            self._sigma_sums += sigma.sum(axis=0)
            self._sigma_n += sigma.shape[0]
            z[scored] = np.max(np.abs(d[scored]) / sigma, axis=1)
        alarm = np.nan_to_num(z, nan=0.0) > self.threshold
        self.exclusions += np.bincount(code, minlength=len(Exclusion))
        self.alarms += int(alarm.sum())
        if alarm.any() and self.first_alarm_t_s is None:
            self.first_alarm_t_s = float(tk[np.argmax(alarm)])
        return Evaluations(tk, d, z, code, alarm)

    def _trim(self) -> None:
        """Drop what no epoch to come can reach (the oldest waiting one, or the next, minus the span),
        and what an epoch later than ``gnss_late_s`` behind the IMU would need (it is history)."""
        imu, g = self._imu, self._gnss
        keep_from = (
            g.t_s[g.t_s.size - g.pending] if g.pending else (g.t_s[-1] if g.t_s.size else -np.inf)
        )
        keep_from -= self.config.span_s + 1.0
        if imu.t_s.size:
            # A receiver that stopped, or fell behind, does not hold the IMU's history forever.
            keep_from = max(keep_from, imu.t_s[-1] - self.config.span_s - self.config.gnss_late_s)
        _drop_before(imu, ("t_s", "f_int", "g0", "counts"), keep_from)
        _drop_before(g, ("t_s", "v_int", "gaps", "outliers"), keep_from)
        trans = imu.transitions_s
        while len(trans) > 1 and trans[1] < keep_from - self.config.transient_s:
            trans.pop(0)

    # --- what it says ---------------------------------------------------------------------

    def mdf_mps2(self, within_s: float) -> float | None:
        """``MDF(t)`` on the thrust axis, m/s² (module docstring), with the ``σ_L`` the epochs were
        judged with on average (the learned one before any); None before the noise is learned."""
        if self.noise is None:
            return None
        sigma = self._sigma_sums / self._sigma_n if self._sigma_n else self.noise.sigma_mps2
        seen = kernel_fraction(within_s - self.noise.latency_s, self.config.end_s, self._windows)
        with np.errstate(divide="ignore"):
            mdf = (self.threshold + DETECTION_QUANTILE) * sigma / seen
        return float(np.min(mdf))

    def summary(self) -> Summary:
        n = max(self._flight_samples, 1)
        share = np.sqrt(self._share_sums / n)
        return Summary(
            tested_epochs=int(self.exclusions[Exclusion.TESTED]),
            exclusions={e.name.lower(): int(self.exclusions[e]) for e in Exclusion if e},
            flight_s=float(self.exclusions[Exclusion.TESTED] / self.gnss_rate_hz),
            share=share,
            observable=share >= OBSERVABLE_SHARE,
            latency_s=None if self.noise is None else self.noise.latency_s,
            baseline_mps2=self.baseline_mps2,
            threshold=self.threshold,
            false_alarms_per_hour=self.config.false_alarms_per_hour,
            mdf_10s_mps2=self.mdf_mps2(IN_FLIGHT_WITHIN_S),
            alarms=self.alarms,
            first_alarm_t_s=self.first_alarm_t_s,
        )


def thrust_axis_batch(
    imu_t_s: FloatArray,
    accel_mps2: FloatArray,
    gyro_rps: FloatArray,
    gnss_t_s: FloatArray,
    vel_enu_mps: FloatArray,
    *,
    config: ThrustAxisConfig | None = None,
    gnss_rate_hz: float | None = None,
) -> tuple[Evaluations, ThrustAxisMonitor]:
    """A whole flight at once (replay): every epoch's evaluation and the monitor that made them.

    ``gnss_rate_hz`` defaults to the GNSS epochs' median rate.
    """
    gt = np.asarray(gnss_t_s, float)
    if gnss_rate_hz is None:
        gnss_rate_hz = 1.0 / float(np.median(np.diff(gt))) if gt.size > 1 else 1.0
    monitor = ThrustAxisMonitor(config, gnss_rate_hz=gnss_rate_hz)
    w = len(monitor.config.windows_s)
    # The receiver first: the IMU's history is then kept until every epoch is judged.
    parts = [
        monitor.update_gnss(gt, vel_enu_mps),
        monitor.update_imu(imu_t_s, accel_mps2, gyro_rps),
    ]
    return Evaluations.concatenate(parts, w), monitor


def thrust_axis_coverage(summary: Summary | None, *, reason: str = "") -> CheckCoverage:
    """The check's line in a verdict's coverage (:mod:`estimators.coverage`).

    Per axis the MDF of ``D`` in :data:`~estimators.coverage.IN_FLIGHT_WITHIN_S` over the axis's
    share: a zero signal ``MDF/rms(uᵢ)``, a scale ``MDF/(g₀·rms(uᵢ)²)`` (module docstring); an
    axis below :data:`OBSERVABLE_SHARE` is not observable (infinite). ``summary`` None: no GNSS,
    the check does not apply (``reason`` says why); nothing judged: it did not run, and the
    reason names the exclusion that took most epochs; it applies (not tested: the verdict cannot
    say "no fault") once the vehicle flew, as in a log cut in the air or a daemon restarted there.
    Epochs left out for GNSS outliers are said in the reason (the receiver's, not the unit's).
    """
    if summary is None:
        return CheckCoverage(
            Check.THRUST_AXIS, Triad.ACCEL, ran=False, applies=False, reason=reason
        )
    if summary.mdf_10s_mps2 is None or summary.baseline_mps2 is None:
        why = reason or _not_judged(summary)
        flew = bool(np.any(summary.share > 0.0))
        return CheckCoverage(Check.THRUST_AXIS, Triad.ACCEL, ran=False, applies=flew, reason=why)
    outliers = summary.exclusions.get("gnss_outlier", 0)
    if outliers:
        said = f"{outliers:,} epochs not judged: windows holding a GNSS velocity outlier"
        reason = f"{reason}; {said}" if reason else said
    share = np.where(summary.observable, summary.share, np.nan)
    bias = summary.mdf_10s_mps2 / share
    scale = summary.mdf_10s_mps2 / (summary.baseline_mps2 * share**2)
    return CheckCoverage(
        Check.THRUST_AXIS,
        Triad.ACCEL,
        ran=True,
        samples=summary.tested_epochs,
        mdf_bias_si=_triple(bias),
        mdf_scale=_triple(scale),
        false_alarm_prob=summary.false_alarms_per_hour,
        reason=reason,
    )


def _triple(v: FloatArray) -> tuple[float, float, float]:
    x = [float(a) if np.isfinite(a) else np.inf for a in v]
    return (x[0], x[1], x[2])


def _not_judged(summary: Summary) -> str:
    if summary.tested_epochs:
        return (
            f"{summary.tested_epochs} epochs of flight, fewer than the learning period's: "
            "the noise was not learned"
        )
    counted = {k: n for k, n in summary.exclusions.items() if n}
    if not counted:
        return "no GNSS epoch in flight"
    worst = max(counted, key=lambda k: counted[k])
    listed = ", ".join(f"{k.replace('_', ' ')} {n}" for k, n in counted.items())
    return f"no epoch judged ({listed}): mostly {_WHY[worst]}"


_WHY = {
    "history": "a flight shorter than the windows' span",
    "no_baseline": "no rest before the flight to set the ground baseline",
    "rest": "the vehicle at rest",
    "transient": "take-off and touch-down",
    "clipped": "a clipped accelerometer",
    "gap": "gaps in the IMU or GNSS stream",
    "gnss_outlier": "GNSS velocity outliers",
}


def _drop_before(history: Any, columns: tuple[str, ...], keep_from: float) -> None:
    """Drop a history's rows before ``keep_from`` (its ``t_s``, s), keeping at least its last two:
    the columns named, arrays of one length, are cut alike."""
    t_s = history.t_s
    k = min(int(np.searchsorted(t_s, keep_from)), t_s.size - 2)
    if k > 0:
        for name in columns:
            setattr(history, name, getattr(history, name)[k:])
