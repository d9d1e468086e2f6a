"""A GNSS receiver's velocity for a simulated session (the thrust-axis check's other input).

The receiver reports the true velocity (ENU, the navigation frame of
:mod:`estimators.sim.motion`) at its own epochs ``t0 + k/rate``, as it was ``latency_s`` earlier
(the time its solution takes), plus white noise of ``vel_sd_mps`` per horizontal component and
``vertical_factor`` times that vertically (a receiver's vertical is the worse one). The true
velocity is the trapezoid integral of the kinematic acceleration ``mat_nb·f_b − g·ẑ``, from rest.
"""

from __future__ import annotations

import numpy as np

from estimators._typing import FloatArray

from .session import Truth


def gnss_velocity(
    truth: Truth,
    *,
    rate_hz: float,
    vel_sd_mps: float,
    latency_s: float,
    rng: np.random.Generator,
    vertical_factor: float = 1.5,
) -> tuple[FloatArray, FloatArray]:
    """(M,) epoch times, s, and (M, 3) ENU velocity, m/s, of a receiver on ``truth``'s vehicle."""
    if not (rate_hz > 0 and vel_sd_mps >= 0 and latency_s >= 0 and vertical_factor > 0):
        raise ValueError(
            f"need rate_hz > 0, vel_sd_mps >= 0, latency_s >= 0, vertical_factor > 0; got "
            f"{rate_hz!r}, {vel_sd_mps!r}, {latency_s!r}, {vertical_factor!r}"
        )
    t = truth.t_s
    accel_n = np.einsum("nij,nj->ni", truth.mat_nb, truth.specific_force_b_mps2)
    accel_n[:, 2] -= truth.gravity_true_mps2
    steps = 0.5 * (accel_n[1:] + accel_n[:-1]) * np.diff(t)[:, None]
    vel_n = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    epochs = np.arange(t[0] + latency_s, t[-1], 1.0 / rate_hz)
    true_vel = np.column_stack([np.interp(epochs - latency_s, t, vel_n[:, k]) for k in range(3)])
    sd = vel_sd_mps * np.array([1.0, 1.0, vertical_factor])
    return epochs, true_vel + sd * rng.standard_normal(true_vel.shape)
