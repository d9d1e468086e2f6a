"""Hand-built IMU sessions for the static-detector and position tests (plain numpy).

A scene is a list of segments played in order from a starting specific-force
direction:

* :class:`Rest` — the unit is static; output = g·(current up direction) + noise;
* :class:`Rotate` — a turn about a fixed body axis (None: about the current up
  direction, a heading change) with a minimum-jerk angle profile (rate zero at
  both ends, as by hand), or at a constant rate; the gravity direction in body
  axes turns the other way (``f_b(t) = R(θ(t))ᵀ f_b(0)``);
* :class:`Bump` — a knock: vibration of both triads, no net rotation;
* :class:`Gap` — no samples for a while (the time stamps jump).

Noise is white, or AR(1) with coefficient ``phi`` (same marginal standard deviation).
The truth carries, per sample, whether the unit was at rest and the index of
the rest segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from estimators.session import ImuSession

G_MPS2 = 9.80665


@dataclass(frozen=True)
class Rest:
    duration_s: float


@dataclass(frozen=True)
class Rotate:
    duration_s: float
    axis_b: tuple | None
    angle_deg: float
    constant_rate: bool = False


@dataclass(frozen=True)
class Bump:
    duration_s: float
    accel_sd_mps2: float = 2.0
    gyro_sd_rps: float = 0.05


@dataclass(frozen=True)
class Gap:
    duration_s: float


@dataclass(frozen=True)
class Scene:
    session: ImuSession
    rest: np.ndarray  # (N,) bool: sample inside a Rest segment
    rest_index: np.ndarray  # (N,) index of the Rest segment, -1 elsewhere
    up_b: np.ndarray  # (N, 3) true unit specific-force direction


def _noise(rng: np.random.Generator, n: int, sd: float, phi: float) -> np.ndarray:
    white = rng.standard_normal((n, 3))
    if phi == 0.0:
        return sd * white
    return sd * np.sqrt(1.0 - phi * phi) * lfilter([1.0], [1.0, -phi], white, axis=0)


def build_scene(
    segments,
    *,
    rng: np.random.Generator,
    rate_hz: float = 100.0,
    up0_b=(0.0, 0.0, 1.0),
    accel_noise_mps2: float = 0.01,
    gyro_noise_rps: float = 0.001,
    phi: float = 0.0,
    temp_c: float | None = None,
) -> Scene:
    dt = 1.0 / rate_hz
    up = np.asarray(up0_b, float) / np.linalg.norm(up0_b)
    t_parts, f_parts, w_parts, rest_parts, idx_parts, extra_accel = [], [], [], [], [], []
    t_next = 0.0
    k_rest = 0
    for seg in segments:
        n = round(seg.duration_s * rate_hz)
        if isinstance(seg, Gap):
            t_next += seg.duration_s
            continue
        t = t_next + dt * np.arange(n)
        t_next = t[-1] + dt
        if isinstance(seg, Rotate):
            axis = (
                up
                if seg.axis_b is None
                else np.asarray(seg.axis_b, float) / np.linalg.norm(seg.axis_b)
            )
            big = np.radians(seg.angle_deg)
            tau = (np.arange(n) + 1) / n
            if seg.constant_rate:
                theta, rate = big * tau, np.full(n, big / seg.duration_s)
            else:
                theta = big * (10 * tau**3 - 15 * tau**4 + 6 * tau**5)
                rate = big / seg.duration_s * 30 * tau**2 * (1 - tau) ** 2
            f = Rotation.from_rotvec(theta[:, None] * axis).inv().apply(up)
            w = rate[:, None] * axis
            up = f[-1]
        else:
            f = np.broadcast_to(up, (n, 3)).copy()
            w = np.zeros((n, 3))
        bump = np.zeros((n, 3))
        if isinstance(seg, Bump):
            bump = seg.accel_sd_mps2 * rng.standard_normal((n, 3))
            w = seg.gyro_sd_rps * rng.standard_normal((n, 3))
        is_rest = isinstance(seg, Rest)
        t_parts.append(t)
        f_parts.append(f)
        w_parts.append(w)
        extra_accel.append(bump)
        rest_parts.append(np.full(n, is_rest))
        idx_parts.append(np.full(n, k_rest if is_rest else -1))
        k_rest += int(is_rest)
    t = np.concatenate(t_parts)
    f = np.concatenate(f_parts)
    n_all = t.size
    accel = G_MPS2 * f + np.concatenate(extra_accel) + _noise(rng, n_all, accel_noise_mps2, phi)
    gyro = np.concatenate(w_parts) + _noise(rng, n_all, gyro_noise_rps, phi)
    temp = None if temp_c is None else temp_c + 0.1 * rng.standard_normal(n_all)
    return Scene(
        ImuSession(t, accel, gyro, temp), np.concatenate(rest_parts), np.concatenate(idx_parts), f
    )


def tumble(n_rest: int, *, rest_s: float, turn_s: float = 2.0, rng: np.random.Generator) -> list:
    """``n_rest`` rests joined by turns of 40–140° about random body axes."""
    segs = [Rest(rest_s)]
    for _ in range(n_rest - 1):
        segs += [
            Rotate(turn_s, tuple(rng.standard_normal(3)), float(rng.uniform(40.0, 140.0))),
            Rest(rest_s),
        ]
    return segs


def count_compositions(monkeypatch) -> list[int]:
    """The samples of each composition a :class:`RotationIntegrator` runs from now on (its Python
    step per sample), appended as they run."""
    from estimators.static_detector import RotationIntegrator

    composed: list[int] = []
    compose = RotationIntegrator._compose

    def counting(self, dws, dxs, dys, dzs):
        dxs = list(dxs)
        composed.append(len(dxs))
        compose(self, dws, dxs, dys, dzs)

    monkeypatch.setattr(RotationIntegrator, "_compose", counting)
    return composed
