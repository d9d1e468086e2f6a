"""Conventions shared by every estimator: units, frames, constants, error model.

Units and frames
----------------
* SI inside: time ``t_s`` in seconds, specific force ``accel_mps2`` in m/s²,
  angular rate ``gyro_rps`` in rad/s, temperature ``temp_c`` in °C (the one
  non-SI quantity, because every datasheet and passport states it so).
* Arrays of triad samples have shape ``(N, 3)``; columns are the *sensor* axes
  x, y, z of the body frame (right-handed; M5 uses its own axis naming and says
  so in its module).
* The accelerometer measures specific force: a static unit reads +g along the
  axis that points *up*.
* Normalized quantities (methods.md M1) are dimensionless: ``ã = a / g`` and
  ``ω̃ = ω / Ω``; a triad's *reference* is ``g`` (local gravity magnitude) for the
  accelerometers and ``Ω`` (Earth rate) for the gyros.

Error model of a triad (methods.md M1, exact form)
---------------------------------------------------
For a static unit with true unit reference direction ``u`` (``|u| = 1``, in the
body frame) the normalized output of sensor ``i`` is::

    ã_i = (1 + e_i) · (s_i · u) + b_i + n_i

* ``b_i`` normalized zero signal (bias / reference),
* ``e_i`` relative scale-factor error,
* ``s_i`` the unit vector of sensor ``i``'s sensitive axis. With the six small
  non-orthogonality angles ``δ_ij`` (sensor axis ``i`` turned about body axis
  ``j``) the sensitive axes are, before normalization to unit length::

      s_x ∝ [ 1,     δ_xz, −δ_xy]
      s_y ∝ [−δ_yz,  1,     δ_yx]
      s_z ∝ [ δ_zy, −δ_zx,  1   ]

Only the norm of ``u`` is known, so a rotation of all three axes together is not
observable; what is observable are the cosines between the sensitive axes. This
project *defines* the three non-orthogonality parameters exactly as those
cosines::

    δ1 = s_x · s_y   ( = δ_xz − δ_yz to first order)
    δ2 = s_x · s_z   ( = δ_zy − δ_xy to first order)
    δ3 = s_y · s_z   ( = δ_yx − δ_zx to first order)

which are the paper's differences to first order and are exact targets for the
refined (nonlinear) estimator. With ``A`` the matrix whose row ``i`` is
``(1 + e_i) s_iᵀ``, the exact static relation is
``(ã − b)ᵀ (A Aᵀ)⁻¹ (ã − b) = 1`` (an ellipsoid), whose first-order expansion is
the scalar calibration equation of M1.

Parameter vector order (everywhere: estimates, passports, predicates F1…F9)::

    [bx, by, bz, ex, ey, ez, d1, d2, d3]
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np

from estimators._typing import FloatArray

EARTH_RATE_RPS = 7.292115e-5
"""Earth rotation rate Ω (WGS-84), rad/s."""

STANDARD_GRAVITY_MPS2 = 9.80665
"""Conventional standard gravity g_n, m/s² (a unit, not a local value)."""

MPS2_PER_MG = 1.0e-3 * STANDARD_GRAVITY_MPS2
"""One milli-g (datasheet unit of accelerometer bias and noise) in m/s²."""

RPS_PER_DPH = np.pi / 180.0 / 3600.0
"""One degree per hour (datasheet unit of gyro bias) in rad/s."""

# WGS-84 constants for Somigliana's normal gravity and the free-air correction.
_WGS84_GAMMA_E = 9.7803253359  # normal gravity at the equator, m/s²
_WGS84_K = 1.931852652458e-3  # Somigliana constant
_WGS84_E2 = 6.69437999014e-3  # first eccentricity squared
_WGS84_A = 6378137.0  # semi-major axis, m
_WGS84_F = 1.0 / 298.257223563
_WGS84_M = 0.00344978650684  # ω²a²b/GM


class Triad(StrEnum):
    """A sensor triad of the IMU."""

    ACCEL = "accel"
    GYRO = "gyro"


class Grade(StrEnum):
    """Sensor grade of an IMU: selects the passport's tolerance floors and the simulator's presets."""

    MEMS = "mems"
    TACTICAL = "tactical"
    NAVIGATION = "navigation"


class Cause(StrEnum):
    """What a failed predicate F1…F9 says is wrong (methods.md M1)."""

    ZERO_SIGNAL = "zero_signal"
    SCALE_FACTOR = "scale_factor"
    NON_ORTHOGONALITY = "non_orthogonality"


AXES = ("x", "y", "z")

PARAM_NAMES = ("bx", "by", "bz", "ex", "ey", "ez", "d1", "d2", "d3")
"""Order of the nine error parameters of a triad."""

PARAM_CAUSE = (Cause.ZERO_SIGNAL,) * 3 + (Cause.SCALE_FACTOR,) * 3 + (Cause.NON_ORTHOGONALITY,) * 3
"""Cause named by predicate F(j+1) for parameter index j."""

PARAM_AXIS = ("x", "y", "z", "x", "y", "z", "xy", "xz", "yz")
"""Sensor axis (or axis pair, for non-orthogonality) of parameter index j."""

N_PARAMS = 9

DEFAULT_FALSE_ALARM_PROB = 1.0e-3
"""Per-triad probability α that the diagnosis (F1…F9, :mod:`estimators.diagnosis`) flags a healthy
triad, unless configured; stated here so that the chain's and the service's options, which
default to it, do not load the diagnosis."""


def normal_gravity_mps2(latitude_deg: float, height_m: float = 0.0) -> float:
    """Local gravity magnitude from the WGS-84 normal gravity field, m/s².

    Somigliana's closed formula on the ellipsoid plus the second-order free-air
    correction for the height above the ellipsoid (NIMA TR8350.2, eq. 4-1 and
    4-3). Accurate to about 1e-6 relative near the surface; local anomalies
    (up to ~1e-4 relative) are not modelled: configure a measured value when it
    matters.

    Parameters
    ----------
    latitude_deg : geodetic latitude, degrees, in [-90, 90].
    height_m : height above the ellipsoid, metres.
    """
    if not np.isfinite(latitude_deg) or abs(latitude_deg) > 90.0:
        raise ValueError(f"latitude_deg must be within [-90, 90], got {latitude_deg!r}")
    if not np.isfinite(height_m) or not -1.0e4 < height_m < 1.0e5:
        raise ValueError(f"height_m must be within (-10 km, 100 km), got {height_m!r}")
    s2 = np.sin(np.radians(latitude_deg)) ** 2
    gamma0 = _WGS84_GAMMA_E * (1.0 + _WGS84_K * s2) / np.sqrt(1.0 - _WGS84_E2 * s2)
    h = height_m
    corr = (
        1.0
        - 2.0 / _WGS84_A * (1.0 + _WGS84_F + _WGS84_M - 2.0 * _WGS84_F * s2) * h
        + 3.0 / _WGS84_A**2 * h * h
    )
    return float(gamma0 * corr)


def reference_magnitude(triad: Triad, gravity_mps2: float) -> float:
    """The scalar reference of a triad: g for accelerometers (m/s²), Ω for gyros (rad/s)."""
    return float(gravity_mps2) if Triad(triad) is Triad.ACCEL else EARTH_RATE_RPS


def sensor_axes(nonorth_rad: FloatArray) -> FloatArray:
    """Unit sensitive axes of a triad from its six non-orthogonality angles.

    Parameters
    ----------
    nonorth_rad : (6,) angles ``[δ_xy, δ_xz, δ_yx, δ_yz, δ_zx, δ_zy]``, rad
        (sensor axis ``i`` turned about body axis ``j``).

    Returns
    -------
    (3, 3) array whose row ``i`` is the unit vector ``s_i`` (body frame).
    """
    d_xy, d_xz, d_yx, d_yz, d_zx, d_zy = np.asarray(nonorth_rad, dtype=float).reshape(6)
    s = np.array(
        [
            [1.0, d_xz, -d_xy],
            [-d_yz, 1.0, d_yx],
            [d_zy, -d_zx, 1.0],
        ]
    )
    axes: FloatArray = s / np.linalg.norm(s, axis=1, keepdims=True)
    return axes


def observable_nonorth(axes: FloatArray) -> FloatArray:
    """The three observable non-orthogonality parameters ``[d1, d2, d3]`` (cosines).

    ``axes`` is the (3, 3) matrix of unit sensitive axes from :func:`sensor_axes`.
    """
    return np.array([axes[0] @ axes[1], axes[0] @ axes[2], axes[1] @ axes[2]])


def triad_matrix(scale_err: FloatArray, axes: FloatArray) -> FloatArray:
    """The (3, 3) matrix ``A`` with rows ``(1 + e_i) s_iᵀ``: ``ã = A u + b``."""
    return (1.0 + np.asarray(scale_err, dtype=float).reshape(3, 1)) * axes


def nine_params(bias_norm: FloatArray, scale_err: FloatArray, axes: FloatArray) -> FloatArray:
    """The true parameter vector ``[b, e, d]`` (order :data:`PARAM_NAMES`) of a triad."""
    return np.concatenate(
        [
            np.asarray(bias_norm, float).reshape(3),
            np.asarray(scale_err, float).reshape(3),
            observable_nonorth(axes),
        ]
    )
