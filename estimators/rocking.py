"""Gyro scale-factor errors from attitude drift under synchronous rocking (methods.md M5).

Bogdanov & Savelyev rock the unit about two axes at the same angular frequency
``ν`` with a ±π/2 phase difference. A scale-factor error ``δK_i = ΔK_i/K_i`` of
gyro channel ``i`` then makes the *third* computed angle drift at a constant
rate. With the static drift (additive errors) removed::

    X_k = 2 (Ḋ_k − Ḋ_k0) / (A_i · A_j · ν · sin Δφ)          (M5 eq. 4)
    X_k = δK_i + δK_j − δK_k                                    (M5 eqs. 1–3, first order)
    δK_k = (X_i + X_j) / 2 = (ΣX − X_k) / 2                    (M5 eq. 5)
    K_k = K_kH / (1 + δK_k)                                     (M5 eq. 6)

Axes and angles (the paper's)
-----------------------------
Body axes X forward, Y up, Z right; roll γ about X, yaw ψ about Y, pitch θ
about Z (conventions of :mod:`estimators.strapdown`); gyro channel 1 = X, 2 = Y,
3 = Z. Every per-axis array here is in **body-axis order**: index 0 = X (γ,
channel 1), 1 = Y (ψ, channel 2), 2 = Z (θ, channel 3). So ``X[0] = Xγ``,
``X[1] = Xψ``, ``X[2] = Xθ``.

Phase convention. The drift about axis ``k`` comes from rocking about the
other two axes ``i = k+1``, ``j = k+2`` (cyclic over X, Y, Z); the stand's
angles are ``A sin(ν t + φ)`` and ``Δφ = φ_i − φ_j``. With every angle
positive by the right-hand rule, ``Δφ = +π/2`` makes ``X_k`` positive for
positive ``δK_i + δK_j − δK_k``: pitch leads roll (Xψ), roll leads yaw (Xθ),
yaw leads pitch (Xγ). ``Δφ = −π/2`` flips the sign of the drift, as the paper
says; the closed form takes ``sin Δφ = ±1`` by the sign of the measured phase,
so X keeps its meaning. (The article's own statement "roll leads pitch" for Xψ
corresponds to the opposite sign of pitch; its angle signs live in its
reference [2].)

Beyond the paper: a model-based estimate
----------------------------------------
The closed form is first order in the amplitudes and in δK. An exact
simulation of the paper's unit on its own stand (12.2°, 0.53 Hz) gives Xψ, Xθ
0.3 % below the formula and Xγ 5.7 % above it (a small difference of large
terms: in Xψ, Xθ a term in A² of −1.0 % and one in δK of +0.7 % nearly cancel,
in Xγ +3.8 % and +1.8 % add up), so
the closed-form δK are −0.3 %, +1.2 %, +0.7 % off, besides the ~3 % that the
stand's 1 % tolerances allow. :func:`estimate_scale_errors` also solves the
exact problem: it fits the stand's actual amplitudes, frequency and phases to
the attitude computed from the record corrected with the current δK and zero
signal (the uncorrected attitude's amplitudes are off by δK themselves),
simulates that stand through ``(1 + δK)``, the record's still gyro mean and the
same integrator, starting from the record's own attitude at the start of the
steady window, and moves δK by Gauss–Newton steps (sensitivities by simulated
finite differences) until the simulated drifts equal the measured ones. It
needs no stand settings; integrator errors cancel; noise-free it recovers a
simulated unit's δK to about 1e-6 relative.

Stand model and limits: the stand is a yaw-pitch-roll gimbal that realizes
the Euler angles above (the third angle is still); the unit sits at the
rotation centre (only gyros are used). Earth rate is optional
(``earth_rate_rps``, in the stand's rest axes; the attitude is then expressed
in those rotating axes): without it the still gyro mean is treated as a
body-fixed zero signal, which is wrong at order Ω·A²: at 54° N it moves the
model-based δK by 0.10–0.17 % (the closed form by 0.03 %).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize_scalar

from estimators._typing import FloatArray
from estimators.conventions import EARTH_RATE_RPS, RPS_PER_DPH
from estimators.session import ImuSession
from estimators.strapdown import (
    ANGLE_NAMES,
    body_rate_from_euler,
    euler_from_quat,
    integrate_attitude,
    quat_from_euler,
    quat_from_rotvec,
    quat_multiply,
    rotate_to_body,
)

PAPER_X = np.array([0.002954, 0.014514, 0.009119])
"""The paper's measured ``[Xγ, Xψ, Xθ]`` (body-axis order)."""

PAPER_DK = np.array([0.0118165, 0.0060365, 0.008734])
"""The paper's ``[δK1, δK2, δK3]`` (M5 eq. 5 applied to :data:`PAPER_X`)."""

PAPER_AMPLITUDE_RAD = float(np.radians(12.2))
PAPER_FREQUENCY_HZ = 0.53
PAPER_REL_SIGMA = 0.01
"""The stand's stated amplitude and frequency uncertainty (1 % each)."""

MIN_STATIC_S = 5.0
MIN_PERIODS = 10
PHASE_TOLERANCE_RAD = float(np.radians(10.0))

# Segmentation thresholds on the one-period moving RMS of the gyro output,
# relative to its 99th percentile (the rocking plateau).
_STATIC_LEVEL = 0.05
_ROCKING_LEVEL = 0.5
_PLATEAU_BAND = 0.03
_MIN_CONTRAST = 10.0
# Amplitude ratios that tell one, two or three rocking axes apart.
_SECOND_AXIS_MIN = 0.25
_THIRD_AXIS_MAX = 0.25
_N_HARMONICS = 3
_FD_STEP = 1e-5
_GN_TOL = 1e-7


class RockingError(ValueError):
    """A record cannot be used by the rocking method (the message says what is missing)."""


class RockingPair(StrEnum):
    """Which two angles rock; the third one drifts (M5 eqs. 1–3)."""

    ROLL_PITCH = "roll+pitch"
    ROLL_YAW = "roll+yaw"
    PITCH_YAW = "pitch+yaw"

    @property
    def drift_axis(self) -> int:
        """Body axis ``k`` of the drifting angle: ψ (Y) for roll+pitch, θ (Z) for roll+yaw, γ (X) for pitch+yaw."""
        return {RockingPair.ROLL_PITCH: 1, RockingPair.ROLL_YAW: 2, RockingPair.PITCH_YAW: 0}[self]

    @property
    def lead_axis(self) -> int:
        """Axis ``i = k+1``: ``Δφ = φ_i − φ_j = +π/2`` gives a positive X (module docstring)."""
        return (self.drift_axis + 1) % 3

    @property
    def lag_axis(self) -> int:
        """Axis ``j = k+2``."""
        return (self.drift_axis + 2) % 3

    @property
    def x_name(self) -> str:
        """``psi``, ``theta`` or ``gamma``: the X this pair measures."""
        return ANGLE_NAMES[self.drift_axis]

    @classmethod
    def from_drift_axis(cls, axis: int) -> RockingPair:
        return next(p for p in cls if p.drift_axis == axis)


PAPER_PHASE_RAD = {
    RockingPair.ROLL_PITCH: np.pi / 2,
    RockingPair.ROLL_YAW: -np.pi / 2,
    RockingPair.PITCH_YAW: np.pi / 2,
}
"""``Δφ`` of the paper's three experiments: the roll+yaw run had yaw leading roll (−π/2)."""


# --- the closed form (the paper) ---------------------------------------------


def x_from_drift(
    drift_rps: ArrayLike,
    amplitude_lead_rad: ArrayLike,
    amplitude_lag_rad: ArrayLike,
    frequency_hz: ArrayLike,
    phase_rad: ArrayLike,
) -> FloatArray:
    """``X = 2·Ḋ / (A_i A_j ν sin Δφ)`` (M5 eq. 4; ``ν = 2π f``; Ḋ with the static drift removed, rad/s)."""
    nu = 2.0 * np.pi * np.asarray(frequency_hz, float)
    x: FloatArray = (
        2.0
        * np.asarray(drift_rps, float)
        / (np.asarray(amplitude_lead_rad) * np.asarray(amplitude_lag_rad) * nu * np.sin(phase_rad))
    )
    return x


def dk_from_x(x: ArrayLike) -> FloatArray:
    """``δK_k = (ΣX − X_k)/2`` (M5 eq. 5); ``x`` = ``[Xγ, Xψ, Xθ]`` (..., 3) → ``[δK1, δK2, δK3]``."""
    xs = np.asarray(x, dtype=np.float64)
    total: FloatArray = xs.sum(axis=-1, keepdims=True)
    return 0.5 * (total - xs)


def x_from_dk(dk: ArrayLike) -> FloatArray:
    """``X_k = δK_i + δK_j − δK_k`` (M5 eqs. 1–3, first order): the inverse of :func:`dk_from_x`."""
    dks = np.asarray(dk, dtype=np.float64)
    total: FloatArray = dks.sum(axis=-1, keepdims=True)
    return total - 2.0 * dks


def corrected_coefficients(k_nominal: ArrayLike, dk: ArrayLike) -> FloatArray:
    """``K = K_H / (1 + δK)`` (M5 eq. 6), per channel; any unit of the transfer coefficient."""
    return np.asarray(k_nominal, np.float64) / (1.0 + np.asarray(dk, np.float64))


# --- the stand and the unit (simulation) ---------------------------------------


def earth_rate_stand_rps(latitude_deg: float, heading_deg: float = 0.0) -> FloatArray:
    """(3,) Earth rate in the stand's rest axes (X forward at ``heading_deg`` from north, Y up, Z right), rad/s."""
    if not np.isfinite(latitude_deg) or abs(latitude_deg) > 90.0:
        raise ValueError(f"latitude_deg must be within [-90, 90], got {latitude_deg!r}")
    if not np.isfinite(heading_deg):
        raise ValueError(f"heading_deg must be finite, got {heading_deg!r}")
    lat, hdg = np.radians(latitude_deg), np.radians(heading_deg)
    return EARTH_RATE_RPS * np.array(
        [np.cos(lat) * np.cos(hdg), np.sin(lat), -np.cos(lat) * np.sin(hdg)]
    )


@dataclass(frozen=True)
class GyroUnit:
    """The simulated gyro triad: ``ω̃ = (1 + δK)·ω + b + noise`` per channel.

    Attributes
    ----------
    scale_err : (3,) δK of channels 1–3 (X, Y, Z).
    bias_rps : (3,) additive zero signal, rad/s.
    arw_rad_per_sqrt_s : white-noise density (angle random walk), rad/s/√Hz.
    """

    scale_err: tuple[float, ...] = tuple(PAPER_DK.tolist())
    bias_rps: tuple[float, ...] = tuple((np.array([2.0, -30.0, 5.0]) * RPS_PER_DPH).tolist())
    arw_rad_per_sqrt_s: float = float(np.radians(0.003) / 60.0)

    def __post_init__(self) -> None:
        for name, n in (("scale_err", 3), ("bias_rps", 3)):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (n,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be {n} finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(v.tolist()))
        if not (np.isfinite(self.arw_rad_per_sqrt_s) and self.arw_rad_per_sqrt_s >= 0.0):
            raise ValueError(
                f"arw_rad_per_sqrt_s must be a non-negative number, got {self.arw_rad_per_sqrt_s!r}"
            )


@dataclass(frozen=True)
class RockingRun:
    """One run on the stand: static, rocking (with raised-cosine ramps), static.

    Attributes
    ----------
    pair : the two rocking angles.
    amplitude_rad : amplitude of both rocking angles, rad.
    frequency_hz : rocking frequency ``f`` (``ν = 2π f``), Hz.
    phase_rad : ``Δφ = φ_i − φ_j`` in the cyclic order of the module docstring.
    static_before_s, rocking_s, static_after_s : durations, s (the paper: ~25, ~100, ~25).
    ramp_s : amplitude ramp at each end of the rocking, s.
    """

    pair: RockingPair
    amplitude_rad: float = PAPER_AMPLITUDE_RAD
    frequency_hz: float = PAPER_FREQUENCY_HZ
    phase_rad: float = np.pi / 2
    static_before_s: float = 25.0
    rocking_s: float = 100.0
    static_after_s: float = 25.0
    ramp_s: float = 2.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "pair", RockingPair(self.pair))
        for name in ("amplitude_rad", "frequency_hz", "rocking_s"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in ("static_before_s", "static_after_s", "ramp_s"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)!r}")
        if 2.0 * self.ramp_s > self.rocking_s:
            raise ValueError(
                f"two ramps of {self.ramp_s} s do not fit in {self.rocking_s} s of rocking"
            )

    @property
    def duration_s(self) -> float:
        return self.static_before_s + self.rocking_s + self.static_after_s

    def amplitudes_rad(self) -> FloatArray:
        """(3,) per-axis amplitude (zero on the still axis)."""
        a = np.zeros(3)
        a[[self.pair.lead_axis, self.pair.lag_axis]] = self.amplitude_rad
        return a

    def phases_rad(self) -> FloatArray:
        """(3,) per-axis phase: the lagging axis at 0, the leading one at ``Δφ``."""
        p = np.zeros(3)
        p[self.pair.lead_axis] = self.phase_rad
        return p


def paper_runs(
    *,
    amplitude_rad: float = PAPER_AMPLITUDE_RAD,
    frequency_hz: float = PAPER_FREQUENCY_HZ,
    phase_rad: float | None = None,
) -> tuple[RockingRun, RockingRun, RockingRun]:
    """The paper's three 150 s runs, in the order of its method (ψ, θ, γ drift).

    ``phase_rad`` None gives the paper's phases (:data:`PAPER_PHASE_RAD`); a
    number sets ``Δφ`` of all three runs.
    """

    def run(pair: RockingPair) -> RockingRun:
        phase = PAPER_PHASE_RAD[pair] if phase_rad is None else phase_rad
        return RockingRun(pair, amplitude_rad, frequency_hz, phase)

    return run(RockingPair.ROLL_PITCH), run(RockingPair.ROLL_YAW), run(RockingPair.PITCH_YAW)


def _sinusoid_angles(
    t_s: FloatArray,
    amplitude_rad: FloatArray,
    phase_rad: FloatArray,
    frequency_hz: float,
    offset_rad: FloatArray,
    t_ref_s: float,
) -> tuple[FloatArray, FloatArray]:
    """Angles ``c + A sin(ν(t − t_ref) + φ)`` and their rates, (N, 3) each."""
    nu = 2.0 * np.pi * frequency_hz
    arg = nu * (np.asarray(t_s)[:, None] - t_ref_s) + np.asarray(phase_rad)[None]
    amp = np.asarray(amplitude_rad, np.float64)[None]
    return np.asarray(offset_rad, np.float64)[None] + amp * np.sin(arg), amp * nu * np.cos(arg)


def _gyro_output(
    angles_rad: FloatArray,
    angle_rates_rps: FloatArray,
    scale_err: ArrayLike,
    bias_rps: ArrayLike,
    earth_rate_rps: FloatArray | None,
) -> FloatArray:
    """``(1 + δK)·(ω_stand + C_rbᵀ Ω) + b`` for the stand angles; ``scale_err`` (..., 3) broadcasts a batch."""
    omega = body_rate_from_euler(angles_rad, angle_rates_rps)
    if earth_rate_rps is not None:
        omega = omega + rotate_to_body(quat_from_euler(angles_rad), earth_rate_rps)
    dk = np.asarray(scale_err, np.float64)[..., None, :]
    return (1.0 + dk) * omega + np.asarray(bias_rps, np.float64)


def simulate_run(
    run: RockingRun,
    unit: GyroUnit = GyroUnit(),
    *,
    rate_hz: float = 100.0,
    earth_rate_rps: FloatArray | None = None,
    rng: np.random.Generator,
) -> ImuSession:
    """A gyro record of one stand run (methods.md M5 bench); no accelerometer triad.

    Parameters
    ----------
    run : the stand program.
    unit : the gyro errors.
    rate_hz : sample rate, Hz.
    earth_rate_rps : (3,) Earth rate in the stand's rest axes, rad/s (:func:`earth_rate_stand_rps`); None: not simulated.
    rng : noise source.

    Returns
    -------
    :class:`ImuSession` with ``t_s`` (N,) from 0 and ``gyro_rps`` (N, 3), rad/s, paper axes.
    """
    if not (np.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
    n = round(run.duration_s * rate_hz) + 1
    t = np.arange(n) / rate_hz
    t_on = run.static_before_s
    t_off = t_on + run.rocking_s
    angles, rates = _sinusoid_angles(
        t, run.amplitudes_rad(), run.phases_rad(), run.frequency_hz, np.zeros(3), t_on
    )
    # Raised-cosine envelope e(t): the stand starts and stops smoothly; d(e·s)/dt = e'·s + e·s'.
    if run.ramp_s > 0.0:
        up = np.clip((t - t_on) / run.ramp_s, 0.0, 1.0)
        down = np.clip((t_off - t) / run.ramp_s, 0.0, 1.0)
        x = np.minimum(up, down)
        env = 0.5 * (1.0 - np.cos(np.pi * x))
        slope = np.where(up < down, 1.0, -1.0) * np.where(
            (x > 0.0) & (x < 1.0), 0.5 * np.pi / run.ramp_s * np.sin(np.pi * x), 0.0
        )
    else:
        env = ((t >= t_on) & (t <= t_off)).astype(float)
        slope = np.zeros_like(t)
    rates = env[:, None] * rates + slope[:, None] * angles
    angles = env[:, None] * angles
    gyro = _gyro_output(angles, rates, unit.scale_err, unit.bias_rps, earth_rate_rps)
    gyro = gyro + unit.arw_rad_per_sqrt_s * np.sqrt(rate_hz) * rng.standard_normal(gyro.shape)
    return ImuSession(t, None, gyro)


def simulate_runs(
    runs: Sequence[RockingRun],
    unit: GyroUnit = GyroUnit(),
    *,
    rate_hz: float = 100.0,
    earth_rate_rps: FloatArray | None = None,
    rng: np.random.Generator,
) -> ImuSession:
    """Several runs recorded one after another as one record (arguments as :func:`simulate_run`)."""
    if not runs:
        raise ValueError("simulate_runs needs at least one run")
    parts = [
        simulate_run(r, unit, rate_hz=rate_hz, earth_rate_rps=earth_rate_rps, rng=rng) for r in runs
    ]
    starts = np.cumsum([0.0] + [p.t_s[-1] + 1.0 / rate_hz for p in parts[:-1]])
    return ImuSession(
        np.concatenate([p.t_s + t0 for p, t0 in zip(parts, starts, strict=True)]),
        None,
        np.vstack([_recorded_gyro(p) for p in parts]),
    )


def _recorded_gyro(session: ImuSession) -> FloatArray:
    assert session.gyro_rps is not None  # simulate_run records the gyros
    return session.gyro_rps


# --- finding the parts of a record ---------------------------------------------


@dataclass(frozen=True)
class EpisodeSegments:
    """Index ranges ``[start, stop)`` of one rocking episode in a record.

    ``window`` is the steady rocking (ramps excluded, a whole number of periods
    of the coarse frequency ``frequency_hz``); the static ranges are the still
    parts next to it.
    """

    static_before: tuple[int, int]
    window: tuple[int, int]
    static_after: tuple[int, int]
    frequency_hz: float


def _runs(mask: FloatArray) -> list[tuple[int, int]]:
    """``[start, stop)`` of the runs of True in a boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def _peak_frequency_hz(t_s: FloatArray, gyro_rps: FloatArray) -> float:
    """Frequency of the largest spectral peak of the gyro output (zero-padded FFT, parabolic peak)."""
    dt = float(np.median(np.diff(t_s)))
    x = gyro_rps - gyro_rps.mean(axis=0)
    nfft = 8 * (1 << int(np.ceil(np.log2(len(x)))))
    power = (np.abs(np.fft.rfft(x, n=nfft, axis=0)) ** 2).sum(axis=1)
    power[0] = 0.0
    k = int(np.argmax(power[1:-1])) + 1
    a, b, c = np.log(power[k - 1 : k + 2] + 1e-300)
    shift = 0.5 * (a - c) / (a - 2.0 * b + c) if (a - 2.0 * b + c) != 0.0 else 0.0
    return float((k + shift) / (nfft * dt))


def find_episodes(
    t_s: FloatArray,
    gyro_rps: FloatArray,
    *,
    min_static_s: float = MIN_STATIC_S,
    min_periods: int = MIN_PERIODS,
) -> list[EpisodeSegments]:
    """Rocking episodes of a record, each with its steady window and the still parts around it.

    The one-period moving RMS of the gyro output separates still samples (below
    5 % of its 99th percentile) from rocking (above 50 %); the steady window is
    the part within ±3 % of the episode's median level, shrunk by one period at
    each end and cut to a whole number of periods.

    Parameters
    ----------
    t_s : (N,) times, s, increasing.
    gyro_rps : (N, 3) gyro output, rad/s.
    min_static_s : shortest usable still part, s.
    min_periods : fewest steady rocking periods.

    Raises
    ------
    RockingError
        No rocking distinguishable from still parts, an episode without a still
        part before or after it, or too little steady rocking.
    """
    t = np.asarray(t_s, float)
    g = np.asarray(gyro_rps, float)
    if t.ndim != 1 or g.shape != (t.size, 3):
        raise RockingError(
            f"a record needs t_s (N,) and gyro_rps (N, 3), got {t.shape} and {g.shape}"
        )
    if t.size < 16 or t[-1] - t[0] < 2.0 * min_static_s:
        raise RockingError(
            f"the record is too short ({t[-1] - t[0] if t.size else 0.0:.1f} s): it needs still parts of >= {min_static_s:g} s around the rocking"
        )
    dt = float(np.median(np.diff(t)))
    f0 = _peak_frequency_hz(t, g)
    w = max(3, round(1.0 / (f0 * dt)))
    # The raw rate magnitude, not its deviation from a median: rocking about two axes has a
    # rectified mean rate (½·A²·ν) that a median would carry into the still parts.
    magnitude_sq = np.sum(g**2, axis=1)
    env = np.sqrt(np.convolve(magnitude_sq, np.ones(w) / w, mode="same"))
    hi, lo = np.percentile(env, 99.0), np.percentile(env, 2.0)
    if not hi > _MIN_CONTRAST * lo:
        raise RockingError(
            f"no rocking distinguishable from still parts (gyro level {lo:.3g} to {hi:.3g} rad/s): "
            "the record needs still parts before and after two-axis rocking"
        )
    still = [(a + w, b - w) for a, b in _runs(env < _STATIC_LEVEL * hi) if (b - w) - (a + w) > 1]
    still = [(a, b) for a, b in still if t[b - 1] - t[a] >= min_static_s]
    episodes = []
    for a, b in _runs(env > _ROCKING_LEVEL * hi):
        level = np.median(env[a:b])
        plateau = [
            (p + w, q - w) for p, q in _runs(np.abs(env[a:b] / level - 1.0) <= _PLATEAU_BAND)
        ]
        p, q = max(plateau, key=lambda r: r[1] - r[0]) if plateau else (0, 0)
        f_episode = _peak_frequency_hz(t[a:b], g[a:b]) if b - a >= 16 else f0
        n_periods = int(np.floor((q - p) * dt * f_episode))
        if n_periods < min_periods:
            raise RockingError(
                f"the rocking at {t[a]:.1f}–{t[b - 1]:.1f} s has {max(n_periods, 0)} steady periods; it needs >= {min_periods}"
            )
        n_win = round(n_periods / (f_episode * dt))
        start = a + p + ((q - p) - n_win) // 2
        before = [s for s in still if s[1] <= a]
        after = [s for s in still if s[0] >= b]
        if not before:
            raise RockingError(
                f"the rocking at {t[a]:.1f}–{t[b - 1]:.1f} s has no still part before it (needs >= {min_static_s:g} s)"
            )
        if not after:
            raise RockingError(
                f"the rocking at {t[a]:.1f}–{t[b - 1]:.1f} s has no still part after it (needs >= {min_static_s:g} s)"
            )
        episodes.append(EpisodeSegments(before[-1], (start, start + n_win), after[0], f_episode))
    return episodes


# --- measuring one episode --------------------------------------------------------


@dataclass(frozen=True)
class StandFit:
    """The stand's motion as seen in a record's computed attitude.

    Angles ``c + A sin(2π f (t − t_ref) + φ)`` per axis (body-axis order; zero
    amplitude on the still axis). Covariances assume white fit residuals, so
    they are lower bounds under angle random walk (and tiny either way).

    Attributes
    ----------
    frequency_hz, frequency_sigma_hz : ``f`` and its standard deviation.
    amplitude_rad, amplitude_sigma_rad : (3,) amplitudes and their standard deviations.
    phase_rad : (3,) phases at ``t_ref_s``.
    offset_rad : (3,) centre angles.
    t_ref_s : time origin of the phases (the window's centre), s.
    """

    frequency_hz: float
    frequency_sigma_hz: float
    amplitude_rad: FloatArray
    amplitude_sigma_rad: FloatArray
    phase_rad: FloatArray
    offset_rad: FloatArray
    t_ref_s: float

    def angles(self, t_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(N, 3) stand angles and (N, 3) their rates at ``t_s``."""
        return _sinusoid_angles(
            t_s,
            self.amplitude_rad,
            self.phase_rad,
            self.frequency_hz,
            self.offset_rad,
            self.t_ref_s,
        )


@dataclass(frozen=True)
class Episode:
    """One rocking experiment measured from a record (methods.md M5).

    Attributes
    ----------
    pair : the two rocking angles (the third drifts).
    t_s, gyro_rps : (N,), (N, 3) the record from the start of the still part
        before to the end of the still part after (as recorded, uncorrected).
    segments : index ranges into ``t_s``.
    stand : the fitted stand motion.
    phase_diff_rad : ``Δφ = φ_i − φ_j`` (module docstring), in (−π, π].
    drift_static_rps : (3,) Euler-angle rates over the still parts (common slope), rad/s.
    drift_rocking_rps : (3,) Euler-angle rates over the steady window, rad/s.
    static_gyro_mean_rps : (3,) mean gyro output over the still parts, rad/s.
    arw_sq_rad2_per_s : (3,) white-noise level per channel from the still parts
        (variance × sample interval, rad²/s).
    drift_angle_rad : (N,) the computed third angle (the one that drifts), rad.
    window_start_quat : (4,) computed attitude at the start of the steady window
        (rest axes, scalar last): the model starts there, because the drift that
        follows depends on the attitude error already present (at order error × amplitude).
    """

    pair: RockingPair
    t_s: FloatArray
    gyro_rps: FloatArray
    segments: EpisodeSegments
    stand: StandFit
    phase_diff_rad: float
    drift_static_rps: FloatArray
    drift_rocking_rps: FloatArray
    static_gyro_mean_rps: FloatArray
    arw_sq_rad2_per_s: FloatArray
    drift_angle_rad: FloatArray
    window_start_quat: FloatArray

    @property
    def drift_axis(self) -> int:
        return self.pair.drift_axis

    @property
    def drift_rps(self) -> float:
        """Drift of the third angle while rocking minus the static drift, rad/s (``Ḋ_k − Ḋ_k0``)."""
        k = self.drift_axis
        return float(self.drift_rocking_rps[k] - self.drift_static_rps[k])

    def _slices(self) -> tuple[slice, slice, slice]:
        s = self.segments
        return slice(*s.static_before), slice(*s.window), slice(*s.static_after)

    @property
    def window_s(self) -> float:
        _, win, _ = self._slices()
        return float(self.t_s[win][-1] - self.t_s[win][0])

    @property
    def static_durations_s(self) -> tuple[float, float]:
        before, _, after = self._slices()
        return float(self.t_s[before][-1] - self.t_s[before][0]), float(
            self.t_s[after][-1] - self.t_s[after][0]
        )

    def drift_variance_rps2(self, *, static_from_gyro_mean: bool = False) -> float:
        """Noise variance of :attr:`drift_rps` (or of the rocking drift against a gyro-mean bias), (rad/s)².

        Under angle random walk of level ``q`` (rad²/s) the least-squares slope
        over ``T`` seconds has variance ``6q/(5T)``; two still parts with their
        own intercepts give ``6q/5 · ΣT⁵/(ΣT³)²``; a mean of the gyro over ``T``
        seconds has variance ``q/T``. The rocking window mixes all channels
        (their mean level is used); the still parts see channel ``k``.
        """
        q_mean = float(np.mean(self.arw_sq_rad2_per_s))
        q_k = float(self.arw_sq_rad2_per_s[self.drift_axis])
        var = 1.2 * q_mean / self.window_s
        ts = np.array(self.static_durations_s)
        if static_from_gyro_mean:
            return var + q_k / float(ts.sum())
        return var + 1.2 * q_k * float(np.sum(ts**5) / np.sum(ts**3) ** 2)


def _fit_columns(
    t_s: FloatArray, t_ref_s: float, frequency_hz: float, n_harmonics: int
) -> FloatArray:
    """Design ``[1, t − t_ref, cos hν(t − t_ref), sin hν(t − t_ref) for h = 1…n]`` (N, 2 + 2n)."""
    tau = t_s - t_ref_s
    cols = [np.ones_like(tau), tau]
    for h in range(1, n_harmonics + 1):
        arg = 2.0 * np.pi * h * frequency_hz * tau
        cols += [np.cos(arg), np.sin(arg)]
    return np.column_stack(cols)


def drift_rates(t_s: FloatArray, angles_rad: FloatArray, frequency_hz: float) -> FloatArray:
    """Drift rates of angles over a steady rocking window, rad/s.

    Least-squares slope of ``c + d·t + Σ_h (a_h cos hνt + b_h sin hνt)``,
    h = 1…3 (the periodic error of the computed angle is removed with it).

    Parameters
    ----------
    t_s : (N,) times, s.
    angles_rad : (..., N) angle series (a batch shares ``t_s``).
    frequency_hz : rocking frequency.

    Returns
    -------
    (...,) slopes ``d``, rad/s.
    """
    a = np.asarray(angles_rad, float)
    design = _fit_columns(t_s, 0.5 * (t_s[0] + t_s[-1]), frequency_hz, _N_HARMONICS)
    coef = np.linalg.lstsq(design, a.reshape(-1, a.shape[-1]).T, rcond=None)[0]
    slopes: FloatArray = coef[1].reshape(a.shape[:-1])
    return slopes


def _static_drift(
    t_s: FloatArray, angles_rad: FloatArray, before: slice, after: slice
) -> FloatArray:
    """(3,) common slope of the angles over both still parts (each with its own intercept)."""
    tb, ta = t_s[before], t_s[after]
    tc = 0.5 * (tb[0] + ta[-1])
    design = np.zeros((tb.size + ta.size, 3))
    design[:, 0] = np.concatenate([tb, ta]) - tc
    design[: tb.size, 1] = 1.0
    design[tb.size :, 2] = 1.0
    y = np.concatenate([angles_rad[before], angles_rad[after]])
    slopes: FloatArray = np.linalg.lstsq(design, y, rcond=None)[0][0]
    return slopes


def _fit_stand(
    t_s: FloatArray, angles_rad: FloatArray, axes: list[int], f0_hz: float, *, search_lines: float
) -> StandFit:
    """Common-frequency sinusoids on the rocking angles (variable projection over f, then the full Jacobian).

    The frequency is searched within ``f0_hz ± search_lines / span`` (``1/span``
    is the width of the spectral line).
    """
    t_ref = 0.5 * (t_s[0] + t_s[-1])
    y = angles_rad[:, axes]
    half_width = search_lines / (t_s[-1] - t_s[0])

    def cost(f: float) -> float:
        design = _fit_columns(t_s, t_ref, f, 1)
        return float(np.linalg.lstsq(design, y, rcond=None)[1].sum())

    f = float(
        minimize_scalar(
            cost,
            bounds=(f0_hz - half_width, f0_hz + half_width),
            method="bounded",
            options={"xatol": 1e-10},
        ).x
    )
    design = _fit_columns(t_s, t_ref, f, 1)
    coef, res = np.linalg.lstsq(design, y, rcond=None)[:2]
    n, m = y.shape
    # Full Jacobian of [f, (c, d, a, b) per axis] for the covariance.
    tau = t_s - t_ref
    arg = 2.0 * np.pi * f * tau
    jac = np.zeros((n * m, 1 + 4 * m))
    for col in range(m):
        rows = slice(col * n, (col + 1) * n)
        a_c, b_s = coef[2, col], coef[3, col]
        jac[rows, 0] = 2.0 * np.pi * tau * (-a_c * np.sin(arg) + b_s * np.cos(arg))
        jac[rows, 1 + 4 * col : 5 + 4 * col] = design
    s2 = float(res.sum()) / max(n * m - jac.shape[1], 1) if res.size else 0.0
    # Centred time over whole periods keeps JᵀJ well conditioned: Cholesky is safe here.
    cov = s2 * cho_solve(cho_factor(jac.T @ jac), np.eye(jac.shape[1]))
    amplitude, amp_sigma, phase, offset = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    for col, ax in enumerate(axes):
        a_c, b_s = coef[2, col], coef[3, col]
        amp = float(np.hypot(a_c, b_s))
        grad = np.array([a_c, b_s]) / amp
        idx = [3 + 4 * col, 4 + 4 * col]
        amplitude[ax] = amp
        amp_sigma[ax] = float(np.sqrt(grad @ cov[np.ix_(idx, idx)] @ grad))
        phase[ax] = float(np.arctan2(a_c, b_s))  # a cos + b sin = A sin(· + φ)
        offset[ax] = coef[0, col]
    return StandFit(f, float(np.sqrt(cov[0, 0])), amplitude, amp_sigma, phase, offset, float(t_ref))


def _classify(amplitude_rad: FloatArray, t_span: tuple[float, float]) -> RockingPair:
    order = np.argsort(amplitude_rad)[::-1]
    a1, a2, a3 = amplitude_rad[order]
    where = f"the rocking at {t_span[0]:.1f}–{t_span[1]:.1f} s"
    if a2 < _SECOND_AXIS_MIN * a1:
        raise RockingError(
            f"{where} rocks {_ANGLE_WORDS[order[0]]} only (other amplitudes < {_SECOND_AXIS_MIN:.0%} of it): "
            "the method needs two axes rocking at the same frequency with a ±90° phase"
        )
    if a3 > _THIRD_AXIS_MAX * a2:
        raise RockingError(
            f"{where} rocks all three angles; the method needs exactly two rocking and the third still"
        )
    return RockingPair.from_drift_axis(int(order[2]))


_ANGLE_WORDS = ("roll", "yaw", "pitch")


def stand_attitude(
    t_s: FloatArray,
    gyro_rps: FloatArray,
    *,
    quat0: FloatArray | None = None,
    earth_rate_rps: FloatArray | None = None,
) -> FloatArray:
    """(..., N, 4) attitude relative to the stand's rest axes from gyro output (..., N, 3).

    The strapdown integral is relative to inertial axes that coincide with the
    rest axes at ``t_s[0]``; with ``earth_rate_rps`` (3,) the rest axes turn at
    that constant rate, so ``q_rest(t) = q(−Ω (t − t_0)) ⊗ q(t)`` exactly.
    """
    q = integrate_attitude(t_s, gyro_rps, quat0=quat0)
    if earth_rate_rps is None:
        return q
    t = np.asarray(t_s, float)
    back = quat_from_rotvec(-(t - t[0])[:, None] * np.asarray(earth_rate_rps, float)[None])
    return quat_multiply(back, q)


def measure_episode(
    t_s: FloatArray,
    gyro_rps: FloatArray,
    segments: EpisodeSegments,
    *,
    scale_err: FloatArray | None = None,
    bias_rps: FloatArray | None = None,
    earth_rate_rps: FloatArray | None = None,
    frequency_hz: float | None = None,
    phase_tolerance_rad: float = PHASE_TOLERANCE_RAD,
) -> Episode:
    """Drifts and stand motion of one episode (methods.md M5, the paper's measurement).

    The attitude is integrated from the start of the still part before the
    rocking (the stand's rest attitude, identity) and expressed in the rest
    axes (:func:`stand_attitude`); its Euler angles give the static drift
    (still parts), the rocking drift (:func:`drift_rates` over the steady
    window) and the stand fit.

    Parameters
    ----------
    t_s, gyro_rps : the whole record, (N,) s and (N, 3) rad/s.
    segments : from :func:`find_episodes`.
    scale_err : (3,) δK to correct the record with (``ω/(1 + δK)``, M5 eq. 6); None: as recorded.
    bias_rps : (3,) zero signal to remove before that, rad/s; None: none.
    earth_rate_rps : (3,) Earth rate in the rest axes, rad/s; None: not modelled.
    frequency_hz : the rocking frequency if already fitted to this record: it is
        then refined within a twentieth of the spectral line (a correction
        moves it only that little); None searches the whole line.
    phase_tolerance_rad : how far ``|Δφ|`` may be from π/2.

    Raises
    ------
    RockingError
        Single-axis or three-axis rocking, or a phase not near ±π/2.
    """
    lo, hi = segments.static_before[0], segments.static_after[1]
    t = np.asarray(t_s, float)[lo:hi]
    g_rec = np.asarray(gyro_rps, float)[lo:hi]

    def local_range(r: tuple[int, int]) -> tuple[int, int]:
        return r[0] - lo, r[1] - lo

    local = EpisodeSegments(
        local_range(segments.static_before),
        local_range(segments.window),
        local_range(segments.static_after),
        segments.frequency_hz,
    )
    g = g_rec if bias_rps is None else g_rec - np.asarray(bias_rps, float)
    g = g if scale_err is None else g / (1.0 + np.asarray(scale_err, float))
    quat = stand_attitude(t, g, earth_rate_rps=earth_rate_rps)
    angles = euler_from_quat(quat)
    before, win, after = (
        slice(*local.static_before),
        slice(*local.window),
        slice(*local.static_after),
    )
    tw = t[win]
    span = (float(tw[0]), float(tw[-1]))
    coarse = np.linalg.lstsq(
        _fit_columns(tw, tw.mean(), segments.frequency_hz, 1), angles[win], rcond=None
    )[0]
    pair = _classify(np.hypot(coarse[2], coarse[3]), span)
    axes = [pair.lead_axis, pair.lag_axis]
    if frequency_hz is None:
        stand = _fit_stand(tw, angles[win], axes, segments.frequency_hz, search_lines=0.5)
    else:
        stand = _fit_stand(tw, angles[win], axes, frequency_hz, search_lines=0.05)
    dphi = float(
        np.angle(np.exp(1j * (stand.phase_rad[pair.lead_axis] - stand.phase_rad[pair.lag_axis])))
    )
    if abs(abs(dphi) - np.pi / 2) > phase_tolerance_rad:
        raise RockingError(
            f"the {pair.value} rocking at {span[0]:.1f}–{span[1]:.1f} s has a phase difference of {np.degrees(dphi):.1f}°, "
            f"not within {np.degrees(phase_tolerance_rad):.0f}° of ±90°"
        )
    still = np.concatenate([g_rec[before], g_rec[after]])
    centred = np.concatenate(
        [g_rec[before] - g_rec[before].mean(axis=0), g_rec[after] - g_rec[after].mean(axis=0)]
    )
    dt = float(np.median(np.diff(t)))
    return Episode(
        pair=pair,
        t_s=t,
        gyro_rps=g_rec,
        segments=local,
        stand=stand,
        phase_diff_rad=dphi,
        drift_static_rps=_static_drift(t, angles, before, after),
        drift_rocking_rps=drift_rates(tw, angles[win].T, stand.frequency_hz),
        static_gyro_mean_rps=still.mean(axis=0),
        arw_sq_rad2_per_s=centred.var(axis=0) * dt,
        drift_angle_rad=angles[:, pair.drift_axis],
        window_start_quat=quat[local.window[0]],
    )


# --- the estimates ----------------------------------------------------------------


@dataclass(frozen=True)
class StandSettings:
    """What the stand was set to, with its stated uncertainty (the closed form uses it).

    Attributes
    ----------
    amplitude_rad : amplitude of every rocking angle, rad.
    frequency_hz : rocking frequency, Hz.
    amplitude_rel_sigma, frequency_rel_sigma : relative uncertainties (the paper: 1 % each).
    """

    amplitude_rad: float = PAPER_AMPLITUDE_RAD
    frequency_hz: float = PAPER_FREQUENCY_HZ
    amplitude_rel_sigma: float = PAPER_REL_SIGMA
    frequency_rel_sigma: float = PAPER_REL_SIGMA

    def __post_init__(self) -> None:
        for name in ("amplitude_rad", "frequency_hz"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in ("amplitude_rel_sigma", "frequency_rel_sigma"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class ClosedForm:
    """The paper's estimate (M5 eqs. 4–5) with its uncertainty.

    Attributes
    ----------
    x : (3,) ``[Xγ, Xψ, Xθ]``.
    x_cov : (3, 3) covariance of ``x``: stand uncertainty (Gaussian, independent
        per stand axis and frequency) plus drift noise.
    dk : (3,) ``[δK1, δK2, δK3]``.
    dk_cov : (3, 3) covariance of ``dk``.
    dk_bound : (3,) worst case of ``dk`` from the stand uncertainty alone
        (all errors adding up: the paper's "1 % gives 3 %").
    amplitude_rad : (3, 2) amplitudes ``(A_i, A_j)`` used for each X.
    frequency_hz : (3,) frequency used for each X.
    """

    x: FloatArray
    x_cov: FloatArray
    dk: FloatArray
    dk_cov: FloatArray
    dk_bound: FloatArray
    amplitude_rad: FloatArray
    frequency_hz: FloatArray


@dataclass(frozen=True)
class ModelBased:
    """The model-based estimate (module docstring).

    Attributes
    ----------
    dk : (3,) ``[δK1, δK2, δK3]``.
    dk_cov : (3, 3) covariance from the drift noise (:meth:`Episode.drift_variance_rps2`).
    steps : Gauss–Newton steps taken.
    jacobian : (3, 3) ``∂Ḋ/∂δK`` of the modelled drifts (rows: episodes in body-axis order of their drift axis), rad/s.
    residual_rps : (3,) measured minus modelled rocking drift at the solution, rad/s.
    """

    dk: FloatArray
    dk_cov: FloatArray
    steps: int
    jacobian: FloatArray
    residual_rps: FloatArray


@dataclass(frozen=True)
class RockingResult:
    """Everything M5 reports (methods.md M5).

    Attributes
    ----------
    episodes : the three experiments, indexed by drift axis (0: γ, 1: ψ, 2: θ), as recorded.
    closed : the paper's closed form.
    model : the model-based estimate (the default ``dk``).
    corrected : the three experiments re-measured with ``ω/(1 + dk)`` (M5 eq. 6).
    fitted : the three experiments re-measured with ``(ω − b)/(1 + dk)``: their
        ``stand`` is the stand's actual motion (what the model simulated).
    stand : the stand settings the closed form used (None: the fitted motion).
    """

    episodes: tuple[Episode, Episode, Episode]
    closed: ClosedForm
    model: ModelBased
    corrected: tuple[Episode, Episode, Episode]
    fitted: tuple[Episode, Episode, Episode]
    stand: StandSettings | None = None

    @property
    def dk(self) -> FloatArray:
        """(3,) the default estimate: model-based δK of channels 1–3."""
        return self.model.dk

    @property
    def dk_sigma(self) -> FloatArray:
        return np.sqrt(np.diag(self.model.dk_cov))

    @property
    def drift_rps(self) -> FloatArray:
        """(3,) ``Ḋ_k − Ḋ_k0`` of each experiment's drift axis, as recorded, rad/s."""
        return np.array([e.drift_rps for e in self.episodes])

    @property
    def drift_corrected_rps(self) -> FloatArray:
        """(3,) the same after the correction with :attr:`dk`, rad/s."""
        return np.array([e.drift_rps for e in self.corrected])

    def corrected_coefficients(self, k_nominal: ArrayLike = (1.0, 1.0, 1.0)) -> FloatArray:
        """``K = K_H / (1 + δK)`` (M5 eq. 6) with the model-based δK."""
        return corrected_coefficients(k_nominal, self.dk)


def closed_form(episodes: Sequence[Episode], stand: StandSettings | None = None) -> ClosedForm:
    """The paper's X and δK (M5 eqs. 4–5) with the stand's and the noise's uncertainty.

    Parameters
    ----------
    episodes : three episodes indexed by drift axis (0: γ, 1: ψ, 2: θ).
    stand : the stand's settings and their uncertainty; None uses each
        episode's fitted amplitudes and frequency with their fit uncertainty.
    """
    if [e.drift_axis for e in episodes] != [0, 1, 2]:
        raise ValueError(
            "closed_form needs the three episodes ordered by drift axis: pitch+yaw, roll+pitch, roll+yaw"
        )
    amp = np.zeros((3, 2))
    freq = np.zeros(3)
    # Uncertain stand quantities p (relative σ): with settings, the amplitude of
    # the X, Y, Z stand axes and the common frequency; fitted, A_i, A_j, f per episode.
    sigma_p = np.zeros(4 if stand is not None else 9)
    uses = np.zeros((3, sigma_p.size))
    for k, e in enumerate(episodes):
        i, j = e.pair.lead_axis, e.pair.lag_axis
        if stand is not None:
            amp[k], freq[k] = stand.amplitude_rad, stand.frequency_hz
            uses[k, [i, j, 3]] = 1.0
        else:
            amp[k], freq[k] = e.stand.amplitude_rad[[i, j]], e.stand.frequency_hz
            sigma_p[3 * k : 3 * k + 3] = np.array(
                [*e.stand.amplitude_sigma_rad[[i, j]], e.stand.frequency_sigma_hz]
            ) / [*amp[k], freq[k]]
            uses[k, 3 * k : 3 * k + 3] = 1.0
    if stand is not None:
        sigma_p[:] = [stand.amplitude_rel_sigma] * 3 + [stand.frequency_rel_sigma]
    # The paper's formula: Δφ = ±π/2 exactly (the sign flips X); a stand off π/2 is a model error.
    phase = np.copysign(np.pi / 2, [e.phase_diff_rad for e in episodes])
    x = x_from_drift([e.drift_rps for e in episodes], amp[:, 0], amp[:, 1], freq, phase)
    sens = -uses * x[:, None]  # ∂X_k/∂ln p = −X_k for every p that X_k divides by
    dx_ddrift = x_from_drift(1.0, amp[:, 0], amp[:, 1], freq, phase)
    var_noise = np.array([e.drift_variance_rps2() for e in episodes]) * dx_ddrift**2
    x_cov = sens @ np.diag(sigma_p**2) @ sens.T + np.diag(var_noise)
    to_dk = 0.5 * (np.ones((3, 3)) - np.eye(3))  # M5 eq. 5 as a matrix
    return ClosedForm(
        x, x_cov, dk_from_x(x), to_dk @ x_cov @ to_dk.T, np.abs(to_dk @ sens) @ sigma_p, amp, freq
    )


def _bias_estimate(
    episode: Episode, scale_err: FloatArray, earth_rate_rps: FloatArray | None
) -> FloatArray:
    """(..., 3) zero signal: the still gyro mean less the Earth rate it saw (``(1 + δK)·Ω`` at rest)."""
    omega_rest = np.zeros(3) if earth_rate_rps is None else np.asarray(earth_rate_rps, float)
    return episode.static_gyro_mean_rps - (1.0 + np.asarray(scale_err, float)) * omega_rest


def _model_drift(
    episode: Episode, stand: StandFit, scale_err: FloatArray, earth_rate_rps: FloatArray | None
) -> FloatArray:
    """(B,) modelled rocking drift of the episode's drift axis for a batch of δK (B, 3), rad/s.

    The stand's fitted motion over the steady window, through ``(1 + δK)``, the
    Earth rate and the record's zero signal, integrated like the record from
    the record's own attitude at the window start.
    """
    t = episode.t_s[slice(*episode.segments.window)]
    angles, rates = stand.angles(t)
    scale_err = np.atleast_2d(scale_err)
    bias = _bias_estimate(episode, scale_err, earth_rate_rps)
    gyro = _gyro_output(angles, rates, scale_err, bias[:, None, :], earth_rate_rps)
    q = stand_attitude(t, gyro, quat0=episode.window_start_quat, earth_rate_rps=earth_rate_rps)
    return drift_rates(t, euler_from_quat(q)[..., episode.drift_axis], stand.frequency_hz)


def _order_by_drift_axis(episodes: Sequence[Episode]) -> tuple[Episode, Episode, Episode]:
    by_axis: dict[int, Episode] = {}
    for e in episodes:
        if e.drift_axis in by_axis:
            raise RockingError(f"two episodes rock {e.pair.value}; give one run per pair")
        by_axis[e.drift_axis] = e
    missing = [RockingPair.from_drift_axis(k).value for k in range(3) if k not in by_axis]
    if missing:
        found = ", ".join(RockingPair.from_drift_axis(k).value for k in sorted(by_axis)) or "none"
        raise RockingError(
            f"δK needs the three rocking pairs; the records hold {found} (missing: {', '.join(missing)})"
        )
    return by_axis[0], by_axis[1], by_axis[2]


def estimate_scale_errors(
    sessions: Sequence[ImuSession],
    *,
    stand: StandSettings | None = None,
    earth_rate_rps: FloatArray | None = None,
    phase_tolerance_rad: float = PHASE_TOLERANCE_RAD,
    min_static_s: float = MIN_STATIC_S,
    min_periods: int = MIN_PERIODS,
    max_steps: int = 8,
) -> RockingResult:
    """Gyro scale-factor errors from rocking records: the paper's closed form and the model-based estimate.

    Parameters
    ----------
    sessions : records with gyro samples (rad/s, paper axes); together they must
        hold one episode of each pair (a record may hold several episodes, each
        with still parts around it).
    stand : the stand's nominal settings for the closed form; None uses the
        motion fitted to the records (the model-based estimate never needs it).
    earth_rate_rps : (3,) Earth rate in the stand's rest axes, rad/s, if the records contain it.
    phase_tolerance_rad : how far ``|Δφ|`` may be from π/2.
    min_static_s, min_periods : see :func:`find_episodes`.
    max_steps : Gauss–Newton steps allowed.

    Raises
    ------
    RockingError
        Unusable records (see :func:`find_episodes`, :func:`measure_episode`),
        a missing or repeated pair, or no convergence.
    """
    found = []
    for s in sessions:
        if s.gyro_rps is None:
            raise RockingError("a rocking record needs gyro samples (gx, gy, gz)")
        for seg in find_episodes(
            s.t_s, s.gyro_rps, min_static_s=min_static_s, min_periods=min_periods
        ):
            found.append(
                measure_episode(
                    s.t_s,
                    s.gyro_rps,
                    seg,
                    earth_rate_rps=earth_rate_rps,
                    phase_tolerance_rad=phase_tolerance_rad,
                )
            )
    episodes = _order_by_drift_axis(found)

    def measure_all(dk: FloatArray, *, remove_bias: bool) -> tuple[Episode, Episode, Episode]:
        e0, e1, e2 = (
            measure_episode(
                e.t_s,
                e.gyro_rps,
                e.segments,
                scale_err=dk,
                bias_rps=_bias_estimate(e, dk, earth_rate_rps) if remove_bias else None,
                earth_rate_rps=earth_rate_rps,
                frequency_hz=e.stand.frequency_hz,
                phase_tolerance_rad=phase_tolerance_rad,
            )
            for e in episodes
        )
        return e0, e1, e2

    measured = np.array([e.drift_rocking_rps[e.drift_axis] for e in episodes])
    dk = closed_form(episodes, stand).dk
    # The drift is nearly linear in δK: the sensitivities simulated at the first step
    # serve every step (the stand re-fit is what makes the iteration necessary).
    batch = np.vstack([np.zeros(3), _FD_STEP * np.eye(3)])
    jac = None
    delta = np.full(3, np.inf)
    for steps in range(max_steps + 1):
        # The stand is fitted to the record corrected with the current δK and zero
        # signal: the uncorrected attitude's amplitudes are off by δK themselves.
        fitted = measure_all(dk, remove_bias=True)
        trial = dk[None] + (batch if jac is None else batch[:1])
        rows = np.array(
            [
                _model_drift(e, f.stand, trial, earth_rate_rps)
                for e, f in zip(episodes, fitted, strict=True)
            ]
        )
        residual = measured - rows[:, 0]
        if jac is None:
            jac = (rows[:, 1:] - rows[:, :1]) / _FD_STEP
        if np.max(np.abs(delta)) < _GN_TOL:
            break
        if steps == max_steps:
            raise RockingError(
                f"the model-based estimate did not converge in {max_steps} Gauss–Newton steps: the records do not fit the stand model"
            )
        delta = np.linalg.solve(jac, residual)
        dk = dk + delta
    assert jac is not None  # set at the first step
    sigma_r = np.sqrt([e.drift_variance_rps2(static_from_gyro_mean=True) for e in episodes])
    g = np.linalg.solve(jac, np.diag(sigma_r))
    model = ModelBased(dk, g @ g.T, steps, jac, residual)
    closed = closed_form(episodes if stand is not None else _with_stand(episodes, fitted), stand)
    return RockingResult(episodes, closed, model, measure_all(dk, remove_bias=False), fitted, stand)


def _with_stand(
    episodes: tuple[Episode, Episode, Episode], corrected: tuple[Episode, Episode, Episode]
) -> tuple[Episode, Episode, Episode]:
    """The recorded episodes with the stand motion fitted on the corrected record (not biased by δK)."""
    e0, e1, e2 = (replace(e, stand=c.stand) for e, c in zip(episodes, corrected, strict=True))
    return e0, e1, e2
