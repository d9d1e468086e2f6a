"""Gross plausibility at rest, with no gate built on the sensor under test (methods.md M1, F0 on window means).

F0 runs only on the samples the static detector calls static, and that detector's thresholds come
from the passport's (or the sensor class's) noise: a unit a little noisier than its class is never
at rest, F0 never runs and a dead accelerometer reading 0.35 g passes in silence. This test needs no
such gate: rest is told by whichever triad is quiet, against the stream's *own* noise.

Windows and the noise floor
---------------------------
The samples are cut into non-overlapping windows of ``W = max(MIN_WINDOW_SAMPLES, round(0.5 s ·
rate))`` samples (counted, not timed: whatever the rate). A window's *spread* per triad is the root
of its summed per-axis sample variances, as the static detector's
(:mod:`estimators.static_detector`). The stream's *noise floor* ``s̃`` per triad is the typical spread
of its quietest windows so far, found as :meth:`StaticDetectorConfig.from_session
<estimators.static_detector.StaticDetectorConfig.from_session>` finds it for ``calibrate``: the
windows up to ``LOW_MODE_FACTOR`` × the ``LOW_QUANTILE`` quantile of all spreads form the low mode,
and ``s̃`` is their median; streamed, the spreads are counted in a histogram of
``_BINS_PER_DECADE`` log bins (12 % wide), so the state stays small and the floor at each window is
that of the windows up to it. A window is *quiet* for a triad when its spread is at most
``SESSION_NOISE_FACTOR · s̃`` (floored at the detector's ``SPREAD_FLOOR_*``); a gyro is quiet only
below ``STILL_RATE_RPS`` as well (a gyro ringing above it is not resting, whatever its floor). The
per-axis noise of a sample, ``σ_i``, is pooled over every quiet window so far (mean of their
variances); a window mean's is ``√(σ_i²/W + w_i²)`` with ``w_i`` the passport's audited bias wander
(``bias_instability_std``, which does not average down; F0's λ0 adds it the same way), white noise
otherwise (a coloured noise makes the mean noisier than this; the tolerance dominates the bound for
every class).

Rest, per test
--------------
* **Accelerometer.** A window is at rest for it when the gyro is *still* — quiet, and each axis's
  mean within ``STILL_RATE_RPS`` of the passport's zero signal, widened by the passport's
  zero-signal band (tolerance and the Earth rate) up to another ``STILL_RATE_RPS``: a healthy gyro
  within its tolerance must not switch the accelerometer's test off (the measured Xsens unit's gyro
  rests 0.05 rad/s off 0, inside its class's 20 °/s: its accelerometer was never tested), and a
  class's wide band must not let steady turns in (at 20 °/s a flight's turns counted as rest and
  failed windows) — and the accelerometer is quiet too (against its own floor: a faulty
  accelerometer with steady noise is quiet, a knock is not).
* **Gyro.** A window is at rest for it when the accelerometer is quiet and its ``|ā|`` near g (within
  the accelerometer test's tolerance below plus ``NEAR_G_SIGMAS`` σ of the window mean), and the
  gyro is quiet. Its mean is not bounded: that is what is tested.

What this cannot tell apart: a sustained linear acceleration under a still gyro (a vehicle braking
hard in a straight line: ``|a| = g·√(1 + (a/g)²)``) and free fall read as an accelerometer off g; a
turn at a constant rate with quiet sensors (a car on a long curve, a slow steady yaw) reads as a
gyro zero signal, and a still gyro's bound lets a coordinated turn move ``|a|`` by at most
``(ωv)²/2g`` (2 % of g at 0.1 rad/s and 30 m/s). Only persistence and quietness limit these: a failure is declared after
``GROSS_PERSISTENCE_S`` of tested windows failing in a row (a window not at rest breaks the run), and
it recovers after as long passing. A window spans whatever time gap its samples do.

The tests (each on the window mean)
-----------------------------------
* ``|ā| − g`` against the tolerance the passport allows, ``[−tol_low, tol_high]`` plus
  ``z·σ_|ā|``. The tolerance is the worst case over all orientations of the passport's zero-signal,
  scale and cross-axis tolerances and of the reference's error: the least and largest
  ``s = ½(|ã|² − 1)`` a within-tolerance unit reads at rest, exactly over orientations and units
  (:func:`estimators.scalar.tolerance_extremes`, F0's tolerance terms), hence with the reference's
  relative error ``r``: ``tol_low = g(1 − √(1 + 2s_min)(1 − r))``, ``tol_high = g(√(1 + 2s_max)(1 + r)
  − 1)`` (for the MPU-6000's limits −1.74 and +1.76 m/s²). The passport's nominal errors are
  compensated first, as F0 does. ``σ_|ā|² = Σ u_i² σ_mean,i²`` with ``u`` the window's gravity
  direction.
* Each gyro axis: ``|ω̄_i − b_i| ≤ tol_b,i + Ω·r_i + z·σ_mean,i`` with ``b`` the passport's zero signal
  and ``tol_b`` its tolerance; the Earth rate's projection is unknown without a heading and enters
  as a bound, ``Ω`` times the largest gain of row ``i`` of the triad matrix within its tolerances
  (``r_i = 1 + |e_i| + tol_e,i + Σ_pairs (|δ| + tol_δ)``).

False alarms and power
----------------------
The stated ``false_alarm_prob`` is that of a *declared* failure for a healthy unit at rest at the
edge of its tolerance: ``P = persist_windows`` windows failing in a row, independent for white noise,
so each window's test is two-sided at ``p_w = false_alarm_prob^(1/P)`` and ``z = Φ⁻¹(1 − p_w/2)``
(1.53 for 1e-9 over ten windows). A fault is declared with probability 0.95 when each of the ``P``
windows fails with ``0.95^(1/P)``, i.e. when it exceeds the tolerance by ``(z + z_power)·σ_mean``
with ``z_power = Φ⁻¹(0.95^(1/P))`` (2.57 for ten windows): the minimum detectable fault.

Batch and stream
----------------
:class:`GrossMonitor` takes samples in frames of any length: a frame is held as it comes, and a
window's work (O(1), vectorized over the windows a frame completes) is done once, when it completes;
its state — the open window's sums, two histograms, pooled variances and the runs — round-trips
through :meth:`GrossMonitor.state_dict`. :func:`gross_batch` runs it over a whole session in blocks.
However the samples are cut, every window is computed from the same samples alike: the same
decisions (after a checkpoint, the open window's moments come from its sums and agree to rounding).
Coverage values for the minimum detectable fault (:class:`GrossCoverage`) come with both.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from statistics import NormalDist
from types import MappingProxyType
from typing import Any

import numpy as np

from estimators._typing import FloatArray
from estimators.conventions import AXES, EARTH_RATE_RPS, Triad
from estimators.coverage import Check, CheckCoverage, gross_mdf, tolerance_triples
from estimators.ninepar import canonical_triad_matrix
from estimators.nominal_passport import SensorClass, nominal_passport
from estimators.passport import Passport, TriadPassport
from estimators.scalar import tolerance_extremes
from estimators.session import ImuSession, validate_session
from estimators.static_detector import (
    LOW_MODE_FACTOR,
    LOW_QUANTILE,
    SESSION_NOISE_FACTOR,
    SPREAD_FLOOR_MPS2,
    SPREAD_FLOOR_RPS,
)

GROSS_STATE_VERSION = 1
GROSS_WINDOW_S = 0.5
"""Window length at the stream's rate, s (the static detector's)."""
MIN_WINDOW_SAMPLES = 8
"""Fewest samples in a window: below it a spread has too few degrees of freedom to tell rest."""
GROSS_PERSISTENCE_S = 5.0
"""Failing tested windows in a row, in time, before a failure is declared (and passing, before it recovers)."""
STILL_RATE_RPS = 0.05
"""A still gyro: each axis's window mean within this of the passport's zero signal plus its zero-signal
band (tolerance and the Earth rate) up to this much again, spread within it too (module docstring).
0.05 rad/s lets a coordinated turn move |a| by at most 0.5 % of g at 30 m/s, 0.1 rad/s by 2 %."""
NEAR_G_SIGMAS = 6.0
"""Rest for the gyro test: the accelerometer's ``|ā| − g`` within its tolerance plus this many σ of the
window mean (a linear acceleration or a turn moves it further). Not the accelerometer's own
per-window test: at ``z`` ≈ 1.5 it fails one window in eight of a unit at its tolerance's edge, and
each such window would break the gyro's run of failing windows, hiding a gyro fault (found on a
passport whose tolerances lie below the noise: 39 of 100 gyro faults at 1.5× the MDF declared)."""
AXIS_NAMED_COS = 0.9
"""An accelerometer failure names the axis whose |u_i| (gravity direction) is at least this at its onset:
at rest along one axis, |a| moves with that axis's zero signal and scale only."""
NOMINAL_CLASS = SensorClass.CONSUMER_MEMS
"""Tolerances used without a passport (or for a triad the passport lacks)."""
BLOCK_WINDOWS = 1024
"""Windows per block of :func:`gross_batch` (bounded memory on any session length)."""

_LOG_MIN = -8.0
_BINS_PER_DECADE = 16
_N_BINS = 11 * _BINS_PER_DECADE
_LOW_MODE_BINS = math.floor(_BINS_PER_DECADE * math.log10(LOW_MODE_FACTOR))
_ACC, _GYR = slice(0, 3), slice(3, 6)
_SPREAD_FLOORS = np.array([[SPREAD_FLOOR_MPS2], [SPREAD_FLOOR_RPS]])
_TESTS = (Triad.ACCEL, Triad.GYRO, Triad.GYRO, Triad.GYRO)
_TEST_AXIS: tuple[int | None, ...] = (None, 0, 1, 2)


@dataclass(frozen=True)
class GrossConfig:
    """What the gross test needs, derived once from a passport and the rate (:func:`gross_config`).

    Attributes
    ----------
    window_samples : W, samples per window.
    persist_windows : tested windows failing (passing) in a row that declare (clear) a failure.
    gravity_mps2 : local gravity, m/s².
    accel_map : (3, 3) ``A⁻¹`` of the passport's nominal accelerometer matrix.
    accel_offset : (3,) ``A⁻¹ b`` of its nominal zero signals (normalized by g).
    accel_tol_low_mps2, accel_tol_high_mps2 : allowed ``g − |a|`` and ``|a| − g`` at rest, without noise.
    gyro_zero_rps : (3,) the passport's nominal gyro zero signals, rad/s.
    gyro_tol_rps : (3,) allowed ``|ω̄_i − b_i|`` at rest without noise (tolerance + Earth rate).
    false_alarm_prob : of a declared failure (module docstring, False alarms and power).
    z : per window, ``Φ⁻¹(1 − p_w/2)`` with ``p_w = false_alarm_prob^(1/persist_windows)``.
    z_power : per window, ``Φ⁻¹(0.95^(1/persist_windows))``: the margin over the bound, in σ, that
        declares a fault with probability 0.95.
    accel_wander_mps2, gyro_wander_rps : (3,) the passport's bias wander per axis, SI.
    source : whose tolerances (``"passport <unit_id>"`` or ``"nominal consumer_mems"``, per triad).
    """

    window_samples: int
    persist_windows: int
    gravity_mps2: float
    accel_map: FloatArray
    accel_offset: FloatArray
    accel_tol_low_mps2: float
    accel_tol_high_mps2: float
    gyro_zero_rps: FloatArray
    gyro_tol_rps: FloatArray
    false_alarm_prob: float
    z: float
    z_power: float
    accel_wander_mps2: FloatArray
    gyro_wander_rps: FloatArray
    source: str


def _accel_tolerance(
    tp: TriadPassport, gravity_mps2: float, gravity_rel_err: float
) -> tuple[float, float]:
    """``(tol_low, tol_high)``: how far below and above g ``|ã|`` of a within-tolerance unit at rest
    reads, m/s² (module docstring): the exact least and largest ``s`` over orientations and units
    (:func:`estimators.scalar.tolerance_extremes`, asymmetric: a unit's zero signals and gains lift
    ``|ã|`` further than they lower it), widened by the reference's relative error."""
    tol = tp.tolerance.copy()
    tol[:3] *= tp.reference / gravity_mps2
    s_min, s_max = tolerance_extremes(tol)
    low = 1.0 - math.sqrt(max(0.0, 1.0 + 2.0 * s_min)) * (1.0 - gravity_rel_err)
    high = math.sqrt(1.0 + 2.0 * s_max) * (1.0 + gravity_rel_err) - 1.0
    return gravity_mps2 * low, gravity_mps2 * high


def _gyro_row_gain(tp: TriadPassport) -> FloatArray:
    """(3,) ``r_i``, the largest gain of row ``i`` of the gyro's triad matrix within tolerance."""
    span = np.abs(tp.nominal) + tp.tolerance
    pairs = ((0, 1), (0, 2), (1, 2))  # d1 xy, d2 xz, d3 yz (conventions.PARAM_AXIS)
    cross = np.zeros(3)
    for k, (i, j) in enumerate(pairs):
        cross[i] += span[6 + k]
        cross[j] += span[6 + k]
    gain: FloatArray = 1.0 + span[3:6] + cross
    return gain


def tolerance_passports(
    passport: Passport | None, *, gravity_mps2: float
) -> tuple[dict[Triad, TriadPassport], dict[Triad, str]]:
    """Per triad, the passport whose tolerances the gross test uses and whose they are: the unit's,
    or for a triad it lacks (or no passport) the nominal passport of :data:`NOMINAL_CLASS`."""
    nominal = nominal_passport(NOMINAL_CLASS, gravity_mps2=gravity_mps2)
    tps: dict[Triad, TriadPassport] = {}
    source: dict[Triad, str] = {}
    for triad in (Triad.ACCEL, Triad.GYRO):
        if passport is not None and triad in passport.triads:
            tps[triad], source[triad] = passport.triads[triad], f"passport {passport.unit_id}"
        else:
            tps[triad], source[triad] = nominal.triads[triad], f"nominal {NOMINAL_CLASS.value}"
    return tps, source


def gross_config(
    passport: Passport | None,
    *,
    rate_hz: float,
    gravity_mps2: float,
    gravity_rel_err: float,
    false_alarm_prob: float,
    persistence_s: float = GROSS_PERSISTENCE_S,
) -> GrossConfig:
    """The gross test's configuration for a unit at a rate (module docstring).

    Parameters
    ----------
    passport : the unit's passport; None (or a triad it lacks): the nominal passport of
        :data:`NOMINAL_CLASS` (:func:`estimators.nominal_passport.nominal_passport`).
    rate_hz : the stream's sample rate, Hz (sets W).
    gravity_mps2 : local gravity, m/s²; gravity_rel_err its relative error bound.
    false_alarm_prob : of a declared failure, in (0, 1).
    persistence_s : time of failing windows in a row that declares a failure, s.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"rate_hz must be finite and > 0, got {rate_hz!r}")
    if not (0.0 < false_alarm_prob < 1.0):
        raise ValueError(f"false_alarm_prob must be in (0, 1), got {false_alarm_prob!r}")
    if not (math.isfinite(persistence_s) and persistence_s >= 0.0):
        raise ValueError(f"persistence_s must be finite and >= 0, got {persistence_s!r}")
    w = max(MIN_WINDOW_SAMPLES, round(GROSS_WINDOW_S * rate_hz))
    tps, source = tolerance_passports(passport, gravity_mps2=gravity_mps2)
    ta, tg = tps[Triad.ACCEL], tps[Triad.GYRO]
    acc_nom = ta.nominal.copy()
    acc_nom[:3] *= ta.reference / gravity_mps2
    a_inv = np.asarray(
        np.linalg.solve(canonical_triad_matrix(acc_nom), np.eye(3)), dtype=np.float64
    )
    tol_low, tol_high = _accel_tolerance(ta, gravity_mps2, gravity_rel_err)
    gyro_zero = tg.nominal[:3] * tg.reference
    gyro_tol = tg.tolerance[:3] * tg.reference + EARTH_RATE_RPS * _gyro_row_gain(tg)
    names = (
        source[Triad.ACCEL]
        if source[Triad.ACCEL] == source[Triad.GYRO]
        else ", ".join(f"{k.value}: {v}" for k, v in source.items())
    )
    persist = max(1, math.ceil(persistence_s * rate_hz / w - 1e-9))
    p_window = false_alarm_prob ** (1.0 / persist)
    return GrossConfig(
        window_samples=int(w),
        persist_windows=persist,
        gravity_mps2=float(gravity_mps2),
        accel_map=a_inv,
        accel_offset=a_inv @ acc_nom[:3],
        accel_tol_low_mps2=tol_low,
        accel_tol_high_mps2=tol_high,
        gyro_zero_rps=np.asarray(gyro_zero, dtype=float),
        gyro_tol_rps=np.asarray(gyro_tol, dtype=float),
        false_alarm_prob=float(false_alarm_prob),
        z=NormalDist().inv_cdf(1.0 - 0.5 * p_window),
        z_power=NormalDist().inv_cdf(0.95 ** (1.0 / persist)),
        accel_wander_mps2=ta.bias_instability_std * ta.reference,
        gyro_wander_rps=tg.bias_instability_std * tg.reference,
        source=names,
    )


@dataclass(frozen=True)
class GrossChange:
    """A gross failure declared (``raised``) or cleared, in SI.

    Attributes
    ----------
    triad, axis : the triad; the axis (``"x"``…) when the geometry names it, else None.
    raised : True when declared, False when it recovered.
    t_s : declared: first sample of the run's first failing window; cleared: of its first passing window.
    value_si : accelerometer ``|ā| − g`` (m/s²); gyro ``ω̄_i`` (rad/s) — of that window.
    nominal_si : 0 (accelerometer), the passport zero signal ``b_i`` (gyro).
    bound_si : the bound crossed on that side, noise term included.
    sigma_si : the window mean's standard deviation used.
    duration_s : span of the run that declared or cleared it (first to last sample).
    """

    triad: Triad
    axis: str | None
    raised: bool
    t_s: float
    value_si: float
    nominal_si: float
    bound_si: float
    sigma_si: float
    duration_s: float


@dataclass(frozen=True)
class GrossCoverage:
    """What the gross test of one triad tested, for the minimum detectable fault (estimators.coverage).

    Attributes
    ----------
    triad : the triad.
    windows : windows of W samples tested (at rest for this triad's test).
    fail_windows : of those, windows outside the bound.
    window_samples : W.
    max_abs_u : (3,) largest ``|u_i|`` of the gravity direction over the tested windows (accelerometer;
        0 where an axis never saw gravity); None for the gyro (each axis tested directly).
    sigma_mean_si : (3,) per-axis standard deviation of a window mean (the stream's pooled quiet
        noise / √W with the passport's bias wander), SI; NaN before any quiet window.
    tolerance_si : (3,) allowed deviation without noise per axis: the accelerometer's ``|a| − g``
        tolerance on its wider side (the same for all three), the gyro's ``tol_b,i + Ω·r_i``.
    persist_windows : P, failing windows in a row that declare a failure.
    false_alarm_prob : of a declared failure; z, z_power : per window (:class:`GrossConfig`). The
        minimum detectable deviation of the tested statistic is ``tolerance + (z + z_power)·σ_mean``.
    source : whose tolerances.
    """

    triad: Triad
    windows: int
    fail_windows: int
    window_samples: int
    max_abs_u: tuple[float, float, float] | None
    sigma_mean_si: tuple[float, float, float]
    tolerance_si: tuple[float, float, float]
    persist_windows: int
    false_alarm_prob: float
    z: float
    z_power: float
    source: str

    @property
    def window_false_alarm_prob(self) -> float:
        """Per window, two-sided: ``false_alarm_prob^(1/persist_windows)`` (``z``'s probability)."""
        return float(self.false_alarm_prob ** (1.0 / self.persist_windows))

    @property
    def window_power(self) -> float:
        """Per window: ``0.95^(1/persist_windows)`` (``z_power``'s), so that the run is found with 0.95."""
        return float(0.95 ** (1.0 / self.persist_windows))

    def check(self, tp: TriadPassport, *, gravity_mps2: float, total_windows: int) -> CheckCoverage:
        """This triad's gross test as a verdict's coverage (:mod:`estimators.coverage`): windows tested
        and the minimum detectable zero signal (both triads) and scale error (the accelerometer: a
        gyro at rest turns at no rate a scale error could multiply) against ``tp``'s tolerances (the
        passport whose tolerances the test used, :func:`tolerance_passports`); ``total_windows``:
        the windows the stream completed, for why none was at rest."""
        tolerance_bias_si, tol_scale = tolerance_triples(tp.tolerance, tp.reference)
        if self.windows == 0:
            other = (
                "the gyro was never still with the accelerometer quiet"
                if self.triad is Triad.ACCEL
                else "the accelerometer was never quiet near g with the gyro quiet"
            )
            return CheckCoverage(
                Check.GROSS, self.triad, ran=False, tolerance_bias_si=tolerance_bias_si,
                reason=f"no rest in {total_windows} window(s) of {self.window_samples} samples: {other}",
            )  # fmt: skip
        per_window = {
            "false_alarm_prob": self.window_false_alarm_prob,
            "power": self.window_power,
        }
        if self.triad is Triad.ACCEL:
            assert self.max_abs_u is not None
            bias, scale = gross_mdf(
                tolerance_si=self.tolerance_si[0], sigma_mean_si=max(self.sigma_mean_si),
                max_abs_u=self.max_abs_u, reference=gravity_mps2, **per_window,
            )  # fmt: skip
            tolerance_scale: tuple[float, float, float] | None = tol_scale
            mdf_scale: tuple[float, float, float] | None = scale
        else:
            # Each gyro axis is tested on its own mean: its direction factor is 1.
            bias = _triple(
                np.array([
                    gross_mdf(
                        tolerance_si=tol, sigma_mean_si=sig, max_abs_u=(1.0, 1.0, 1.0),
                        reference=1.0, **per_window,
                    )[0][0]
                    for tol, sig in zip(self.tolerance_si, self.sigma_mean_si, strict=True)
                ])
            )  # fmt: skip
            tolerance_scale = mdf_scale = None
        return CheckCoverage(
            Check.GROSS, self.triad, ran=True, samples=self.windows, mdf_bias_si=bias,
            mdf_scale=mdf_scale, tolerance_bias_si=tolerance_bias_si,
            tolerance_scale=tolerance_scale, false_alarm_prob=self.false_alarm_prob,
        )  # fmt: skip


@dataclass(frozen=True)
class GrossUpdate:
    """What one :meth:`GrossMonitor.update` did: windows completed, tested and failed per triad, changes."""

    windows: int
    tested: Mapping[Triad, int]
    failed: Mapping[Triad, int]
    changes: tuple[GrossChange, ...]


_NONE = MappingProxyType({Triad.ACCEL: 0, Triad.GYRO: 0})
_NO_WINDOWS = GrossUpdate(0, _NONE, _NONE, ())
"""What a frame that completes no window did (shared: most frames)."""


class _Run:
    """Persistence of one test (module docstring): runs of failing and passing tested windows."""

    __slots__ = ("fail_run", "failing", "onset", "pass_run", "recovery")

    def __init__(self) -> None:
        self.fail_run = 0
        self.pass_run = 0
        self.failing = False
        # (t_s, value, bound, sigma, axis) of the run's first window; axis -1: not named.
        self.onset: tuple[float, float, float, float, int] | None = None
        self.recovery: tuple[float, float, float, float, int] | None = None

    def state(self) -> dict[str, Any]:
        return {
            "fail_run": self.fail_run,
            "pass_run": self.pass_run,
            "failing": self.failing,
            "onset": None if self.onset is None else list(self.onset),
            "recovery": None if self.recovery is None else list(self.recovery),
        }

    @classmethod
    def load(cls, s: dict[str, Any]) -> _Run:
        run = cls()
        run.fail_run, run.pass_run = int(s["fail_run"]), int(s["pass_run"])
        run.failing = bool(s["failing"])
        for name in ("onset", "recovery"):
            v = s[name]
            if v is not None:
                t, val, b, sg, ax = v
                setattr(run, name, (float(t), float(val), float(b), float(sg), int(ax)))
        if run.fail_run < 0 or run.pass_run < 0:
            raise ValueError("negative run length")
        return run


def _triple(x: FloatArray) -> tuple[float, float, float]:
    return float(x[0]), float(x[1]), float(x[2])


def _spread_bins(spread: FloatArray) -> FloatArray:
    """The histogram bin of each spread (≥ 0; a zero spread, noise-free data, in the lowest)."""
    idx = np.floor((np.log10(np.maximum(spread, 1e-300)) - _LOG_MIN) * _BINS_PER_DECADE)
    bins: FloatArray = np.clip(idx, 0, _N_BINS - 1)
    return bins


def _floors(hist: FloatArray, spread: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per triad (2) and window (K): the typical quiet spread after counting the window's ``spread``
    (2, K) into the histograms ``hist`` (2, bins) (module docstring); and the histograms after all."""
    k = spread.shape[1]
    onehot = np.zeros((2, k, _N_BINS))
    onehot[np.arange(2)[:, None], np.arange(k), _spread_bins(spread).astype(np.intp)] = 1.0
    counts = hist[:, None, :] + np.cumsum(onehot, axis=1)
    cum = np.cumsum(counts, axis=2)
    iq = np.argmax(cum >= LOW_QUANTILE * cum[..., -1:], axis=2)
    lim = np.minimum(iq + _LOW_MODE_BINS, _N_BINS - 1)
    low = np.take_along_axis(cum, lim[..., None], axis=2)
    imed = np.argmax(cum >= 0.5 * low, axis=2)
    typical = 10.0 ** (_LOG_MIN + (imed + 0.5) / _BINS_PER_DECADE)
    return typical, counts[:, -1]


class GrossMonitor:
    """The gross test on a stream (module docstring): :meth:`update` per frame, small state.

    ``update(t_s, accel_mps2, gyro_rps)`` takes (N,) times and (N, 3) finite samples in SI (the
    caller rejects non-finite ones), in time order.
    """

    def __init__(self, config: GrossConfig) -> None:
        self.config = config
        # The open window: frames held as they came (no work per frame), and sums only where a
        # checkpoint folded them (state_dict), so the state stays a few numbers.
        self._held: list[tuple[FloatArray, FloatArray]] = []
        self._held_n = 0
        self._n = 0
        self._t0 = math.nan
        self._shift = np.zeros(6)
        self._s1 = np.zeros(6)
        self._s2 = np.zeros(6)
        self._hist = np.zeros((2, _N_BINS))
        self._var_sum = np.zeros(6)
        self._var_n = np.zeros(2)
        self._runs = [_Run() for _ in _TESTS]
        self.windows = 0
        self.tested = {Triad.ACCEL: 0, Triad.GYRO: 0}
        self.failed = {Triad.ACCEL: 0, Triad.GYRO: 0}
        self._max_abs_u = np.zeros(3)

    # ------------------------------------------------------------------ windows

    def _add_partial(self, t_s: FloatArray, x: FloatArray) -> None:
        if not x.shape[0]:
            return
        if self._n == 0:
            self._shift = x[0].copy()
            self._t0 = float(t_s[0])
        d = x - self._shift
        self._s1 += d.sum(axis=0)
        d *= d
        self._s2 += d.sum(axis=0)
        self._n += x.shape[0]

    def _windows(
        self, t_s: FloatArray, x: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Means (K, 6), sample variances (K, 6), first and last sample times (K,) of the windows
        completed by the held frames and ``x`` (at least one); the rest is held."""
        w = self.config.window_samples
        if self._held:
            t_s = np.concatenate([*(h[0] for h in self._held), t_s])
            x = np.concatenate([*(h[1] for h in self._held), x])
            self._held, self._held_n = [], 0
        parts_m, parts_v, parts_t0, parts_t1 = [], [], [], []
        start = 0
        if self._n:  # sums a checkpoint folded: the first window completes them
            start = w - self._n
            self._add_partial(t_s[:start], x[:start])
            s1, s2 = self._s1, self._s2
            parts_m.append((self._shift + s1 / w)[None, :])
            parts_v.append(np.maximum((s2 - s1 * s1 / w) / (w - 1), 0.0)[None, :])
            parts_t0.append(np.array([self._t0]))
            parts_t1.append(t_s[start - 1 : start])
            self._n, self._s1, self._s2 = 0, np.zeros(6), np.zeros(6)
        k = (x.shape[0] - start) // w
        if k:
            blocks = x[start : start + k * w].reshape(k, w, 6)
            tb = t_s[start : start + k * w].reshape(k, w)
            parts_m.append(blocks.mean(axis=1))
            parts_v.append(blocks.var(axis=1, ddof=1))
            parts_t0.append(tb[:, 0])
            parts_t1.append(tb[:, -1])
        end = start + k * w
        if end < x.shape[0]:
            self._held, self._held_n = [(t_s[end:], x[end:])], x.shape[0] - end
        cat = np.concatenate
        return cat(parts_m), cat(parts_v), cat(parts_t0), cat(parts_t1)

    # ------------------------------------------------------------------ the tests

    def update(self, t_s: FloatArray, accel_mps2: FloatArray, gyro_rps: FloatArray) -> GrossUpdate:
        t = np.array(t_s, dtype=float)  # a copy: frames are held until their window completes
        a, g = np.asarray(accel_mps2, dtype=float), np.asarray(gyro_rps, dtype=float)
        if t.ndim != 1 or a.shape != (t.size, 3) or g.shape != a.shape:
            raise ValueError(
                f"accel_mps2 and gyro_rps must be (N, 3) with t_s (N,), got {a.shape}, {g.shape} and {t.shape}"
            )
        x = np.concatenate((a, g), axis=1)
        if self._n + self._held_n + t.size < self.config.window_samples:
            # The usual small frame: held (a window's work is done once, when it completes).
            if t.size:
                self._held.append((t, x))
                self._held_n += t.size
            return _NO_WINDOWS
        means, var, t_first, t_last = self._windows(t, x)
        k = means.shape[0]
        cfg = self.config
        w = cfg.window_samples
        spread = np.sqrt(np.stack([var[:, _ACC].sum(axis=1), var[:, _GYR].sum(axis=1)]))
        typical, self._hist = _floors(self._hist, spread)
        quiet_a, quiet_g = spread <= np.maximum(SESSION_NOISE_FACTOR * typical, _SPREAD_FLOORS)
        quiet_g &= spread[1] <= STILL_RATE_RPS
        # Per-axis noise pooled over the quiet windows up to each window.
        sig = np.empty((k, 6))
        for j, (q, sl) in enumerate(((quiet_a, _ACC), (quiet_g, _GYR))):
            n_q = self._var_n[j] + np.cumsum(q)
            # Added window by window onto the sum so far, as one window at a time would: the same
            # bits however the stream is cut into batches.
            v_q = np.cumsum(np.vstack([self._var_sum[sl], var[:, sl] * q[:, None]]), axis=0)[1:]
            wander = cfg.accel_wander_mps2 if j == 0 else cfg.gyro_wander_rps
            # Before any quiet window (n_q = 0) the window is not quiet either: its σ is not used.
            sig[:, sl] = np.sqrt(v_q / np.maximum(n_q, 1.0)[:, None] / w + wander**2)
            self._var_n[j], self._var_sum[sl] = n_q[-1], v_q[-1]

        a_c = cfg.gravity_mps2 * (
            (means[:, _ACC] / cfg.gravity_mps2) @ cfg.accel_map.T - cfg.accel_offset
        )
        mag = np.linalg.norm(a_c, axis=1)
        u = a_c / np.maximum(mag, 1e-12)[:, None]
        dev = mag - cfg.gravity_mps2
        sig_a = np.sqrt(np.einsum("ij,ij->i", u * u, sig[:, _ACC] ** 2))
        hi = cfg.accel_tol_high_mps2 + cfg.z * sig_a
        lo = cfg.accel_tol_low_mps2 + cfg.z * sig_a
        rate = means[:, _GYR]
        err = rate - cfg.gyro_zero_rps
        still = quiet_g & np.all(
            np.abs(err) <= STILL_RATE_RPS + np.minimum(cfg.gyro_tol_rps, STILL_RATE_RPS), axis=1
        )
        rest_a = quiet_a & still
        near_g = (dev <= hi) & (dev >= -lo)
        fail_a = rest_a & ~near_g
        margin = NEAR_G_SIGMAS * sig_a
        rest_g = (
            quiet_a
            & (dev <= cfg.accel_tol_high_mps2 + margin)
            & (dev >= -cfg.accel_tol_low_mps2 - margin)
            & quiet_g
        )
        bound_g = cfg.gyro_tol_rps + cfg.z * sig[:, _GYR]
        fail_g = rest_g[:, None] & (np.abs(err) > bound_g)

        if rest_a.any():
            self._max_abs_u = np.maximum(self._max_abs_u, np.abs(u[rest_a]).max(axis=0))
        tested = {Triad.ACCEL: int(rest_a.sum()), Triad.GYRO: int(rest_g.sum())}
        failed = {Triad.ACCEL: int(fail_a.sum()), Triad.GYRO: int(fail_g.any(axis=1).sum())}
        self.windows += k
        for tr in tested:
            self.tested[tr] += tested[tr]
            self.failed[tr] += failed[tr]

        # The four tests (accelerometer, gyro x y z) as rows: tested, failed, and what a change reports.
        rest = np.vstack([rest_a, rest_g, rest_g, rest_g])
        fail = np.vstack([fail_a, fail_g.T])
        values = np.vstack([dev, rate.T])
        bounds = np.vstack([np.where(dev >= 0.0, hi, lo), bound_g.T])
        sigmas = np.vstack([sig_a, sig[:, _GYR].T])
        named = np.where(np.abs(u).max(axis=1) >= AXIS_NAMED_COS, np.abs(u).argmax(axis=1), -1)
        changes: list[GrossChange] = []
        for i, run in enumerate(self._runs):
            if not rest[i].any() and run.fail_run == 0 and run.pass_run == 0:
                continue  # a moving unit's windows: nothing to carry
            ax = _TEST_AXIS[i]

            def at(
                j: int, i: int = i, ax: int | None = ax
            ) -> tuple[float, float, float, float, int]:
                axis = int(named[j]) if ax is None else ax
                return (
                    float(t_first[j]),
                    float(values[i, j]),
                    float(bounds[i, j]),
                    float(sigmas[i, j]),
                    axis,
                )

            changes += self._persist(i, run, rest[i].tolist(), fail[i].tolist(), at, t_last)
        return GrossUpdate(k, tested, failed, tuple(changes))

    def _persist(
        self,
        i: int,
        run: _Run,
        rest: list[bool],
        fail: list[bool],
        at: Callable[[int], tuple[float, float, float, float, int]],
        t_last: FloatArray,
    ) -> list[GrossChange]:
        """Runs over the K windows of one test (O(1) per window); the changes they make. ``at(j)``:
        what window ``j`` reports (first time, value, bound, sigma, axis or −1)."""
        p = self.config.persist_windows
        out: list[GrossChange] = []
        for j, (tested, failed) in enumerate(zip(rest, fail, strict=True)):
            if not tested:
                run.fail_run = run.pass_run = 0
            elif failed:
                run.pass_run = 0
                if run.fail_run == 0:
                    run.onset = at(j)
                run.fail_run += 1
                if run.fail_run == p and not run.failing and run.onset is not None:
                    run.failing = True
                    out.append(self._change(i, True, run.onset, float(t_last[j])))
            else:
                run.fail_run = 0
                if run.pass_run == 0:
                    run.recovery = at(j)
                run.pass_run += 1
                if run.pass_run == p and run.failing and run.recovery is not None:
                    run.failing = False
                    out.append(self._change(i, False, run.recovery, float(t_last[j])))
        return out

    def _change(
        self, i: int, raised: bool, at: tuple[float, float, float, float, int], t_end_s: float
    ) -> GrossChange:
        t_s, value, bound, sigma, axis = at
        triad = _TESTS[i]
        nominal = 0.0 if triad is Triad.ACCEL else float(self.config.gyro_zero_rps[axis])
        return GrossChange(
            triad=triad,
            axis=None if axis < 0 else AXES[axis],
            raised=raised,
            t_s=t_s,
            value_si=value,
            nominal_si=nominal,
            bound_si=bound,
            sigma_si=sigma,
            duration_s=t_end_s - t_s,
        )

    # ------------------------------------------------------------------ reading it

    def failing(self) -> list[tuple[Triad, str | None]]:
        """The tests whose failure is declared now: (triad, axis) — axis None for the accelerometer."""
        return [
            (_TESTS[i], None if (ax := _TEST_AXIS[i]) is None else AXES[ax])
            for i, run in enumerate(self._runs)
            if run.failing
        ]

    def sample_noise_si(self, triad: Triad) -> FloatArray | None:
        """(3,) per-sample noise of ``triad`` per axis, SI, pooled over its quiet windows so far (module
        docstring): the noise the stream itself shows; None before its first quiet window."""
        j = 0 if Triad(triad) is Triad.ACCEL else 1
        if self._var_n[j] == 0:
            return None
        sl = _ACC if j == 0 else _GYR
        noise: FloatArray = np.sqrt(self._var_sum[sl] / self._var_n[j])
        return noise

    def coverage(self) -> dict[Triad, GrossCoverage]:
        cfg = self.config
        w = cfg.window_samples
        out = {}
        for j, triad in enumerate((Triad.ACCEL, Triad.GYRO)):
            sl = _ACC if j == 0 else _GYR
            wander = cfg.accel_wander_mps2 if j == 0 else cfg.gyro_wander_rps
            with np.errstate(invalid="ignore", divide="ignore"):
                sig = np.sqrt(self._var_sum[sl] / self._var_n[j] / w + wander**2)
            tol = (
                np.full(3, max(cfg.accel_tol_low_mps2, cfg.accel_tol_high_mps2))
                if triad is Triad.ACCEL
                else cfg.gyro_tol_rps
            )
            out[triad] = GrossCoverage(
                triad=triad,
                windows=self.tested[triad],
                fail_windows=self.failed[triad],
                window_samples=w,
                max_abs_u=_triple(self._max_abs_u) if j == 0 else None,
                sigma_mean_si=_triple(sig),
                tolerance_si=_triple(tol),
                persist_windows=cfg.persist_windows,
                false_alarm_prob=cfg.false_alarm_prob,
                z=cfg.z,
                z_power=cfg.z_power,
                source=cfg.source,
            )
        return out

    def restart(self) -> None:
        """The source restarted: the open window is dropped (it would join two streams); the rest stays."""
        self._n, self._s1, self._s2 = 0, np.zeros(6), np.zeros(6)
        self._held, self._held_n = [], 0

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict[str, Any]:
        """Plain, versioned state (the config is rebuilt from the passport and the rate, not saved);
        the held frames of the open window are folded into its sums first."""
        for t_s, x in self._held:
            self._add_partial(t_s, x)
        self._held, self._held_n = [], 0
        return {
            "version": GROSS_STATE_VERSION,
            "window_samples": self.config.window_samples,
            "n": self._n,
            "t0": None if math.isnan(self._t0) else self._t0,
            "shift": self._shift.tolist(),
            "s1": self._s1.tolist(),
            "s2": self._s2.tolist(),
            "hist": self._hist.astype(np.int64).tolist(),
            "var_sum": self._var_sum.tolist(),
            "var_n": self._var_n.astype(np.int64).tolist(),
            "runs": [r.state() for r in self._runs],
            "windows": self.windows,
            "tested": [self.tested[Triad.ACCEL], self.tested[Triad.GYRO]],
            "failed": [self.failed[Triad.ACCEL], self.failed[Triad.GYRO]],
            "max_abs_u": self._max_abs_u.tolist(),
        }

    @classmethod
    def from_state(cls, config: GrossConfig, state: dict[str, Any]) -> GrossMonitor:
        """Resume from :meth:`state_dict`; ``ValueError`` for another version or values it never holds.

        A state saved at another window length (the stream's rate changed) keeps its runs, counts
        and coverage and starts the windows and the noise floor afresh.
        """
        if not isinstance(state, dict) or state.get("version") != GROSS_STATE_VERSION:
            raise ValueError(f"gross state is not version {GROSS_STATE_VERSION}")
        mon = cls(config)
        try:
            mon._runs = [_Run.load(s) for s in state["runs"]]
            mon.windows = int(state["windows"])
            ta, tg = (int(v) for v in state["tested"])
            fa, fg = (int(v) for v in state["failed"])
            mon.tested = {Triad.ACCEL: ta, Triad.GYRO: tg}
            mon.failed = {Triad.ACCEL: fa, Triad.GYRO: fg}
            mon._max_abs_u = np.asarray(state["max_abs_u"], dtype=float).reshape(3)
            if int(state["window_samples"]) == config.window_samples:
                mon._n = int(state["n"])
                mon._t0 = math.nan if state["t0"] is None else float(state["t0"])
                for name in ("shift", "s1", "s2", "var_sum"):
                    setattr(mon, f"_{name}", np.asarray(state[name], dtype=float).reshape(6))
                mon._hist = np.asarray(state["hist"], dtype=float).reshape(2, _N_BINS)
                mon._var_n = np.asarray(state["var_n"], dtype=float).reshape(2)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"invalid gross state: {exc}") from None
        if len(mon._runs) != len(_TESTS) or not 0 <= mon._n < config.window_samples:
            raise ValueError("invalid gross state: runs or open window out of range")
        arrays = (mon._shift, mon._s1, mon._s2, mon._var_sum, mon._hist, mon._var_n, mon._max_abs_u)
        if not all(np.all(np.isfinite(a)) for a in arrays) or np.any(mon._hist < 0):
            raise ValueError("invalid gross state: non-finite or negative values")
        return mon


@dataclass(frozen=True)
class GrossResult:
    """:func:`gross_batch`'s answer: the changes in time order, coverage per triad, the config used, rejections."""

    changes: list[GrossChange]
    coverage: dict[Triad, GrossCoverage]
    config: GrossConfig
    windows: int
    rejected: dict[str, int]


def gross_batch(
    session: ImuSession,
    passport: Passport | None,
    *,
    gravity_mps2: float,
    gravity_rel_err: float = 3.0e-3,
    false_alarm_prob: float = 1.0e-9,
    persistence_s: float = GROSS_PERSISTENCE_S,
) -> GrossResult:
    """The gross test over a whole session (module docstring), for the offline chain.

    The session is validated first (:func:`estimators.session.validate_session`: non-finite samples
    and repeated time stamps are left out and counted in ``rejected``). A session without gyros is
    tested on the accelerometer alone: rest is then its own quietness, and no gyro test runs (its
    coverage says 0 windows). ``gravity_rel_err`` and ``false_alarm_prob`` as the pipeline's options.
    """
    clean, rejected = validate_session(session)
    if clean.accel_mps2 is None:
        raise ValueError("gross_batch needs the accelerometer triad")
    cfg = gross_config(
        passport,
        rate_hz=clean.rate_hz,
        gravity_mps2=gravity_mps2,
        gravity_rel_err=gravity_rel_err,
        false_alarm_prob=false_alarm_prob,
        persistence_s=persistence_s,
    )
    # Without gyros a resting gyro at its zero signal stands in; its own test is dropped below.
    gyro = (
        clean.gyro_rps
        if clean.gyro_rps is not None
        else np.broadcast_to(cfg.gyro_zero_rps, clean.accel_mps2.shape)
    )
    mon = GrossMonitor(cfg)
    step = BLOCK_WINDOWS * cfg.window_samples
    changes: list[GrossChange] = []
    for s in range(0, clean.n_samples, step):
        sl = slice(s, s + step)
        changes += mon.update(clean.t_s[sl], clean.accel_mps2[sl], gyro[sl]).changes
    coverage = mon.coverage()
    if clean.gyro_rps is None:
        changes = [c for c in changes if c.triad is Triad.ACCEL]
        coverage[Triad.GYRO] = replace(
            coverage[Triad.GYRO], windows=0, fail_windows=0, sigma_mean_si=(math.nan,) * 3
        )
    return GrossResult(changes, coverage, cfg, mon.windows, dict(rejected.counts))
