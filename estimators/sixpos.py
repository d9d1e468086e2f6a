"""Six-position tests, g-dependent gyro bias and the rate-table scale factor (methods.md M4).

Li et al. calibrate an ADIS16355 on a three-axis table:

* **accelerometers, six positions** (each axis up, then down; 100 Hz, 1 min per
  position after a 10 min warm-up). The model of sensor ``i`` (the paper's eq. 7
  in SI units) is::

      A_i = b_i + (1 + S_i)·a_i + M_ij·a_j + M_ik·a_k + Q_i·a_i²

  with ``a = g·u`` the specific force of a static unit whose body-frame up
  direction is ``u``; ``b`` bias (m/s²), ``S`` relative scale-factor error,
  ``M`` misalignment (coupling of the other two axes, ≈ rad), ``Q`` quadratic
  term (1/(m/s²)). Five unknowns per axis, six positions: least squares, one
  residual degree of freedom per axis.
* **gyro g-dependent bias**: in the same positions, ``W_i = Bf_i + Σ_j Bg_ij·a_j``
  (+ the Earth rate). Axis ``j`` up and down give ``m1 = Bf + Bg·g`` and
  ``m2 = Bf − Bg·g``, so ``Bf = (m1 + m2)/2`` and ``Bg = (m1 − m2)/(2g)``; the
  least squares over all six positions is exactly that.
* **gyro scale factor** from a rate table stepping 20 °/s at a time to ±200 °/s:
  a straight-line fit of the gyro output against the table rate.

``g`` must be the *local* gravity (:func:`estimators.conventions.normal_gravity_mps2`):
the paper used 9.788 m/s² at Guangzhou; assuming 9.80665 instead scales every
``S`` by ``g_local/9.80665`` (about −0.19 %).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from estimators._typing import BoolArray, FloatArray
from estimators.conventions import AXES, EARTH_RATE_RPS, STANDARD_GRAVITY_MPS2, Grade, nine_params
from estimators.least_squares import LinearFit, fit_linear, linear_solver
from estimators.ninepar import SOURCE_NONE, SOURCE_STATIC_MEANS, SOURCE_TURNS
from estimators.plateaus import find_plateaus
from estimators.positions import Position, build_positions
from estimators.session import ImuSession
from estimators.static_detector import StaticDetectorConfig, StaticInterval, detect_static

if TYPE_CHECKING:
    from estimators.sim import Effect, ErrorModel, SessionSpec, TemperatureProfile, TriadErrorModel

_EffectT = TypeVar("_EffectT", bound="Effect")

ACCEL_TERM_NAMES = ("bias_mps2", "scale_error", "misalign_1", "misalign_2", "quad_per_mps2")
"""Per-axis parameter order of :class:`AccelSixPosition` (``misalign_1/2``: the other axes in x, y, z order)."""

GYRO_TERM_NAMES = ("bias_rps", "g_sens_x", "g_sens_y", "g_sens_z")
"""Per-gyro parameter order of :class:`GyroGSensitivity` (``g_sens_*`` in rad/s per m/s²)."""

MAX_FACE_TILT_RAD = np.radians(20.0)
"""A position farther than this from every axis-up/down attitude is not a six-position face."""


def _face_name(axis: int, sign: float) -> str:
    return f"{'+' if sign > 0 else '-'}{AXES[axis]} up"


def face_directions(accel_mean_mps2: FloatArray) -> FloatArray:
    """(K, 3) nominal up directions ``±e_i`` of the positions, from their mean specific force.

    Raises ValueError if a position is more than 20° from every axis-up/down
    attitude, or if one of the six faces (±x, ±y, ±z up) is missing.
    """
    a = np.asarray(accel_mean_mps2, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"accelerometer means must have shape (K, 3), got {a.shape}")
    norm = np.linalg.norm(a, axis=1)
    if np.any(norm == 0.0):
        raise ValueError("a position with zero specific force cannot be a six-position face")
    axis = np.argmax(np.abs(a), axis=1)
    sign = np.sign(a[np.arange(len(a)), axis])
    tilt = np.arccos(np.clip(np.abs(a[np.arange(len(a)), axis]) / norm, 0.0, 1.0))
    bad = np.flatnonzero(tilt > MAX_FACE_TILT_RAD)
    if bad.size:
        raise ValueError(
            f"position {int(bad[0])} is {np.degrees(tilt[bad[0]]):.0f}° from the nearest axis-up/down attitude "
            f"(six-position faces must be within {np.degrees(MAX_FACE_TILT_RAD):.0f}°)"
        )
    present = {(int(i), float(s)) for i, s in zip(axis, sign, strict=True)}
    missing = [_face_name(i, s) for i in range(3) for s in (1.0, -1.0) if (i, s) not in present]
    if missing:
        raise ValueError(
            f"the six-position test needs every axis up and down; missing: {', '.join(missing)}"
        )
    up = np.zeros_like(a)
    up[np.arange(len(a)), axis] = sign
    return up


def _weighted_fit(
    h: FloatArray, y: FloatArray, var: FloatArray | None, names: Sequence[str] | None
) -> LinearFit:
    """LS with per-equation variances ``var`` (M,) (known noise) or, if None, noise from the residuals."""
    return _weighted_solver(h, var, names)(y)


def _weighted_solver(
    h: FloatArray, var: FloatArray | None, names: Sequence[str] | None
) -> Callable[[FloatArray], LinearFit]:
    """:func:`_weighted_fit` of the design ``h`` and variances ``var`` for any ``y``, factored once
    (:func:`~estimators.least_squares.linear_solver`)."""
    if var is None:
        return linear_solver(h, names=names)
    if np.any(~(var > 0)):
        raise ValueError("every position needs a positive variance of its mean")
    s = 1.0 / np.sqrt(var)
    solve = linear_solver(h * s[:, None], sigma_y=1.0, names=names)

    def fit(y: FloatArray) -> LinearFit:
        scaled = solve(y * s)
        return LinearFit(
            values=scaled.values,
            cov=scaled.cov,
            residuals=y - h @ scaled.values,
            sigma=1.0,
            dof=scaled.dof,
        )

    return fit


def _diag_var(cov: FloatArray | None, k: int) -> FloatArray | None:
    if cov is None:
        return None
    c = np.asarray(cov, dtype=float)
    if c.shape != (k, 3, 3):
        raise ValueError(f"covariances of the means must have shape ({k}, 3, 3), got {c.shape}")
    return np.diagonal(c, axis1=1, axis2=2)


@dataclass(frozen=True)
class AccelSixPosition:
    """Six-position accelerometer calibration (M4).

    Attributes
    ----------
    gravity_mps2 : the gravity magnitude assumed, m/s².
    bias_mps2 : (3,) ``b``.
    scale_error : (3,) ``S``.
    misalignment : (3, 3) ``M`` (zero diagonal): ``M[i, j]`` couples axis ``j`` into sensor ``i``.
    quad_per_mps2 : (3,) ``Q``, 1/(m/s²).
    cov : (3, 5, 5) covariance of each axis's ``[b, S, M_ij, M_ik, Q]`` (:data:`ACCEL_TERM_NAMES`).
    residuals_mps2 : (K, 3) measured minus modelled position means.
    """

    gravity_mps2: float
    bias_mps2: FloatArray
    scale_error: FloatArray
    misalignment: FloatArray
    quad_per_mps2: FloatArray
    cov: FloatArray
    residuals_mps2: FloatArray

    @property
    def std(self) -> FloatArray:
        """(3, 5) standard deviations in the order of :data:`ACCEL_TERM_NAMES`."""
        return np.sqrt(np.diagonal(self.cov, axis1=1, axis2=2))

    @property
    def values(self) -> FloatArray:
        """(3, 5) estimates in the order of :data:`ACCEL_TERM_NAMES`."""
        others = np.array([[self.misalignment[i, j] for j in range(3) if j != i] for i in range(3)])
        return np.column_stack([self.bias_mps2, self.scale_error, others, self.quad_per_mps2])

    def nine_params(self) -> FloatArray:
        """The triad's ``[b/g, e, d]`` (conventions order), :func:`vector_to_nine` of this fit."""
        return vector_to_nine(
            self.bias_mps2, self.scale_error, self.misalignment, self.gravity_mps2
        )

    def nine_params_cov(self) -> FloatArray:
        """(9, 9) covariance of :meth:`nine_params`: ``J Σ Jᵀ`` with ``J`` the Jacobian of the
        mapping (central differences) and ``Σ`` the fit's per-axis covariances."""
        theta = self.values[:, :4].reshape(12)
        sigma = np.zeros((12, 12))
        for i in range(3):
            sigma[4 * i : 4 * i + 4, 4 * i : 4 * i + 4] = self.cov[i, :4, :4]
        step = np.maximum(np.sqrt(np.diag(sigma)), 1e-9) * 1e-3
        jac = np.zeros((9, 12))
        for m in range(12):
            d = np.zeros(12)
            d[m] = step[m]
            jac[:, m] = (self._nine_of(theta + d) - self._nine_of(theta - d)) / (2.0 * step[m])
        cov = jac @ sigma @ jac.T
        return np.asarray(0.5 * (cov + cov.T))

    def _nine_of(self, theta: FloatArray) -> FloatArray:
        v = theta.reshape(3, 4)
        mis = np.zeros((3, 3))
        for i in range(3):
            j, k = [m for m in range(3) if m != i]
            mis[i, j], mis[i, k] = v[i, 2], v[i, 3]
        return vector_to_nine(v[:, 0], v[:, 1], mis, self.gravity_mps2)

    def correct(self, accel_mps2: FloatArray) -> FloatArray:
        """(N, 3) specific force with the model inverted (quadratic and coupling by two fixed-point passes).

        ``a = (A − b − M a − Q a²) / (1 + S)``, starting from ``a = (A − b)/(1 + S)``;
        the neglected terms are of order ``(M, Q·a)²``.
        """
        meas = np.asarray(accel_mps2, dtype=float)
        a = (meas - self.bias_mps2) / (1.0 + self.scale_error)
        for _ in range(2):
            a = (meas - self.bias_mps2 - a @ self.misalignment.T - self.quad_per_mps2 * a * a) / (
                1.0 + self.scale_error
            )
        return a


def vector_to_nine(
    bias_mps2: FloatArray, scale_error: FloatArray, misalignment: FloatArray, gravity_mps2: float
) -> FloatArray:
    """The passport's nine parameters ``[b, e, d]`` of a six-position vector fit (docs/methods.md M4 → M1).

    Row ``i`` of the triad matrix is ``r_i = (1 + S_i)·e_i + Σ_j M_ij·e_j``, and M1's
    model is ``ã = A u + b`` with rows ``(1 + e_i)·s_iᵀ`` (``s_i`` unit), so exactly
    ``b_i = bias_i / g``, ``1 + e_i = |r_i|``, ``s_i = r_i / |r_i|`` and
    ``d1 = s_x·s_y``, ``d2 = s_x·s_z``, ``d3 = s_y·s_z``; to first order
    ``e_i = S_i`` and ``d1 = M_xy + M_yx`` etc. The cosines do not depend on how
    the fixture's frame is turned against the sensor's. ``Q`` has no place in the
    linear model (fit it at 0 for a passport).
    """
    rows = np.diag(1.0 + np.asarray(scale_error, dtype=float)) + np.asarray(misalignment, float)
    norms = np.linalg.norm(rows, axis=1)
    return nine_params(
        np.asarray(bias_mps2, float) / gravity_mps2, norms - 1.0, rows / norms[:, None]
    )


def six_position_accel(
    accel_mean_mps2: FloatArray,
    *,
    gravity_mps2: float,
    accel_cov_mps2: FloatArray | None = None,
    up_b: FloatArray | None = None,
    quadratic: bool = True,
) -> AccelSixPosition:
    """Scale, bias, misalignment and quadratic term of each accelerometer (M4, the paper's eq. 7).

    Parameters
    ----------
    accel_mean_mps2 : (K, 3) mean specific force of K ≥ 6 static positions, m/s².
    gravity_mps2 : *local* gravity, m/s².
    accel_cov_mps2 : (K, 3, 3) covariance of each mean, (m/s²)²; None estimates
        the noise from the residuals (needs more than six positions).
    up_b : (K, 3) body-frame up direction of each position; None takes the
        nearest ``±e_i`` (:func:`face_directions`).
    quadratic : fit ``Q``; False fixes it at 0 (the passport's linear model, methods.md M1:
        two residual degrees of freedom per axis instead of one). Its row of ``cov`` is then 0.
    """
    meas = np.asarray(accel_mean_mps2, dtype=float)
    up = face_directions(meas) if up_b is None else np.asarray(up_b, dtype=float)
    if up.shape != meas.shape:
        raise ValueError(
            f"up directions must have the shape of the means {meas.shape}, got {up.shape}"
        )
    return six_position_accel_fitter(
        up, gravity_mps2=gravity_mps2, accel_cov_mps2=accel_cov_mps2, quadratic=quadratic
    )(meas)


def six_position_accel_fitter(
    up_b: FloatArray,
    *,
    gravity_mps2: float,
    accel_cov_mps2: FloatArray | None = None,
    quadratic: bool = True,
) -> Callable[[FloatArray], AccelSixPosition]:
    """:func:`six_position_accel` of K positions whose up directions ``up_b`` (K, 3) and
    covariances are fixed, for any means (K, 3): its three designs checked and factored once
    (a Jacobian of the fit by central differences perturbs the means only). The same
    operations on the same numbers: bit for bit :func:`six_position_accel`'s result."""
    up = np.asarray(up_b, dtype=float)
    if not gravity_mps2 > 0:
        raise ValueError(f"gravity_mps2 must be positive, got {gravity_mps2!r}")
    k = up.shape[0]
    if k < 6:
        raise ValueError(f"the six-position test needs at least 6 positions, got {k}")
    var = _diag_var(accel_cov_mps2, k)
    if var is None and k < (7 if quadratic else 6):
        raise ValueError(
            "with exactly six positions the noise cannot be estimated from residuals: give the covariances of the means"
        )
    a = float(gravity_mps2) * up
    terms = 5 if quadratic else 4
    solvers = []
    for i in range(3):
        j, k2 = [m for m in range(3) if m != i]
        h = np.column_stack([np.ones(k), a[:, i], a[:, j], a[:, k2], a[:, i] ** 2])[:, :terms]
        names = [f"{n} ({AXES[i]})" for n in ACCEL_TERM_NAMES[:terms]]
        solvers.append(_weighted_solver(h, None if var is None else var[:, i], names))

    def fit(accel_mean_mps2: FloatArray) -> AccelSixPosition:
        meas = np.asarray(accel_mean_mps2, dtype=float)
        if meas.shape != up.shape:
            raise ValueError(
                f"up directions must have the shape of the means {meas.shape}, got {up.shape}"
            )
        values = np.zeros((3, 5))
        cov = np.zeros((3, 5, 5))
        resid = np.zeros((k, 3))
        for i, solve in enumerate(solvers):
            axis_fit = solve(meas[:, i] - a[:, i])
            values[i, :terms], cov[i, :terms, :terms] = axis_fit.values, axis_fit.cov
            resid[:, i] = axis_fit.residuals
        mis = np.zeros((3, 3))
        for i in range(3):
            j, k2 = [m for m in range(3) if m != i]
            mis[i, j], mis[i, k2] = values[i, 2], values[i, 3]
        return AccelSixPosition(
            gravity_mps2=float(gravity_mps2),
            bias_mps2=values[:, 0],
            scale_error=values[:, 1],
            misalignment=mis,
            quad_per_mps2=values[:, 4],
            cov=cov,
            residuals_mps2=resid,
        )

    return fit


@dataclass(frozen=True)
class GyroGSensitivity:
    """g-independent and g-dependent gyro bias (M4).

    Attributes
    ----------
    bias_rps : (3,) ``Bf``, rad/s.
    g_sensitivity : (3, 3) ``Bg[i, j]``: gyro ``i`` per m/s² along body axis ``j``, rad/s per m/s².
    cov : (3, 4, 4) covariance of each gyro's ``[Bf, Bg_x, Bg_y, Bg_z]``.
    earth_rate_removed : whether the vertical Earth-rate component was subtracted.
    residuals_rps : (K, 3).
    """

    bias_rps: FloatArray
    g_sensitivity: FloatArray
    cov: FloatArray
    earth_rate_removed: bool
    residuals_rps: FloatArray

    @property
    def std(self) -> FloatArray:
        """(3, 4) standard deviations in the order of :data:`GYRO_TERM_NAMES`."""
        return np.sqrt(np.diagonal(self.cov, axis1=1, axis2=2))


def gyro_g_sensitivity(
    gyro_mean_rps: FloatArray,
    up_b: FloatArray,
    *,
    gravity_mps2: float,
    gyro_cov_rps: FloatArray | None = None,
    latitude_deg: float | None = None,
    earth_rate_b_rps: FloatArray | None = None,
) -> GyroGSensitivity:
    """``Bf`` and ``Bg`` of each gyro from the six positions (M4: ``W = Bf + Bg·a``).

    The static gyro also reads the Earth rate. Its vertical component
    ``Ω·sin φ`` projects on the up direction ``u`` and flips with it, so it
    would enter ``Bg`` as ``Ω sin φ / g`` (about 5e-6 °/s per m/s² at 45°):
    with ``latitude_deg`` it is subtracted. The horizontal component
    (``Ω cos φ``, 0.004 °/s at mid latitudes) depends on the heading of each
    position; when the fixture's headings are known pass the whole Earth rate
    in body axes per position as ``earth_rate_b_rps`` instead, otherwise it
    stays in ``Bf``, ``Bg`` and the residuals (far below a MEMS gyro's bias).

    Parameters
    ----------
    gyro_mean_rps : (K, 3) mean gyro outputs of the positions, rad/s.
    up_b : (K, 3) body-frame up directions (e.g. from :func:`face_directions`).
    gravity_mps2 : local gravity, m/s².
    gyro_cov_rps : (K, 3, 3) covariance of the means; None estimates the noise
        from the residuals.
    latitude_deg : geodetic latitude, degrees, or None.
    earth_rate_b_rps : (K, 3) Earth rate in body axes per position, rad/s, or None.
    """
    w = np.asarray(gyro_mean_rps, dtype=float)
    up = np.asarray(up_b, dtype=float)
    if w.ndim != 2 or w.shape[1] != 3 or up.shape != w.shape:
        raise ValueError(
            f"gyro means and up directions must both have shape (K, 3), got {w.shape} and {up.shape}"
        )
    if latitude_deg is not None and earth_rate_b_rps is not None:
        raise ValueError(
            "give the latitude (vertical Earth rate) or the full Earth rate per position, not both"
        )
    k = w.shape[0]
    var = _diag_var(gyro_cov_rps, k)
    if var is None and k < 5:
        raise ValueError(
            f"estimating Bf and Bg with the noise from residuals needs at least 5 positions, got {k}"
        )
    if latitude_deg is not None:
        w = w - EARTH_RATE_RPS * np.sin(np.radians(latitude_deg)) * up
    if earth_rate_b_rps is not None:
        er = np.asarray(earth_rate_b_rps, dtype=float)
        if er.shape != w.shape:
            raise ValueError(f"earth_rate_b_rps must have shape {w.shape}, got {er.shape}")
        w = w - er
    a = float(gravity_mps2) * up
    h = np.column_stack([np.ones(k), a])
    values = np.zeros((3, 4))
    cov = np.zeros((3, 4, 4))
    resid = np.zeros((k, 3))
    for i in range(3):
        names = [f"{n} (gyro {AXES[i]})" for n in GYRO_TERM_NAMES]
        fit = _weighted_fit(h, w[:, i], None if var is None else var[:, i], names)
        values[i], cov[i], resid[:, i] = fit.values, fit.cov, fit.residuals
    return GyroGSensitivity(
        bias_rps=values[:, 0],
        g_sensitivity=values[:, 1:],
        cov=cov,
        earth_rate_removed=latitude_deg is not None or earth_rate_b_rps is not None,
        residuals_rps=resid,
    )


def paper_rate_profile_rps(*, max_dps: float = 200.0, step_dps: float = 20.0) -> FloatArray:
    """Table rates in time order, rad/s: from rest up in steps to ``+max``, then down to ``−max`` (M4).

    ``0, 20, …, 200, 180, …, −200`` °/s for the defaults.
    """
    if not (step_dps > 0 and max_dps >= step_dps):
        raise ValueError(f"need 0 < step_dps <= max_dps, got step {step_dps!r}, max {max_dps!r}")
    n = round(max_dps / step_dps)
    up = np.arange(0, n + 1) * step_dps
    down = np.arange(n - 1, -n - 1, -1) * step_dps
    rates_rps: FloatArray = np.radians(np.concatenate([up, down]))
    return rates_rps


@dataclass(frozen=True)
class RateTableFit:
    """Straight-line fit of one gyro axis against the table rate (M4).

    Attributes
    ----------
    axis : the gyro axis on the table axis (0, 1, 2).
    scale_error : ``S`` of ``W = bias + (1 + S)·ω``.
    bias_rps : intercept, rad/s.
    cov : (2, 2) covariance of ``[bias, S]``.
    cross_coupling : (3,) slope of every gyro against the table rate (the tested axis's own entry is ``1 + S``).
    residuals_rps : (K,) of the tested axis.
    nonlinearity : largest |residual| over the largest |table rate| (the data-sheet figure).
    table_rate_rps : (K,) the rates used.
    """

    axis: int
    scale_error: float
    bias_rps: float
    cov: FloatArray
    cross_coupling: FloatArray
    residuals_rps: FloatArray
    nonlinearity: float
    table_rate_rps: FloatArray

    @property
    def scale_error_std(self) -> float:
        return float(np.sqrt(self.cov[1, 1]))


def rate_table_fit(
    table_rate_rps: FloatArray,
    gyro_mean_rps: FloatArray,
    *,
    axis: int,
    gyro_var_rps: FloatArray | None = None,
) -> RateTableFit:
    """Scale factor of gyro ``axis`` by a linear fit over the rate steps (M4).

    Parameters
    ----------
    table_rate_rps : (K,) table rates, rad/s (at least three distinct, some non-zero).
    gyro_mean_rps : (K, 3) mean gyro output on each step, rad/s.
    axis : the gyro axis aligned with the table axis.
    gyro_var_rps : (K,) variance of the tested axis's means, (rad/s)²; None
        estimates the noise from the residuals.
    """
    r = np.asarray(table_rate_rps, dtype=float)
    w = np.asarray(gyro_mean_rps, dtype=float)
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    if r.ndim != 1 or w.shape != (r.size, 3):
        raise ValueError(
            f"need table rates (K,) and gyro means (K, 3), got {r.shape} and {w.shape}"
        )
    distinct = np.unique(np.round(r, 9)).size
    if distinct < 3:
        raise ValueError(
            f"the rate-table fit needs at least 3 different table rates, got {distinct}"
        )
    h = np.column_stack([np.ones(r.size), r])
    fit = _weighted_fit(
        h,
        w[:, axis] - r,
        None if gyro_var_rps is None else np.asarray(gyro_var_rps, float),
        ("bias", "scale factor"),
    )
    cross = np.array(
        [fit_linear(h, w[:, i]).values[1] if i != axis else 1.0 + fit.values[1] for i in range(3)]
    )
    return RateTableFit(
        axis=int(axis),
        scale_error=float(fit.values[1]),
        bias_rps=float(fit.values[0]),
        cov=fit.cov,
        cross_coupling=cross,
        residuals_rps=fit.residuals,
        nonlinearity=float(np.max(np.abs(fit.residuals)) / np.max(np.abs(r))),
        table_rate_rps=r,
    )


@dataclass(frozen=True)
class RateSteps:
    """The rate steps found in a record: slices, mean (K, 3) and variance of the mean (K, 3) per step."""

    slices: tuple[slice, ...]
    gyro_mean_rps: FloatArray
    gyro_var_rps: FloatArray


def find_rate_steps(
    t_s: FloatArray,
    gyro_rps: FloatArray,
    *,
    axis: int,
    profile_rps: FloatArray,
    min_hold_s: float = 5.0,
) -> RateSteps:
    """The constant-rate steps of a rate-table record, matched in time order to ``profile_rps``.

    The steps are the plateaus of gyro ``axis`` (:func:`estimators.plateaus.find_plateaus`,
    smallest level change: half the smallest change between consecutive profile
    rates); their number must equal the profile's length. Variances of the
    means assume white noise (sample variance / n).
    """
    t = np.asarray(t_s, dtype=float)
    g = np.asarray(gyro_rps, dtype=float)
    prof = np.asarray(profile_rps, dtype=float)
    if g.shape != (t.size, 3):
        raise ValueError(f"gyro samples must have shape ({t.size}, 3), got {g.shape}")
    if prof.size < 3:
        raise ValueError(f"a rate profile needs at least 3 steps, got {prof.size}")
    step = float(np.min(np.abs(np.diff(prof))))
    if not step > 0:
        raise ValueError("consecutive profile rates must differ")
    slices = find_plateaus(t, g[:, axis], min_step=0.5 * step, min_duration_s=min_hold_s)
    if len(slices) != prof.size:
        raise ValueError(
            f"found {len(slices)} constant-rate steps of gyro {AXES[axis]} lasting at least {min_hold_s:g} s, "
            f"but the profile has {prof.size}: check --axis, the profile and the hold time"
        )
    mean = np.array([g[s].mean(axis=0) for s in slices])
    var = np.array([g[s].var(axis=0, ddof=1) / (s.stop - s.start) for s in slices])
    return RateSteps(slices=tuple(slices), gyro_mean_rps=mean, gyro_var_rps=var)


def session_positions(session: ImuSession, *, min_static_s: float = 5.0) -> tuple[Position, ...]:
    """The static positions of a bench session (static detector with thresholds from the
    session's own noise, :meth:`StaticDetectorConfig.from_session`, then
    :func:`estimators.positions.build_positions`); intervals shorter than ``min_static_s``
    are not positions."""
    config = StaticDetectorConfig.from_session(
        session, base=StaticDetectorConfig(min_static_s=min_static_s)
    )
    return build_positions(session, detect_static(session, config=config)).positions


@dataclass(frozen=True)
class SixPositionTest:
    """Both results of one six-position session (M4)."""

    accel: AccelSixPosition
    gyro: GyroGSensitivity | None
    positions: tuple[Position, ...]


def six_position_test(
    positions: Sequence[Position], *, gravity_mps2: float, latitude_deg: float | None = None
) -> SixPositionTest:
    """Accelerometer calibration and gyro ``Bf``/``Bg`` from the static positions of one test."""
    positions = tuple(positions)
    if not positions:
        raise ValueError("no static positions: the six-position test needs each axis up and down")
    mean = np.array([p.accel_mean_mps2 for p in positions])
    cov = np.array([p.accel_cov_mps2 for p in positions])
    up = face_directions(mean)
    accel = six_position_accel(mean, gravity_mps2=gravity_mps2, accel_cov_mps2=cov, up_b=up)
    gyro = None
    if positions[0].gyro_mean_rps is not None:
        gyro = gyro_g_sensitivity(
            np.array([p.gyro_mean_rps for p in positions]),
            up,
            gravity_mps2=gravity_mps2,
            gyro_cov_rps=np.array([p.gyro_cov_rps for p in positions]),
            latitude_deg=latitude_deg,
        )
    return SixPositionTest(accel=accel, gyro=gyro, positions=positions)


# --- simulated benches (estimators.sim) ---------------------------------------------------------

GUANGZHOU_LATITUDE_DEG = 23.13
GUANGZHOU_HEIGHT_M = 20.0
"""Where the paper's tests ran; normal gravity there is 9.788 m/s² (the paper's value)."""

SIX_FACES_UP_B = np.array(
    [[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0]]
)
"""Body-frame up direction of the six positions in the paper's order (x up, x down, y up, …)."""

_DEG = np.pi / 180.0


def adis_like_model(*, quantization: bool = True) -> ErrorModel:
    """A MEMS unit like the paper's ADIS16355 (:class:`estimators.sim.ErrorModel`).

    Accelerometers: sensitive axes off by ~1 mrad, a quadratic term of about
    1e-4 per m/s² (``scale_nonlinearity`` K2), scale errors 0.3–0.6 %, bias
    3–8 mg, and the MEMS grade's noise and 16-bit steps. Gyros: scale errors
    0.4–0.6 %, bias 0.1–0.3 °/s, g-sensitivity 0.01–0.05 °/s per g
    (``g_sensitivity``), noise 0.05 °/s/√Hz, the grade's steps.
    """
    from estimators.sim import (
        GRADES,
        Bias,
        ErrorModel,
        GSensitivity,
        NonOrthogonality,
        Quantization,
        ScaleFactor,
        ScaleNonlinearity,
        TriadErrorModel,
        WhiteNoise,
    )

    grade = GRADES[Grade.MEMS]
    accel = [
        NonOrthogonality((0.8e-3, -1.1e-3, 0.6e-3, 1.3e-3, -0.9e-3, 0.7e-3)),
        ScaleNonlinearity(k2_per_si=(1.2e-4, -0.8e-4, 1.5e-4)),
        ScaleFactor((3.1e-3, -4.4e-3, 5.6e-3)),
        Bias((0.03, -0.05, 0.08)),
        WhiteNoise((grade.accel.noise_density_si,) * 3),
    ]
    gyro = [
        ScaleFactor((4.0e-3, -6.0e-3, 5.0e-3)),
        Bias((0.2 * _DEG, -0.3 * _DEG, 0.1 * _DEG)),
        GSensitivity(
            np.array([[0.03, 0.01, -0.02], [-0.01, 0.05, 0.02], [0.02, -0.03, 0.04]])
            * _DEG
            / STANDARD_GRAVITY_MPS2
        ),
        WhiteNoise((0.05 * _DEG,) * 3),
    ]
    if quantization and grade.accel.quant_step_si is not None:
        accel.append(Quantization((grade.accel.quant_step_si,) * 3))
    if quantization and grade.gyro.quant_step_si is not None:
        gyro.append(Quantization((grade.gyro.quant_step_si,) * 3))
    return ErrorModel(accel=TriadErrorModel(tuple(accel)), gyro=TriadErrorModel(tuple(gyro)))


def six_position_spec(
    model: ErrorModel,
    *,
    static_s: float = 60.0,
    transition_s: float = 4.0,
    rate_hz: float = 100.0,
    latitude_deg: float = GUANGZHOU_LATITUDE_DEG,
    height_m: float = GUANGZHOU_HEIGHT_M,
    temperature: TemperatureProfile | None = None,
) -> SessionSpec:
    """The paper's six-position test as a simulator spec: each axis up then down, 1 min at 100 Hz."""
    from estimators.sim import SessionSpec, attitude_with_up, multi_position_profile

    attitudes = np.array([attitude_with_up(u) for u in SIX_FACES_UP_B])
    profile = multi_position_profile(attitudes, static_s=static_s, transition_s=transition_s)
    return SessionSpec(
        profile,
        model,
        rate_hz=rate_hz,
        latitude_deg=latitude_deg,
        height_m=height_m,
        temperature=temperature,
    )


def _effect(chain: TriadErrorModel, default: _EffectT) -> _EffectT:
    """The chain's effect of the class of ``default``, or ``default`` (its neutral value) if absent."""
    e = chain.find(type(default))
    return default if e is None else e


def quantizer_offset(chain: TriadErrorModel) -> FloatArray:
    """(3,) mean offset of averaged (dithered) quantized output: −step/2 for FLOOR, 0 for NEAREST."""
    from estimators.sim import Quantization, Rounding

    q = chain.find(Quantization)
    if q is None or q.rounding is Rounding.NEAREST:
        return np.zeros(3)
    if q.rounding is Rounding.FLOOR:
        return -0.5 * np.array(q.step_si)
    raise ValueError(
        "a truncating converter's half-step offset depends on the sign of each reading: no constant bias to state"
    )


def accel_truth(model: ErrorModel) -> FloatArray:
    """(3, 5) true six-position parameters (:data:`ACCEL_TERM_NAMES` order) of a simulator model.

    With unit sensitive axes ``s_i``, scale error ``e``, quadratic ``K2`` and
    bias ``b`` the chain gives ``A_i = b_i + (1 + e_i)(s_i·a + K2_i (s_i·a)²)``,
    so ``S_i = (1 + e_i) s_ii − 1``, ``M_ij = (1 + e_i) s_ij`` and
    ``Q_i = (1 + e_i) K2_i`` (the quadratic cross terms ``K2 s_ij² g²`` are ~1e-6 of g).
    A FLOOR quantizer makes the averaged output half a step low: that is part
    of the bias a user of the output sees, so it is in ``b``.
    """
    from estimators.sim import Bias, NonOrthogonality, ScaleFactor, ScaleNonlinearity

    chain = model.accel
    axes = _effect(chain, NonOrthogonality()).axes
    e = np.array(_effect(chain, ScaleFactor()).scale_err)
    k2 = np.array(_effect(chain, ScaleNonlinearity()).k2_per_si)
    b = np.array(_effect(chain, Bias()).bias_si) + quantizer_offset(chain)
    full = (1.0 + e)[:, None] * axes
    others = np.array([[full[i, j] for j in range(3) if j != i] for i in range(3)])
    return np.column_stack([b, np.diag(full) - 1.0, others, (1.0 + e) * k2])


def gyro_truth(model: ErrorModel) -> tuple[FloatArray, FloatArray]:
    """True ``Bf`` (3,) rad/s (with the quantizer's mean offset) and ``Bg`` (3, 3) rad/s per m/s² of a simulator model."""
    from estimators.sim import Bias, GSensitivity

    chain = model.gyro
    bias = np.array(_effect(chain, Bias()).bias_si) + quantizer_offset(chain)
    gs = np.array(_effect(chain, GSensitivity()).coef_rps_per_mps2)
    return bias, gs


def rate_table_truth(model: ErrorModel) -> FloatArray:
    """(3, 3) true slope of gyro ``i`` against a table rate about body axis ``j``: ``(1 + e_i) s_ij``."""
    from estimators.sim import NonOrthogonality, ScaleFactor

    chain = model.gyro
    axes = _effect(chain, NonOrthogonality()).axes
    e = np.array(_effect(chain, ScaleFactor()).scale_err)
    slopes: FloatArray = (1.0 + e)[:, None] * axes
    return slopes


def simulate_rate_table(
    model: ErrorModel,
    *,
    axis: int,
    profile_rps: FloatArray,
    hold_s: float = 10.0,
    ramp_s: float = 1.0,
    rate_hz: float = 100.0,
    latitude_deg: float = GUANGZHOU_LATITUDE_DEG,
    gravity_mps2: float,
    seed: int,
) -> ImuSession:
    """A rate-table record: body axis ``axis`` vertical (up) on the table axis, the table
    holding each rate of ``profile_rps`` for ``hold_s`` with linear ramps of ``ramp_s``.

    The table's motion is a sequence of :class:`estimators.sim.Spin` segments
    simulated by :func:`estimators.sim.simulate` (true inputs: table rate plus
    the Earth rate, whose horizontal part turns with the table; ``g`` along
    the vertical axis; then the model's effect chains).
    """
    from estimators.sim import MotionProfile, SessionSpec, Spin, attitude_with_up, simulate

    prof = np.asarray(profile_rps, dtype=float)
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    if prof.ndim != 1 or prof.size < 1:
        raise ValueError(
            f"profile_rps must be a non-empty 1-D array of rates, got shape {prof.shape}"
        )
    up_b = np.eye(3)[axis]
    segments = [Spin(hold_s, prof[0], up_b)]
    for a, b in itertools.pairwise(prof):
        segments += [Spin(ramp_s, a, up_b, end_rate_rps=b), Spin(hold_s, b, up_b)]
    profile = MotionProfile(attitude_with_up(up_b), tuple(segments))
    spec = SessionSpec(
        profile, model, rate_hz=rate_hz, latitude_deg=latitude_deg, gravity_mps2=gravity_mps2
    )
    return simulate(spec, seed).session


# --- the passport's nine parameters from six faces and full turns -------------------------------

FULL_TURN_RAD = 2.0 * np.pi
TURN_ANGLE_TOLERANCE = 0.1
"""A turn counts when its integrated angle is within this fraction of the stated one."""
MAX_TURN_AXIS_TILT_RAD = np.radians(15.0)
"""…and its integrated rotation vector lies within this angle of a body axis."""
TURN_MARGIN_S = 1.0
"""A turn is integrated from this far inside the rests on either side (at most half of each)."""
UNKNOWN_SIGMA = (10.0, 1.0, 1.0)
"""Standard deviation written for a parameter a method does not determine (bias, scale, cosine):
ten times the observability range, so the precision rule can never call it observable."""


def face_positions(positions: Sequence[Position]) -> tuple[Position, ...] | None:
    """The positions within :data:`MAX_FACE_TILT_RAD` of an axis-up/down attitude, or None
    unless all six faces are among them."""
    near = []
    for p in positions:
        a = p.accel_mean_mps2
        if a is None:
            continue
        norm = float(np.linalg.norm(a))
        if norm > 0.0 and np.max(np.abs(a)) / norm >= np.cos(MAX_FACE_TILT_RAD):
            near.append(p)
    if not near:
        return None
    try:
        face_directions(np.array([p.accel_mean_mps2 for p in near]))
    except ValueError:
        return None
    return tuple(near)


def six_face_session(positions: Sequence[Position]) -> tuple[Position, ...] | None:
    """The positions when every one is a face (within :data:`MAX_FACE_TILT_RAD` of an
    axis-up/down attitude) and all six faces are among them; None otherwise. Only such a session
    is the six-position vector fit's: a tilted pose beside the faces is data the vector model
    does not hold, and a fit of the faces alone can contradict it (issue 30: a hand-posed
    ten-pose session's z zero signal -0.43 m/s² from its faces, +0.34 from all its poses)."""
    faces = face_positions(positions)
    with_accel = [p for p in positions if p.accel_mean_mps2 is not None]
    return faces if faces is not None and len(faces) == len(with_accel) else None


def accel_vector_nine(
    positions: Sequence[Position], *, gravity_mps2: float
) -> tuple[FloatArray, FloatArray, int] | None:
    """The passport's nine accelerometer parameters from the six faces among ``positions``
    (linear six-position fit, :func:`vector_to_nine`), with their (9, 9) covariance and the
    number of positions used; None without all six faces."""
    faces = face_positions(positions)
    if faces is None:
        return None
    fit = six_position_accel(
        np.array([p.accel_mean_mps2 for p in faces]),
        gravity_mps2=gravity_mps2,
        accel_cov_mps2=np.array([p.accel_cov_mps2 for p in faces]),
        quadratic=False,
    )
    return fit.nine_params(), fit.nine_params_cov(), len(faces)


@dataclass(frozen=True)
class FullTurn:
    """A turn found between two static intervals (M4; the gyro calibration of Ferraris et al.).

    Attributes
    ----------
    axis : body axis turned about (0, 1, 2); sign : +1 or −1, the sense of the turn.
    t_start_s, t_end_s : the last static sample before and the first after, s.
    integral_rad : (3,) ``∫(ω − b) dt`` over the turn, ``b`` the mean rate of the rest on both sides.
    integral_var : (3,) its variance from the white noise, the uncertainty of ``b`` and the
        Earth rate turning with the unit, rad².
    """

    axis: int
    sign: float
    t_start_s: float
    t_end_s: float
    integral_rad: FloatArray
    integral_var: FloatArray

    @property
    def angle_rad(self) -> float:
        return float(np.linalg.norm(self.integral_rad))


def find_full_turns(
    session: ImuSession,
    intervals: Sequence[StaticInterval],
    *,
    turn_rad: float = FULL_TURN_RAD,
) -> tuple[FullTurn, ...]:
    """The turns of ``turn_rad`` about one body axis between consecutive static intervals.

    From :data:`TURN_MARGIN_S` before the end of one interval to as far after the
    start of the next (at most half of each) the gyro output, less the mean rate
    of the rest of both intervals, is integrated (trapezoid); the stretch
    is a turn when the angle is within :data:`TURN_ANGLE_TOLERANCE` of
    ``turn_rad`` and the rotation vector within :data:`MAX_TURN_AXIS_TILT_RAD`
    of a body axis (whose sign gives the sense). A stretch with a time gap
    (more than five sample periods) is not integrated.
    """
    if session.gyro_rps is None or not turn_rad > 0:
        return ()
    t, w = np.asarray(session.t_s, float), np.asarray(session.gyro_rps, float)
    gap = 5.0 / session.rate_hz
    turns = []
    margin = round(TURN_MARGIN_S * session.rate_hz)
    for a, b in itertools.pairwise(intervals):
        # The detector calls the first and last few samples of a turn static: integrate from
        # inside the rests, and take the zero signal from the rests beyond that.
        lo = max(a.stop - 1 - margin, (a.start + a.stop) // 2)
        hi = min(b.start + margin, (b.start + b.stop) // 2)
        tt = t[lo : hi + 1]
        rest = np.concatenate([w[a.start : lo], w[hi + 1 : b.stop]])
        # Two rest samples at least: their spread is the turn's noise (a 1 Hz session has fewer).
        if tt.size < 3 or rest.shape[0] < 2 or np.any(np.diff(tt) > gap):
            continue
        bias = rest.mean(axis=0)
        var = rest.var(axis=0, ddof=1)
        rate = w[lo : hi + 1] - bias
        integral = np.sum(0.5 * (rate[1:] + rate[:-1]) * np.diff(tt)[:, None], axis=0)
        angle = float(np.linalg.norm(integral))
        if abs(angle - turn_rad) > TURN_ANGLE_TOLERANCE * turn_rad:
            continue
        axis = int(np.argmax(np.abs(integral)))
        if abs(integral[axis]) < np.cos(MAX_TURN_AXIS_TILT_RAD) * angle:
            continue
        span = float(tt[-1] - tt[0])
        moving = float(t[b.start] - t[a.stop - 1])
        # White noise integrates to a random walk (σ²·dt per step); the bias error grows with the
        # span. The Earth rate, part of the rests' mean, turns with the unit while it moves: up to
        # Ω per second of turning across the turn axis (heading unknown), a third of it along.
        earth = np.full(3, (EARTH_RATE_RPS * moving) ** 2)
        earth[axis] /= 3.0
        integral_var = var * (span / session.rate_hz) + (var / rest.shape[0]) * span**2 + earth
        turns.append(
            FullTurn(
                axis,
                float(np.sign(integral[axis])),
                float(tt[0]),
                float(tt[-1]),
                integral,
                integral_var,
            )
        )
    return tuple(turns)


def gyro_nine_from_turns(
    turns: Sequence[FullTurn],
    positions: Sequence[Position],
    *,
    turn_rad: float = FULL_TURN_RAD,
    reference_rps: float = EARTH_RATE_RPS,
) -> tuple[FloatArray, FloatArray, BoolArray, tuple[str, ...]]:
    """The gyro triad's nine parameters from full turns and static means (docs/methods.md M4 → M1).

    A turn by ``θ`` about body axis ``j`` integrates to ``K·θ·k_j`` (``K`` the gyro
    triad matrix, rows ``(1 + e_i) s_iᵀ``), so ``K``'s column ``j`` is the mean of
    ``sign·integral/θ`` over the turns about ``j``. Then ``1 + e_i = |K_i|`` and
    ``d`` the cosines of the normalized rows (:func:`vector_to_nine`'s mapping);
    ``e_i`` needs the turn about ``i``, ``d_ij`` the turns about ``i`` and ``j``
    (first order: ``e_i = K_ii − 1``, ``d_ij = K_ij + K_ji``, which gives the
    covariance). The zero signals are the mean gyro output of the static
    positions, with the Earth rate's projection — unknown without the headings —
    counted as an error of ``Ω/√3`` per axis.

    Returns ``(params (9,), cov (9, 9), known (9,) bool, sources (9,))``, biases
    normalized by ``reference_rps``; parameters without their turns are 0 with
    :data:`UNKNOWN_SIGMA`.
    """
    means = np.array([p.gyro_mean_rps for p in positions if p.gyro_mean_rps is not None])
    covs = np.array([p.gyro_cov_rps for p in positions if p.gyro_cov_rps is not None])
    k_mat = np.eye(3)
    col_var = np.zeros((3, 3))
    have = np.zeros(3, dtype=bool)
    for j in range(3):
        about = [tr for tr in turns if tr.axis == j]
        if about:
            have[j] = True
            k_mat[:, j] = np.mean([tr.sign * tr.integral_rad for tr in about], axis=0) / turn_rad
            col_var[:, j] = (
                np.sum([tr.integral_var for tr in about], axis=0) / (len(about) * turn_rad) ** 2
            )
    params = np.zeros(9)
    var = np.zeros(9)
    known = np.zeros(9, dtype=bool)
    if means.size:
        params[:3] = means.mean(axis=0) / reference_rps
        noise = np.diagonal(covs, axis1=1, axis2=2).sum(axis=0) / means.shape[0] ** 2
        var[:3] = noise / reference_rps**2 + (EARTH_RATE_RPS / reference_rps) ** 2 / 3.0
        known[:3] = True
    else:
        var[:3] = UNKNOWN_SIGMA[0] ** 2
    rows = np.where(have[None, :], k_mat, np.eye(3))
    nine = vector_to_nine(np.zeros(3), np.zeros(3), rows - np.eye(3), 1.0)
    pairs = ((0, 1), (0, 2), (1, 2))
    for i in range(3):
        known[3 + i] = bool(have[i])
        params[3 + i] = nine[3 + i] if have[i] else 0.0
        var[3 + i] = col_var[i, i] if have[i] else UNKNOWN_SIGMA[1] ** 2
    for m, (i, j) in enumerate(pairs):
        known[6 + m] = bool(have[i] and have[j])
        params[6 + m] = nine[6 + m] if known[6 + m] else 0.0
        var[6 + m] = col_var[i, j] + col_var[j, i] if known[6 + m] else UNKNOWN_SIGMA[2] ** 2
    sources = tuple(
        [SOURCE_STATIC_MEANS if known[0] else SOURCE_NONE] * 3
        + [SOURCE_TURNS if known[j] else SOURCE_NONE for j in range(3, 9)]
    )
    return params, np.diag(var), known, sources


def ferraris_spec(
    model: ErrorModel,
    *,
    static_s: float = 10.0,
    transition_s: float = 4.0,
    turn_s: float = 6.0,
    turns: bool = True,
    rate_hz: float = 100.0,
    latitude_deg: float = 45.0,
    height_m: float = 0.0,
) -> SessionSpec:
    """A six-position session as users record it for Ferraris-type tools (imucal, ArduPilot, PX4):
    each axis up, then down, held ``static_s``; with ``turns`` a full turn about each axis
    while it points up (rate ramped up and down over a third of ``turn_s`` each), then the
    same face again."""
    from estimators.sim import Hold, MotionProfile, SessionSpec, Spin, Turn, attitude_with_up

    up = SIX_FACES_UP_B
    segments: list[Hold | Turn | Spin] = [Hold(static_s)]
    for k in range(6):
        if k:
            face = tuple(map(tuple, attitude_with_up(up[k])))
            segments += [Turn(face, transition_s), Hold(static_s)]
        if turns and k % 2 == 0:
            rate = FULL_TURN_RAD / (2.0 / 3.0 * turn_s)
            ramp = turn_s / 3.0
            axis = tuple(up[k])
            segments += [
                Spin(ramp, 0.0, axis, end_rate_rps=rate),
                Spin(ramp, rate, axis),
                Spin(ramp, rate, axis, end_rate_rps=0.0),
                Hold(static_s),
            ]
    profile = MotionProfile(tuple(map(tuple, attitude_with_up(up[0]))), tuple(segments))
    return SessionSpec(
        profile, model, rate_hz=rate_hz, latitude_deg=latitude_deg, height_m=height_m
    )
