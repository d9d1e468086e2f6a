"""Simulate an IMU session: true motion → sensor inputs → error chains → :class:`ImuSession`.

Physics (frames of :mod:`estimators.sim.motion`, navigation frame ENU):

* specific force ``f_b = mat_nbᵀ (a_n + [0, 0, g_true])``: a static unit reads
  ``+g`` along its up axis (:mod:`estimators.conventions`);
* gyro input ``ω_ib_b = ω_nb_b + mat_nbᵀ Ω_n`` with ``Ω_n = Ω [0, cos φ, sin φ]``
  at latitude ``φ``: a static gyro triad sees the Earth rate projected on its axes.

Neglected, because they are below a small vehicle's concern at the accuracy
this project checks: the transport rate ``v / R`` (3e-6 rad/s at 20 m/s), the
Coriolis acceleration ``2Ω×v`` (3e-3 m/s² at 20 m/s) and the change of gravity
with the vehicle's excursions. The unit rotates about its sensor point (no
lever arm) unless the spec has a :class:`Mounting`: a unit at the lever arm
``r`` (body axes) from the body point and mounted with its axes at ``mat_sb``
reads ``f_s = mat_sb (f_b + ω̇ × r + ω × (ω × r))`` and ``ω_s = mat_sb ω_ib_b``,
``ω̇`` the central difference of the sampled body rate (``np.gradient``). Two
specs differing only in their mounting, ``unit`` and the unit's own model and
faults are two IMUs on one vehicle: the motion is drawn from the same stream.

Randomness: each consumer (the motion, each effect of each triad, the faults)
draws from its own stream derived from the seed and the consumer's name, so
adding an effect does not change the noise of the others — a simulation with
and without one extra effect differs by that effect alone.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import BoolArray, FloatArray, IntArray
from estimators.conventions import (
    EARTH_RATE_RPS,
    N_PARAMS,
    Triad,
    normal_gravity_mps2,
    reference_magnitude,
)
from estimators.session import ImuSession

from .errors import NOISE_BURST_STAGE, PARAMETER_EFFECT, EffectContext, ErrorModel
from .faults import (
    PARAMETER_FAULTS,
    Fault,
    add_noise_bursts,
    apply_output_faults,
    faults_of,
    param_deltas,
)
from .motion import Motion, MotionProfile, build_motion
from .temperature import TemperatureProfile


@dataclass(frozen=True)
class Mounting:
    """A unit's place on the vehicle: lever arm ``lever_arm_b_m`` (3,) m from the body point, body
    axes, and its axes' attitude ``mat_sb`` (3, 3), sensor ← body (module docstring)."""

    lever_arm_b_m: ArrayLike = (0.0, 0.0, 0.0)
    mat_sb: ArrayLike = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    def __post_init__(self) -> None:
        r = np.asarray(self.lever_arm_b_m, dtype=float)
        m = np.asarray(self.mat_sb, dtype=float)
        if r.shape != (3,) or not np.all(np.isfinite(r)):
            raise ValueError(
                f"Mounting.lever_arm_b_m must be a finite 3-vector, got {self.lever_arm_b_m!r}"
            )
        if (
            m.shape != (3, 3)
            or not np.allclose(m @ m.T, np.eye(3), atol=1e-9)
            or np.linalg.det(m) <= 0
        ):
            raise ValueError(
                f"Mounting.mat_sb must be a (3, 3) rotation matrix, got {self.mat_sb!r}"
            )
        object.__setattr__(self, "lever_arm_b_m", tuple(r))
        object.__setattr__(self, "mat_sb", tuple(map(tuple, m)))

    def sensed(
        self, t_s: FloatArray, f_b: FloatArray, w_b: FloatArray, rate_nb_b: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """The unit's specific force and angular rate (N, 3) from the body point's (module docstring)."""
        r = np.array(self.lever_arm_b_m)
        m = np.array(self.mat_sb)
        wdot = np.gradient(rate_nb_b, t_s, axis=0) if t_s.size > 1 else np.zeros_like(rate_nb_b)
        at_r = f_b + np.cross(wdot, r) + np.cross(w_b, np.cross(w_b, r))
        return at_r @ m.T, w_b @ m.T


@dataclass(frozen=True)
class SessionSpec:
    """Everything that defines a simulated session.

    Attributes
    ----------
    profile : the true motion.
    model : the error model (both triads and the environment).
    rate_hz : sample rate, Hz.
    latitude_deg : geodetic latitude, degrees (Earth-rate direction, normal gravity).
    height_m : height above the ellipsoid, m (normal gravity).
    gravity_mps2 : the *assumed* local gravity, m/s²; None → WGS-84 normal
        gravity at latitude and height. The truth equals it unless the model has
        a ``gravity_mismatch`` effect.
    temperature : temperature profile, or None (the session then has no temperature).
    faults : injected faults.
    t0_s : time of the first sample, s.
    mounting : where the unit sits on the body and how it is turned (None: at the body point, body axes).
    unit : the name the unit's own random streams are drawn under (``""``: the streams of a single
        unit); the motion's stream does not depend on it.
    """

    profile: MotionProfile
    model: ErrorModel
    rate_hz: float = 100.0
    latitude_deg: float = 45.0
    height_m: float = 0.0
    gravity_mps2: float | None = None
    temperature: TemperatureProfile | None = None
    faults: tuple[Fault, ...] = ()
    t0_s: float = 0.0
    mounting: Mounting | None = None
    unit: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "faults", tuple(self.faults))
        for f in self.faults:
            if not isinstance(f, Fault):
                raise ValueError(f"not a Fault: {f!r}")
        if self.gravity_mps2 is not None and not (
            np.isfinite(self.gravity_mps2) and self.gravity_mps2 > 0
        ):
            raise ValueError(f"gravity_mps2 must be positive, got {self.gravity_mps2!r}")
        if not np.isfinite(self.rate_hz) or self.rate_hz <= 0:
            raise ValueError(f"rate_hz must be positive, got {self.rate_hz!r}")

    @property
    def assumed_gravity_mps2(self) -> float:
        if self.gravity_mps2 is not None:
            return float(self.gravity_mps2)
        return normal_gravity_mps2(self.latitude_deg, self.height_m)


@dataclass(frozen=True)
class Truth:
    """What really happened in a simulated session.

    Attributes
    ----------
    t_s : (N,) sample times, s.
    mat_nb : (N, 3, 3) attitude, body → ENU.
    rate_nb_b_rps : (N, 3) body rate relative to ENU, rad/s.
    rate_ib_b_rps : (N, 3) inertial body rate (the gyro input), rad/s.
    specific_force_b_mps2 : (N, 3) specific force (the accelerometer input), m/s².
    static : (N,) nominally static samples (inside scheduled positions).
    position_index : (N,) index of the scheduled position, −1 while moving.
    static_intervals_s : (K, 2) first and last sample time of each position, s.
    temp_c : (N,) true temperature, °C, or None.
    accel_params, gyro_params : (9,) true ``[b, e, d]`` per triad before any fault
        (normalized by the true reference: ``gravity_true_mps2`` and Ω).
    gravity_mps2 : the assumed local gravity, m/s².
    gravity_true_mps2 : the true local gravity, m/s².
    latitude_deg : latitude, degrees.
    faults : the injected faults.
    model : the error model used.
    """

    t_s: FloatArray
    mat_nb: FloatArray
    rate_nb_b_rps: FloatArray
    rate_ib_b_rps: FloatArray
    specific_force_b_mps2: FloatArray
    static: BoolArray
    position_index: IntArray
    static_intervals_s: FloatArray
    temp_c: FloatArray | None
    accel_params: FloatArray
    gyro_params: FloatArray
    gravity_mps2: float
    gravity_true_mps2: float
    latitude_deg: float
    faults: tuple[Fault, ...]
    model: ErrorModel

    def params(self, triad: Triad) -> FloatArray:
        """(9,) the triad's true parameters before any fault."""
        return self.accel_params if Triad(triad) is Triad.ACCEL else self.gyro_params

    def params_at(self, triad: Triad, t_s: ArrayLike) -> FloatArray:
        """(N, 9) (or (9,) for a scalar time) true parameters including parameter faults."""
        t = np.atleast_1d(np.asarray(t_s, float))
        delta = param_deltas(self.faults, triad, t)
        out = np.broadcast_to(self.params(triad), (t.size, N_PARAMS)).copy()
        if delta is not None:
            out += delta
        return out[0] if np.ndim(t_s) == 0 else out

    def reference(self, triad: Triad) -> float:
        """The true scalar reference of ``triad`` (g_true in m/s², or Ω in rad/s)."""
        return reference_magnitude(triad, self.gravity_true_mps2)


@dataclass(frozen=True)
class SimResult:
    """A simulated session and its truth."""

    session: ImuSession
    truth: Truth
    spec: SessionSpec


class RandomStreams:
    """Independent generators keyed by name, all derived from one seed."""

    def __init__(self, seed: int | np.random.Generator, prefix: tuple[str, ...] = ()):
        self.prefix = prefix
        if isinstance(seed, np.random.Generator):
            self.entropy = int(seed.integers(0, 2**63))
        elif isinstance(seed, (int, np.integer)) and seed >= 0:
            self.entropy = int(seed)
        else:
            raise ValueError(
                f"seed must be a non-negative integer or a numpy Generator, got {seed!r}"
            )

    def rng(self, *keys: str) -> np.random.Generator:
        key = tuple(zlib.crc32(k.encode()) for k in (*self.prefix, *keys))
        return np.random.default_rng(np.random.SeedSequence(self.entropy, spawn_key=key))


def earth_rate_n_rps(latitude_deg: float) -> FloatArray:
    """(3,) Earth rate in ENU at ``latitude_deg``, rad/s."""
    phi = np.radians(latitude_deg)
    return EARTH_RATE_RPS * np.array([0.0, np.cos(phi), np.sin(phi)])


def _check_fault_targets(model: ErrorModel, faults: tuple[Fault, ...]) -> None:
    for f in faults:
        if f.kind in PARAMETER_FAULTS:
            needed = PARAMETER_EFFECT[f.index // 3]
            if model.triad(f.triad).find(needed.name) is None:
                raise ValueError(
                    f"a {f.kind.value} fault in {f.target} of the {f.triad.value} triad needs a {needed.name!r} effect in its model"
                )


def _sensor_output(
    spec: SessionSpec,
    triad: Triad,
    x_b: FloatArray,
    f_b: FloatArray,
    t_s: FloatArray,
    temp_c: FloatArray | None,
    reference: float,
    streams: RandomStreams,
) -> FloatArray:
    """(N, 3) output of ``triad`` for the true input ``x_b``: its effect chain, then its faults."""
    chain = spec.model.triad(triad)
    faults = faults_of(spec.faults, triad)
    delta = param_deltas(faults, triad, t_s)
    y = x_b
    bursts_done = False
    for effect in chain.effects:
        if not bursts_done and effect.stage > NOISE_BURST_STAGE:
            y = add_noise_bursts(y, faults, t_s, streams.rng(triad.value, "noise_burst"))
            bursts_done = True
        ctx = EffectContext(
            t_s,
            spec.rate_hz,
            triad,
            reference,
            f_b,
            temp_c,
            delta,
            streams.rng(triad.value, effect.name),
        )
        y = effect.apply(y, ctx)
    if not bursts_done:
        y = add_noise_bursts(y, faults, t_s, streams.rng(triad.value, "noise_burst"))
    return apply_output_faults(y, faults, t_s)


def simulate(spec: SessionSpec, seed: int | np.random.Generator) -> SimResult:
    """Simulate ``spec``; the same seed gives identical arrays.

    Returns the :class:`~estimators.session.ImuSession` (both triads in SI,
    temperature when the spec has a profile) and the :class:`Truth`.
    """
    _check_fault_targets(spec.model, spec.faults)
    streams = RandomStreams(seed)
    motion: Motion = build_motion(spec.profile, spec.rate_hz, streams.rng("motion"), t0_s=spec.t0_s)
    for env in spec.model.environment:
        motion = env.perturb(motion, streams.rng("environment", env.name))
    g_assumed = spec.assumed_gravity_mps2
    g_true = g_assumed + spec.model.gravity_delta_mps2
    if g_true <= 0:
        raise ValueError(f"the true gravity must be positive, got {g_true!r} m/s²")
    t = motion.t_s
    mat_bn = np.swapaxes(motion.mat_nb, 1, 2)
    f_b = np.einsum("nij,nj->ni", mat_bn, motion.accel_n_mps2 + np.array([0.0, 0.0, g_true]))
    w_ib_b = motion.rate_nb_b_rps + mat_bn @ earth_rate_n_rps(spec.latitude_deg)
    if spec.mounting is not None:
        f_b, w_ib_b = spec.mounting.sensed(t, f_b, w_ib_b, motion.rate_nb_b_rps)
    temp = None if spec.temperature is None else spec.temperature.temp_c_at(t - t[0])
    unit_streams = RandomStreams(streams.entropy, ("unit", spec.unit)) if spec.unit else streams
    accel = _sensor_output(spec, Triad.ACCEL, f_b, f_b, t, temp, g_true, unit_streams)
    gyro = _sensor_output(spec, Triad.GYRO, w_ib_b, f_b, t, temp, EARTH_RATE_RPS, unit_streams)
    truth = Truth(
        t_s=t,
        mat_nb=motion.mat_nb,
        rate_nb_b_rps=motion.rate_nb_b_rps,
        rate_ib_b_rps=w_ib_b,
        specific_force_b_mps2=f_b,
        static=motion.static,
        position_index=motion.position_index,
        static_intervals_s=motion.static_intervals_s,
        temp_c=temp,
        accel_params=spec.model.accel.nine_params(g_true),
        gyro_params=spec.model.gyro.nine_params(EARTH_RATE_RPS),
        gravity_mps2=g_assumed,
        gravity_true_mps2=g_true,
        latitude_deg=spec.latitude_deg,
        faults=spec.faults,
        model=spec.model,
    )
    # The session owns its arrays: a consumer editing them must not edit the truth.
    session = ImuSession(t.copy(), accel, gyro, None if temp is None else temp.copy())
    return SimResult(session, truth, spec)
