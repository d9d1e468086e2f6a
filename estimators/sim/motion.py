"""True motion of the simulated unit: attitude, body rate, kinematic acceleration.

Frames (see :mod:`estimators.conventions`): the navigation frame ``n`` is the
local East-North-Up frame, the body frame ``b`` is the frame of the sensor axes
before their non-orthogonality. ``mat_nb`` maps body vectors to navigation
vectors (``v_n = mat_nb @ v_b``). ``rate_nb_b`` is the rate of the body relative
to the navigation frame, in body axes; the gyro input adds the Earth rate (see
:mod:`estimators.sim.session`).

A profile is an initial attitude and an ordered list of segments:

* :class:`Hold` — the unit is static (a *position* of methods.md M1),
* :class:`Turn` — a rotation about a fixed body axis with a minimum-jerk angle
  profile, so rate and angular acceleration are zero at both ends, as when a
  person or a table turns the unit between positions,
* :class:`Fly` — flight-like motion of a small vehicle: smooth roll, pitch and
  yaw excursions, translational acceleration and vibration, faded in and out
  so the segment starts and ends at rest in its start attitude.
* :class:`Spin` — a rotation about a fixed body axis at a constant rate, or at
  a rate changing linearly in time (a rate table's steps and the ramps between
  them).

Every segment gives its attitude and rate from the same analytic angle
functions, so integrating ``rate_nb_b`` reproduces ``mat_nb`` exactly (up to
the integrator's error).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

# scipy is imported in the functions that use it: it takes a large part of a second to import, and
# `calibrate` imports this module (through the audit) for sessions the audit does not simulate too.
from estimators._typing import BoolArray, FloatArray, IntArray

_UP_N = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Hold:
    """The unit rests in its current attitude for ``duration_s`` seconds."""

    duration_s: float


@dataclass(frozen=True)
class Turn:
    """A rotation to the attitude ``to_mat_nb`` (3, 3) about a fixed body axis.

    The angle follows the minimum-jerk profile ``θ(s) = Θ(10s³ − 15s⁴ + 6s⁵)``,
    ``s = τ / duration_s``; the body rate is ``θ'(τ)·k`` with ``k`` the unit axis
    of the rotation ``mat_nb(start)ᵀ·to_mat_nb``.
    """

    to_mat_nb: ArrayLike
    duration_s: float

    def __post_init__(self) -> None:
        m = np.asarray(self.to_mat_nb, dtype=float)
        if (
            m.shape != (3, 3)
            or not np.allclose(m @ m.T, np.eye(3), atol=1e-9)
            or np.linalg.det(m) <= 0
        ):
            raise ValueError(f"Turn.to_mat_nb must be a (3, 3) rotation matrix, got {m.tolist()!r}")
        object.__setattr__(self, "to_mat_nb", tuple(map(tuple, m)))


@dataclass(frozen=True)
class Fly:
    """Flight-like motion of a small vehicle, relative to the start attitude.

    Roll, pitch and yaw deviations (rad, about the body axes x, y, z of the
    start attitude, composed ``Rz(ψ)·Ry(θ)·Rx(φ)``) and the translational
    acceleration (m/s², navigation frame) are sums of ``n_components``
    sinusoids with random frequencies in ``maneuver_hz`` and random phases;
    vibration adds sinusoids with frequencies in ``vibration_hz``. A
    minimum-jerk window of ``ramp_s`` fades everything in and out, so attitude,
    rate, velocity and acceleration are continuous with the neighbouring
    segments. The random draws come from the generator given to
    :func:`build_motion`. Vibration above the Nyquist frequency of the session
    aliases, as it does in a sampled sensor without an anti-alias filter.
    """

    duration_s: float
    attitude_amp_rad: float = 0.25
    yaw_amp_rad: float = 0.8
    accel_amp_mps2: float = 2.0
    maneuver_hz: tuple[float, float] = (0.05, 0.5)
    vibration_mps2: float = 0.5
    vibration_rad: float = 2.0e-4
    vibration_hz: tuple[float, float] = (20.0, 45.0)
    n_components: int = 3
    ramp_s: float = 2.0


@dataclass(frozen=True)
class Spin:
    """A rotation about the fixed body axis ``axis_b`` at the rate ``rate_rps``, rad/s.

    With ``end_rate_rps`` the rate changes linearly from ``rate_rps`` to it over
    the segment (constant angular acceleration); the angle is then
    ``θ(τ) = r₀τ + (r₁ − r₀)τ²/(2·duration_s)``. The rate is not faded: a
    neighbouring segment at another rate makes a step, as a table's does.
    ``axis_b`` is normalized to unit length.
    """

    duration_s: float
    rate_rps: float
    axis_b: ArrayLike = (0.0, 0.0, 1.0)
    end_rate_rps: float | None = None

    def __post_init__(self) -> None:
        k = np.asarray(self.axis_b, dtype=float)
        norm = np.linalg.norm(k) if k.shape == (3,) else 0.0
        if not np.isfinite(norm) or norm == 0.0:
            raise ValueError(f"Spin.axis_b must be a non-zero finite 3-vector, got {self.axis_b!r}")
        end = self.rate_rps if self.end_rate_rps is None else self.end_rate_rps
        if not (np.isfinite(self.rate_rps) and np.isfinite(end)):
            raise ValueError(
                f"Spin rates must be finite, got {self.rate_rps!r} and {self.end_rate_rps!r}"
            )
        object.__setattr__(self, "axis_b", tuple(k / norm))
        object.__setattr__(self, "rate_rps", float(self.rate_rps))
        object.__setattr__(self, "end_rate_rps", float(end))


Segment = Hold | Turn | Fly | Spin


@dataclass(frozen=True)
class MotionProfile:
    """An initial attitude ``initial_mat_nb`` (3, 3) and the ordered segments."""

    initial_mat_nb: ArrayLike
    segments: tuple[Segment, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        m = np.asarray(self.initial_mat_nb, dtype=float)
        if m.shape != (3, 3) or not np.allclose(m @ m.T, np.eye(3), atol=1e-9):
            raise ValueError(f"initial_mat_nb must be a (3, 3) rotation matrix, got {m.tolist()!r}")
        object.__setattr__(self, "initial_mat_nb", tuple(map(tuple, m)))
        segs = tuple(self.segments)
        if not segs:
            raise ValueError("a motion profile needs at least one segment")
        for s in segs:
            if not isinstance(s, (Hold, Turn, Fly, Spin)):
                raise ValueError(f"unknown segment {s!r}")
            if not np.isfinite(s.duration_s) or s.duration_s <= 0:
                raise ValueError(f"segment duration must be positive and finite, got {s!r}")
        object.__setattr__(self, "segments", segs)

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))


@dataclass(frozen=True)
class Motion:
    """Sampled true motion.

    Attributes
    ----------
    t_s : (N,) sample times, s.
    mat_nb : (N, 3, 3) attitude, body → navigation (ENU).
    rate_nb_b_rps : (N, 3) body rate relative to the navigation frame, rad/s, body axes.
    accel_n_mps2 : (N, 3) kinematic acceleration, m/s², navigation frame.
    static : (N,) True inside :class:`Hold` segments (nominally static).
    position_index : (N,) index of the :class:`Hold` segment (0, 1, …), −1 elsewhere.
    """

    t_s: FloatArray
    mat_nb: FloatArray
    rate_nb_b_rps: FloatArray
    accel_n_mps2: FloatArray
    static: BoolArray
    position_index: IntArray

    @property
    def static_intervals_s(self) -> FloatArray:
        """(K, 2) first and last sample time of each :class:`Hold` segment, s."""
        idx = self.position_index
        k = int(idx.max()) + 1 if idx.size else 0
        out = np.empty((k, 2))
        for j in range(k):
            where = np.flatnonzero(idx == j)
            out[j] = self.t_s[where[0]], self.t_s[where[-1]]
        return out


# --- analytic building blocks -------------------------------------------------


def min_jerk(s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Minimum-jerk ramp on ``s ∈ [0, 1]`` and its first two derivatives in ``s``."""
    s = np.clip(s, 0.0, 1.0)
    s2 = s * s
    return (
        s2 * s * (10.0 - 15.0 * s + 6.0 * s2),
        30.0 * s2 * (1.0 - 2.0 * s + s2),
        60.0 * s - 180.0 * s2 + 120.0 * s2 * s,
    )


def fade_window(
    tau_s: FloatArray, length_s: float, ramp_s: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A window rising and falling with minimum-jerk ramps; value and derivatives in s.

    ``tau_s`` is the local time in ``[0, length_s]``; the ramps last
    ``min(ramp_s, length_s / 2)``.
    """
    r = min(ramp_s, 0.5 * length_s)
    up, up1, up2 = min_jerk(tau_s / r)
    dn, dn1, dn2 = min_jerk((length_s - tau_s) / r)
    rising = tau_s < r
    falling = tau_s > length_s - r
    w = np.where(rising, up, np.where(falling, dn, 1.0))
    w1 = np.where(rising, up1 / r, np.where(falling, -dn1 / r, 0.0))
    w2 = np.where(rising, up2 / r**2, np.where(falling, dn2 / r**2, 0.0))
    return w, w1, w2


def sinusoid_sum(
    tau_s: FloatArray, amp: FloatArray, freq_hz: FloatArray, phase_rad: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``Σ_m amp_m sin(2π f_m τ + p_m)`` per channel, with first and second time derivatives.

    ``amp``, ``freq_hz``, ``phase_rad`` have shape (C, M) for C channels of M
    components; returns three (N, C) arrays.
    """
    w = 2.0 * np.pi * np.asarray(freq_hz)
    arg = tau_s[:, None, None] * w[None] + np.asarray(phase_rad)[None]
    s, c = np.sin(arg), np.cos(arg)
    a = np.asarray(amp)[None]
    return (a * s).sum(-1), (a * w * c).sum(-1), (-a * w * w * s).sum(-1)


def euler_zyx_matrix(roll: FloatArray, pitch: FloatArray, yaw: FloatArray) -> FloatArray:
    """(N, 3, 3) ``Rz(yaw)·Ry(pitch)·Rx(roll)``."""
    sf, cf = np.sin(roll), np.cos(roll)
    st, ct = np.sin(pitch), np.cos(pitch)
    sp, cp = np.sin(yaw), np.cos(yaw)
    return np.stack(
        [
            np.stack([cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf], axis=-1),
            np.stack([sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf], axis=-1),
            np.stack([-st, ct * sf, ct * cf], axis=-1),
        ],
        axis=-2,
    )


def euler_zyx_body_rate(
    roll: FloatArray,
    pitch: FloatArray,
    roll_rate: FloatArray,
    pitch_rate: FloatArray,
    yaw_rate: FloatArray,
) -> FloatArray:
    """(N, 3) body rate of ``Rz(ψ)·Ry(θ)·Rx(φ)`` from the Euler angle rates.

    ``p = φ' − ψ' sinθ``, ``q = θ' cosφ + ψ' cosθ sinφ``, ``r = −θ' sinφ + ψ' cosθ cosφ``.
    """
    sf, cf = np.sin(roll), np.cos(roll)
    st, ct = np.sin(pitch), np.cos(pitch)
    return np.column_stack(
        [
            roll_rate - yaw_rate * st,
            pitch_rate * cf + yaw_rate * ct * sf,
            -pitch_rate * sf + yaw_rate * ct * cf,
        ]
    )


def windowed_excursion(
    tau_s: FloatArray,
    length_s: float,
    ramp_s: float,
    amp: FloatArray,
    freq_hz: FloatArray,
    phase_rad: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``w(τ)·s(τ)`` and its first two derivatives, (N, C) each (see :func:`fade_window`)."""
    w, w1, w2 = fade_window(tau_s, length_s, ramp_s)
    s, s1, s2 = sinusoid_sum(tau_s, amp, freq_hz, phase_rad)
    w, w1, w2 = w[:, None], w1[:, None], w2[:, None]
    return w * s, w1 * s + w * s1, w2 * s + 2.0 * w1 * s1 + w * s2


def random_sinusoids(
    rng: np.random.Generator,
    n_channels: int,
    n_components: int,
    rms: ArrayLike,
    band_hz: Sequence[float],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Amplitudes, frequencies and phases of ``n_components`` sinusoids per channel.

    Frequencies are log-uniform in ``band_hz``; each channel's total RMS is ``rms``.
    """
    lo, hi = band_hz
    if not 0 < lo <= hi:
        raise ValueError(f"a frequency band must satisfy 0 < low <= high, got {band_hz!r}")
    freq = np.exp(rng.uniform(np.log(lo), np.log(hi), (n_channels, n_components)))
    phase = rng.uniform(0.0, 2.0 * np.pi, (n_channels, n_components))
    amp = np.broadcast_to(np.asarray(rms, float) * np.sqrt(2.0 / n_components), (n_channels,))[
        :, None
    ]
    return np.repeat(amp, n_components, axis=1), freq, phase


def angle_excursion(
    tau_s: FloatArray,
    length_s: float,
    ramp_s: float,
    amp: FloatArray,
    freq_hz: FloatArray,
    phase_rad: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Attitude deviation ``Rz(ψ)Ry(θ)Rx(φ)`` and its body rate from windowed sinusoids.

    Channels of ``amp`` etc. are (roll, pitch, yaw). Returns ((N, 3, 3), (N, 3)).
    """
    ang, ang1, _ = windowed_excursion(tau_s, length_s, ramp_s, amp, freq_hz, phase_rad)
    mat = euler_zyx_matrix(ang[:, 0], ang[:, 1], ang[:, 2])
    rate = euler_zyx_body_rate(ang[:, 0], ang[:, 1], ang1[:, 0], ang1[:, 1], ang1[:, 2])
    return mat, rate


def displacement_accel(
    tau_s: FloatArray,
    length_s: float,
    ramp_s: float,
    accel_amp: FloatArray,
    freq_hz: FloatArray,
    phase_rad: FloatArray,
) -> FloatArray:
    """(N, C) acceleration of a windowed sinusoidal displacement.

    The displacement amplitudes are ``accel_amp / (2πf)²`` so the plateau
    acceleration has amplitude ``accel_amp``; differentiating the windowed
    displacement keeps velocity and position consistent at the fades.
    """
    disp_amp = np.asarray(accel_amp) / (2.0 * np.pi * np.asarray(freq_hz)) ** 2
    return windowed_excursion(tau_s, length_s, ramp_s, disp_amp, freq_hz, phase_rad)[2]


# --- orientation schemes ------------------------------------------------------


def attitude_with_up(up_b: ArrayLike, heading_rad: float = 0.0) -> FloatArray:
    """(3, 3) ``mat_nb`` whose body-frame up direction is ``up_b``.

    The smallest rotation taking ``up_b`` to the navigation up axis, followed by
    a rotation of ``heading_rad`` about the up axis.
    """
    from scipy.spatial.transform import Rotation

    u = np.asarray(up_b, float)
    u = u / np.linalg.norm(u)
    axis = np.cross(u, _UP_N)
    sin_a = np.linalg.norm(axis)
    cos_a = float(u @ _UP_N)
    if sin_a < 1e-12:
        base = np.eye(3) if cos_a > 0 else Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix()
    else:
        base = Rotation.from_rotvec(axis / sin_a * np.arctan2(sin_a, cos_a)).as_matrix()
    heading: FloatArray = Rotation.from_rotvec([0.0, 0.0, heading_rad]).as_matrix()
    return heading @ base


# An order of the 18 directions (indices into the construction below) found by
# a seeded random search over paths from +z: consecutive directions are 45° to
# 90° apart, and the first n positions, for every n from 9 to 18, give M1's
# regressor matrix H a condition number of at most 4.3 (2.45 for all 18), so a
# session cut short after nine positions is still well posed.
_EIGHTEEN_ORDER = (4, 9, 1, 2, 15, 17, 7, 10, 11, 5, 8, 6, 14, 12, 16, 0, 3, 13)


def eighteen_position_up_vectors() -> FloatArray:
    """(18, 3) body-frame up directions: the 6 axis-up/down and the 12 between two axes at 45°.

    Ordered as a path from +z in which consecutive directions are 45° to 90°
    apart, so every turn is a hand-sized tilt, and every prefix of at least
    nine positions is well conditioned for the nine parameters.
    """
    dirs = [s * e for e in np.eye(3) for s in (1.0, -1.0)]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        for si in (1.0, -1.0):
            for sj in (1.0, -1.0):
                v = np.zeros(3)
                v[i], v[j] = si, sj
                dirs.append(v / np.sqrt(2.0))
    return np.array(dirs)[list(_EIGHTEEN_ORDER)]


def tilt_sequence(up_b: FloatArray, heading_rad: float = 0.0) -> FloatArray:
    """(P, 3, 3) attitudes with body-frame up directions ``up_b`` (P, 3), reached by tilts.

    The first attitude is :func:`attitude_with_up` of ``up_b[0]``; each next
    one turns the previous about the horizontal body axis ``u_next × u_prev``
    by the angle between them, as a person tips a box onto its next face.
    """
    from scipy.spatial.transform import Rotation

    u = np.asarray(up_b, float)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    out = [attitude_with_up(u[0], heading_rad)]
    for prev, nxt in itertools.pairwise(u):
        axis = np.cross(nxt, prev)
        sin_a = np.linalg.norm(axis)
        if sin_a < 1e-12 and prev @ nxt < 0:
            raise ValueError(
                "consecutive up directions must not be opposite (the tilt axis is undefined)"
            )
        rot = np.zeros(3) if sin_a < 1e-12 else axis / sin_a * np.arctan2(sin_a, prev @ nxt)
        out.append(out[-1] @ Rotation.from_rotvec(rot).as_matrix())
    return np.array(out)


def eighteen_position_attitudes(heading_rad: float = 0.0) -> FloatArray:
    """(18, 3, 3) attitudes of the 18-position scheme, reached by tilts of 45° to 90°.

    See :func:`eighteen_position_up_vectors` and :func:`tilt_sequence`;
    ``heading_rad`` is the heading of the first position.
    """
    return tilt_sequence(eighteen_position_up_vectors(), heading_rad)


def random_attitudes(n: int, rng: np.random.Generator) -> FloatArray:
    """(n, 3, 3) attitudes drawn uniformly over the rotation group."""
    from scipy.spatial.transform import Rotation

    if n < 1:
        raise ValueError(f"need at least one attitude, got n={n}")
    mats: FloatArray = Rotation.random(n, random_state=rng).as_matrix()
    return mats.reshape(n, 3, 3)


def multi_position_profile(
    attitudes_nb: FloatArray,
    *,
    static_s: float | FloatArray = 20.0,
    transition_s: float | FloatArray = 4.0,
    first_static_s: float | None = None,
) -> MotionProfile:
    """Hold each attitude of ``attitudes_nb`` (P, 3, 3) in turn, with minimum-jerk turns between.

    ``static_s`` is one length for every position or (P,) lengths, s;
    ``transition_s`` one turn length or (P − 1,) lengths, s (e.g. the measured
    ones of a real session). ``first_static_s`` overrides the first position's
    length (a long initial rest is common, e.g. for a gyro bias estimate).
    """
    att = np.asarray(attitudes_nb, float)
    if att.ndim != 3 or att.shape[1:] != (3, 3) or att.shape[0] < 1:
        raise ValueError(f"attitudes_nb must have shape (P, 3, 3), got {att.shape}")
    p = att.shape[0]
    try:
        holds = np.broadcast_to(np.asarray(static_s, float), (p,)).copy()
        turns = np.broadcast_to(np.asarray(transition_s, float), (p - 1,))
    except ValueError:
        raise ValueError(
            f"static_s must be a number or {p} lengths and transition_s a number or {p - 1}, "
            f"got shapes {np.shape(static_s)} and {np.shape(transition_s)}"
        ) from None
    if first_static_s is not None:
        holds[0] = first_static_s
    segments: list[Segment] = [Hold(float(holds[0]))]
    for m, turn_s, hold_s in zip(att[1:], turns, holds[1:], strict=True):
        segments += [Turn(m, float(turn_s)), Hold(float(hold_s))]
    return MotionProfile(att[0], tuple(segments))


def static_profile(duration_s: float, mat_nb: FloatArray | None = None) -> MotionProfile:
    """One long static interval in ``mat_nb`` (default: body axes = ENU)."""
    return MotionProfile(np.eye(3) if mat_nb is None else mat_nb, (Hold(duration_s),))


def flight_profile(fly: Fly, *, rest_s: float = 10.0, heading_rad: float = 0.0) -> MotionProfile:
    """Rest level, fly the segment ``fly``, rest again."""
    return MotionProfile(
        attitude_with_up([0.0, 0.0, 1.0], heading_rad), (Hold(rest_s), fly, Hold(rest_s))
    )


# --- sampling -------------------------------------------------------------------


def _segment_counts(profile: MotionProfile, rate_hz: float) -> IntArray:
    return np.array([max(1, round(s.duration_s * rate_hz)) for s in profile.segments])


def build_motion(
    profile: MotionProfile, rate_hz: float, rng: np.random.Generator, *, t0_s: float = 0.0
) -> Motion:
    """Sample ``profile`` at ``rate_hz``; each segment lasts a whole number of samples.

    Sample ``k`` is at ``t0_s + k / rate_hz``. A segment's end attitude is the
    next segment's start attitude.
    """
    from scipy.spatial.transform import Rotation

    if not np.isfinite(rate_hz) or rate_hz <= 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
    dt = 1.0 / rate_hz
    counts = _segment_counts(profile, rate_hz)
    n = int(counts.sum())
    mat = np.empty((n, 3, 3))
    rate = np.zeros((n, 3))
    acc = np.zeros((n, 3))
    static = np.zeros(n, bool)
    pos = np.full(n, -1, int)
    current = np.array(profile.initial_mat_nb)
    start = 0
    n_hold = 0
    for seg, cnt in zip(profile.segments, counts, strict=True):
        sl = slice(start, start + cnt)
        tau = np.arange(cnt) * dt
        length = cnt * dt
        if isinstance(seg, Hold):
            mat[sl] = current
            static[sl] = True
            pos[sl] = n_hold
            n_hold += 1
        elif isinstance(seg, Turn):
            target = np.array(seg.to_mat_nb)
            rotvec = Rotation.from_matrix(current.T @ target).as_rotvec()
            theta = np.linalg.norm(rotvec)
            axis = rotvec / theta if theta > 0 else np.array([0.0, 0.0, 1.0])
            s, s1, _ = min_jerk(tau / length)
            mat[sl] = current @ Rotation.from_rotvec(np.outer(theta * s, axis)).as_matrix()
            rate[sl] = np.outer(theta * s1 / length, axis)
            current = target
        elif isinstance(seg, Spin):
            assert seg.end_rate_rps is not None  # Spin.__post_init__ sets it
            axis = np.array(seg.axis_b)
            accel = (seg.end_rate_rps - seg.rate_rps) / length
            angle = seg.rate_rps * tau + 0.5 * accel * tau**2
            mat[sl] = current @ Rotation.from_rotvec(np.outer(angle, axis)).as_matrix()
            rate[sl] = np.outer(seg.rate_rps + accel * tau, axis)
            current = (
                current
                @ Rotation.from_rotvec(
                    0.5 * (seg.rate_rps + seg.end_rate_rps) * length * axis
                ).as_matrix()
            )
        else:
            amp, freq, phase = random_sinusoids(
                rng,
                3,
                seg.n_components,
                [seg.attitude_amp_rad] * 2 + [seg.yaw_amp_rad],
                seg.maneuver_hz,
            )
            vamp, vfreq, vphase = random_sinusoids(
                rng, 3, seg.n_components, seg.vibration_rad, seg.vibration_hz
            )
            dev, rate[sl] = angle_excursion(
                tau,
                length,
                seg.ramp_s,
                np.hstack([amp, vamp]),
                np.hstack([freq, vfreq]),
                np.hstack([phase, vphase]),
            )
            mat[sl] = current @ dev
            aamp, afreq, aphase = random_sinusoids(
                rng, 3, seg.n_components, seg.accel_amp_mps2, seg.maneuver_hz
            )
            bamp, bfreq, bphase = random_sinusoids(
                rng, 3, seg.n_components, seg.vibration_mps2, seg.vibration_hz
            )
            acc[sl] = displacement_accel(
                tau,
                length,
                seg.ramp_s,
                np.hstack([aamp, bamp]),
                np.hstack([afreq, bfreq]),
                np.hstack([aphase, bphase]),
            )
        start += cnt
    return Motion(t0_s + np.arange(n, dtype=np.float64) * dt, mat, rate, acc, static, pos)
