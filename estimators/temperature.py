"""Temperature models of accelerometer bias and scale factor (methods.md M3).

Dang, Lu & Yu run the six-position test (:mod:`estimators.sixpos`) at many
temperatures over −45…+75 °C and model each axis's bias ``D_i`` and relative
scale error ``l_i = (K_i − K0)/K0`` as polynomials in temperature; after
compensating with the best order the zero error stays below 0.0002 g and the
scale ("nonlinearity") error below 0.05 %.

Here the model of axis ``i`` at temperature ``T`` is that of
:mod:`estimators.conventions` with temperature-dependent bias and scale::

    a_meas,i = (1 + e_i(T))·a_i + g·b_i(T)
    b_i(T) = Σ_k bias_coeffs[i, k]·(T − T_ref)^k,   e_i(T) = Σ_k scale_coeffs[i, k]·(T − T_ref)^k

(:class:`estimators.passport.TemperatureModel`, ``b`` normalized by g,
``k = 0 … order``). *Order* is the polynomial degree. The paper says
"order n" for a model with n coefficients (degree n − 1) in one place and
calls its 4-coefficient model "quartic" in another; this project follows the
passport's convention, degree = order, and compares degrees 1…5.

Order selection (GMDH external criterion)
-----------------------------------------
Training residuals always fall as the order grows, so they cannot choose it.
The group method of data handling ranks model structures by an *external*
criterion: the temperatures are split alternately into two sets A and B (by
sorted temperature, so both span the range); each order is fitted on A and
judged on B and vice versa (the symmetric *regularity criterion*)::

    CR(n) = mean over held-out points of (measured − predicted)² / σ²

with σ the standard deviation of each measured bias or scale error (from the
six-position fit), pooled over the three axes and both quantities. A too-low
order leaves a systematic error and CR grows far above 1; a too-high order
fits noise and predicts worse (the paper: "5th order no better, needs more
points"). The order chosen is the *lowest* whose CR is within one standard
error of the smallest CR (the one-standard-error rule of cross-validation):
a higher order must earn its extra coefficients on held-out data by more than
the criterion's own scatter.

Valid range
-----------
The model records the lowest and highest test temperature it was fitted on
(``TemperatureModel.valid_min_c``, ``valid_max_c``). Compensation evaluates it
at the temperature clamped to that range, ``T_c = min(max(T, T_min), T_max)``:
beyond its data a polynomial of degree up to 4 is unbounded (it grows as
``(T − T_ref)^order`` and no test constrains the direction), while the value at
the edge is the nearest thing the chamber measured, so it is the best the
passport knows. Clamping does not make compensation exact out there; the
service therefore also stops checking samples taken outside the range
(:mod:`service.pipeline`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import FloatArray, IntArray
from estimators.least_squares import fit_linear
from estimators.passport import TemperatureModel
from estimators.positions import Position
from estimators.session import ImuSession
from estimators.sixpos import AccelSixPosition, six_position_accel, six_position_spec

# The simulator is imported by the functions that simulate: the service's pipeline imports this
# module (to_reference_temperature) and must not load it.
if TYPE_CHECKING:
    from estimators.sim import ErrorModel

ORDERS = (1, 2, 3, 4, 5)
"""Polynomial degrees compared (the paper's five models)."""

MIN_TEMPERATURES = 4
"""The smallest comparison (order 1) needs two temperatures in each held-out half."""

DEFAULT_REFERENCE_TEMP_C = 20.0
"""Room temperature, where the nominal passport values are usually measured."""


@dataclass(frozen=True)
class OrderScore:
    """How one polynomial order did.

    Attributes
    ----------
    order : polynomial degree.
    regularity : GMDH regularity criterion CR (module docstring); ≈ 1 when the
        order predicts held-out temperatures to the noise level.
    regularity_se : standard error of CR (scatter of the per-point terms / √n).
    training : mean normalized squared residual of the fit on all temperatures
        (shown to make the point: it keeps falling with the order).
    """

    order: int
    regularity: float
    regularity_se: float
    training: float


@dataclass(frozen=True)
class TemperatureFit:
    """The selected temperature model and the evidence for its order (M3).

    Attributes
    ----------
    model : the polynomials (bias normalized by ``gravity_mps2``).
    order : selected degree.
    scores : one :class:`OrderScore` per order compared, ascending.
    reason : one line saying why ``order`` won.
    gravity_mps2 : the g the bias is normalized by, m/s².
    bias_cov : (3, order+1, order+1) covariance of ``model.bias_coeffs`` (normalized).
    scale_cov : (3, order+1, order+1) covariance of ``model.scale_coeffs``.
    """

    model: TemperatureModel
    order: int
    scores: tuple[OrderScore, ...]
    reason: str
    gravity_mps2: float
    bias_cov: FloatArray
    scale_cov: FloatArray


def _vander(temp_c: FloatArray, ref_c: float, half_span_c: float, order: int) -> FloatArray:
    """(N, order+1) powers of the scaled temperature ``(T − T_ref)/half_span`` (well conditioned)."""
    x = (np.asarray(temp_c, dtype=float) - ref_c) / half_span_c
    return x[:, None] ** np.arange(order + 1)[None]


def _fit_series(h: FloatArray, y: FloatArray, std: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Weighted polynomial fit of one series; returns (coefficients, covariance) in scaled powers."""
    fit = fit_linear(h / std[:, None], y / std, sigma_y=1.0)
    return fit.values, fit.cov


def _series(
    bias_mps2: FloatArray, scale_error: FloatArray, bias_std_mps2: FloatArray, scale_std: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(T, 6) values and standard deviations: bias x, y, z then scale x, y, z."""
    return np.hstack([bias_mps2, scale_error]), np.hstack([bias_std_mps2, scale_std])


def _normalized_sq_errors(
    h: FloatArray, values: FloatArray, std: FloatArray, train: IntArray, test: IntArray
) -> FloatArray:
    """(n_test·S,) squared prediction errors at rows ``test`` of the fits of design ``h`` on ``train``, over their variance."""
    out = []
    for s in range(values.shape[1]):
        coef, _ = _fit_series(h[train], values[train, s], std[train, s])
        out.append(((values[test, s] - h[test] @ coef) / std[test, s]) ** 2)
    return np.concatenate(out)


def held_out_scores(
    temp_c: FloatArray,
    design: Callable[[int], FloatArray],
    values: FloatArray,
    std: FloatArray,
    orders: Sequence[int] = ORDERS,
) -> list[OrderScore]:
    """M3's regularity criterion (GMDH, module docstring) of each order the temperatures support.

    The rows sorted by temperature are split into alternate halves; each half's weighted fit predicts the
    other. ``design(n)``: the (T, p) design of order ``n`` (the polynomial's powers, and whatever else the
    series is fitted with); ``values``, ``std``: (T, S) series and their sd. An order is scored only when each
    half has at least as many rows as the design has columns; none: an empty list.
    """
    t = np.asarray(temp_c, dtype=float)
    by_temp = np.argsort(t, kind="stable")
    half_a, half_b = by_temp[0::2], by_temp[1::2]
    scores = []
    for n in sorted(set(int(o) for o in orders)):
        if n < 0:
            continue
        h = design(n)
        if min(half_a.size, half_b.size) < h.shape[1]:
            continue
        errs = np.concatenate(
            [
                _normalized_sq_errors(h, values, std, half_a, half_b),
                _normalized_sq_errors(h, values, std, half_b, half_a),
            ]
        )
        train = np.mean(
            [
                np.mean(
                    ((values[:, s] - h @ _fit_series(h, values[:, s], std[:, s])[0]) / std[:, s])
                    ** 2
                )
                for s in range(values.shape[1])
            ]
        )
        scores.append(
            OrderScore(
                order=n,
                regularity=float(errs.mean()),
                regularity_se=float(errs.std(ddof=1) / np.sqrt(errs.size)),
                training=float(train),
            )
        )
    return scores


def chosen_order(scores: list[OrderScore]) -> tuple[OrderScore, OrderScore]:
    """The order M3 takes and the best-scoring one: the lowest order within one standard error of the best."""
    best = min(scores, key=lambda s: s.regularity)
    return next(s for s in scores if s.regularity <= best.regularity + best.regularity_se), best


def fit_temperature_model(
    temp_c: FloatArray,
    bias_mps2: FloatArray,
    scale_error: FloatArray,
    *,
    bias_std_mps2: FloatArray,
    scale_std: FloatArray,
    gravity_mps2: float,
    orders: Sequence[int] = ORDERS,
    reference_temp_c: float = DEFAULT_REFERENCE_TEMP_C,
) -> TemperatureFit:
    """Polynomial temperature model of bias and scale error per axis, order chosen by GMDH (M3).

    Parameters
    ----------
    temp_c : (T,) temperatures of the six-position tests, °C (T ≥ 4 distinct).
    bias_mps2 : (T, 3) bias per axis at each temperature, m/s².
    scale_error : (T, 3) relative scale error per axis at each temperature.
    bias_std_mps2, scale_std : (T, 3) their standard deviations (> 0).
    gravity_mps2 : local g, m/s² (normalizes the bias in the model).
    orders : degrees to compare; an order is compared only if each held-out
        half has at least as many temperatures as it has coefficients.
    reference_temp_c : T_ref of the polynomials, °C, within the tested temperatures.

    The model's valid range is ``[min(temp_c), max(temp_c)]`` (module docstring).

    Raises
    ------
    ValueError
        Fewer than four temperatures, a shape mismatch, ``reference_temp_c``
        outside the tested temperatures, or no order that the temperatures can
        support.
    """
    t = np.asarray(temp_c, dtype=float)
    if t.ndim != 1:
        raise ValueError(f"temp_c must be a (T,) array, got shape {t.shape}")
    arrays = [
        np.asarray(a, dtype=float) for a in (bias_mps2, scale_error, bias_std_mps2, scale_std)
    ]
    for name, a in zip(
        ("bias_mps2", "scale_error", "bias_std_mps2", "scale_std"), arrays, strict=True
    ):
        if a.shape != (t.size, 3):
            raise ValueError(f"{name} must have shape ({t.size}, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite")
    distinct = np.unique(np.round(t, 6)).size
    if distinct < MIN_TEMPERATURES:
        raise ValueError(
            f"a temperature model needs six-position tests at {MIN_TEMPERATURES} or more different temperatures, got {distinct}"
        )
    if not np.all(arrays[2] > 0) or not np.all(arrays[3] > 0):
        raise ValueError("the standard deviations of bias and scale error must be positive")
    if not gravity_mps2 > 0:
        raise ValueError(f"gravity_mps2 must be positive, got {gravity_mps2!r}")
    t_min_c, t_max_c = float(t.min()), float(t.max())
    if not t_min_c <= reference_temp_c <= t_max_c:
        # The nominal values are the model at T_ref: outside the tests they would be an extrapolation.
        raise ValueError(
            f"reference_temp_c {reference_temp_c:g} °C is outside the tested temperatures {t_min_c:g}…{t_max_c:g} °C; choose one within them"
        )
    values, std = _series(*arrays)
    ref = float(reference_temp_c)
    span = float(max(np.max(np.abs(t - ref)), 1e-9))
    scores = held_out_scores(t, lambda n: _vander(t, ref, span, n), values, std, orders)
    if not scores:
        raise ValueError(
            f"{t.size} temperatures cannot compare orders {tuple(orders)}: each held-out half needs at least as many temperatures as coefficients"
        )
    chosen, best = chosen_order(scores)
    lower = [s for s in scores if s.order < chosen.order]
    reason = f"order {chosen.order}: held-out criterion {chosen.regularity:.3g}"
    if lower:
        reason += f" against {lower[-1].regularity:.3g} for order {lower[-1].order} (a lower order leaves a systematic error)"
    if chosen is not best:
        reason += f"; order {best.order} scores {best.regularity:.3g}, within one standard error ({best.regularity_se:.2g}), so the extra coefficients are not earned"
    elif any(s.order > chosen.order for s in scores):
        reason += "; higher orders predict the held-out temperatures worse"

    n = chosen.order
    h_all = _vander(t, ref, span, n)
    # Scaled powers → powers of (T − T_ref) in °C: coefficient k divides by span^k.
    unscale = span ** -np.arange(n + 1)
    coefs = np.zeros((6, n + 1))
    covs = np.zeros((6, n + 1, n + 1))
    for s in range(6):
        c, cov = _fit_series(h_all, values[:, s], std[:, s])
        coefs[s] = c * unscale
        covs[s] = cov * np.outer(unscale, unscale)
    g = float(gravity_mps2)
    model = TemperatureModel(
        reference_temp_c=ref,
        bias_coeffs=coefs[:3] / g,
        scale_coeffs=coefs[3:],
        valid_min_c=t_min_c,
        valid_max_c=t_max_c,
    )
    return TemperatureFit(
        model=model,
        order=n,
        scores=tuple(scores),
        reason=reason,
        gravity_mps2=g,
        bias_cov=covs[:3] / g**2,
        scale_cov=covs[3:],
    )


def clamp_to_range(model: TemperatureModel, temp_c: FloatArray) -> FloatArray:
    """(N,) temperatures ``temp_c`` (N,), °C, clamped to the model's valid range (unchanged for an unbounded model).

    Why clamp rather than extrapolate: module docstring, "Valid range".
    """
    t = np.asarray(temp_c, dtype=float).reshape(-1)
    if not model.bounded:
        return t
    clamped: FloatArray = np.clip(t, model.valid_min_c, model.valid_max_c)
    return clamped


def model_errors(model: TemperatureModel, temp_c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Normalized bias ``b(T)`` (N, 3) and scale error ``e(T)`` (N, 3) of the model at ``temp_c`` (N,) °C.

    Outside the valid range the values at the nearer edge (:func:`clamp_to_range`): finite at any
    temperature, and what compensation uses.
    """
    x = clamp_to_range(model, temp_c) - model.reference_temp_c
    powers = x[:, None] ** np.arange(model.order + 1)[None]
    return powers @ model.bias_coeffs.T, powers @ model.scale_coeffs.T


def _check_samples(accel_mps2: FloatArray, temp_c: FloatArray) -> tuple[FloatArray, FloatArray]:
    a = np.asarray(accel_mps2, dtype=float)
    t = np.asarray(temp_c, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3 or t.shape != (a.shape[0],):
        raise ValueError(f"need accel (N, 3) and temp_c (N,), got {a.shape} and {t.shape}")
    return a, t


def remove_temperature_errors(
    accel_mps2: FloatArray, temp_c: FloatArray, model: TemperatureModel, *, gravity_mps2: float
) -> FloatArray:
    """(N, 3) specific force with the modelled bias and scale error removed entirely (M3 compensation).

    ``a = (a_meas − g·b(T)) / (1 + e(T))``, ``T`` clamped to the valid range
    (:func:`model_errors`). Used to measure the residual zero and scale errors
    the model leaves.
    """
    a, t = _check_samples(accel_mps2, temp_c)
    b, e = model_errors(model, t)
    return (a - gravity_mps2 * b) / (1.0 + e)


def to_reference_temperature(
    accel_mps2: FloatArray, temp_c: FloatArray, model: TemperatureModel, *, gravity_mps2: float
) -> FloatArray:
    """(N, 3) output as the unit would give it at ``T_ref`` (what the service applies).

    ``a_ref = (1 + e(T_ref))·(a_meas − g·b(T))/(1 + e(T)) + g·b(T_ref)``: the
    temperature-dependent part is removed and the passport's nominal bias and
    scale error (measured at ``T_ref``) stay in the data, so the diagnosis
    against the passport remains valid across the model's range. Outside it
    ``T`` is clamped to the nearer edge (:func:`model_errors`, module docstring):
    the result stays finite, but is only as good as the edge value.
    """
    a, t = _check_samples(accel_mps2, temp_c)
    b, e = model_errors(model, t)
    b_ref, e_ref = model.bias_coeffs[:, 0], model.scale_coeffs[:, 0]
    return (1.0 + e_ref) * (a - gravity_mps2 * b) / (1.0 + e) + gravity_mps2 * b_ref


def group_temperatures(temp_c: FloatArray, *, tolerance_c: float = 2.0) -> FloatArray:
    """(K,) group label of each value of ``temp_c`` (K,): sorted values closer than ``tolerance_c`` join a group.

    Labels count up with temperature. Used to collect the six positions
    measured at one chamber temperature.
    """
    t = np.asarray(temp_c, dtype=float)
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise ValueError("temperatures must be a finite (K,) array")
    order = np.argsort(t, kind="stable")
    jumps = np.concatenate([[0], (np.diff(t[order]) > tolerance_c).astype(int)])
    labels = np.empty(t.size, dtype=int)
    labels[order] = np.cumsum(jumps)
    return labels


# --- six-position tests at many temperatures ------------------------------------------------------


@dataclass(frozen=True)
class TemperatureSeries:
    """Six-position results at each test temperature, the input of :func:`fit_temperature_model`.

    Attributes
    ----------
    temp_c : (T,) mean temperature of each test, °C, ascending.
    bias_mps2, scale_error : (T, 3) per axis.
    bias_std_mps2, scale_std : (T, 3) their standard deviations.
    tests : (T,) the six-position results.
    """

    temp_c: FloatArray
    bias_mps2: FloatArray
    scale_error: FloatArray
    bias_std_mps2: FloatArray
    scale_std: FloatArray
    tests: tuple[AccelSixPosition, ...]


def temperature_series(
    positions: Sequence[Position], *, gravity_mps2: float, tolerance_c: float = 2.0
) -> TemperatureSeries:
    """Group static positions by temperature and run the six-position test in each group (M3 input).

    Positions without a temperature are an error: the temperature model needs
    it. A group that is not a complete six-position test raises with its
    temperature in the message.
    """
    positions = tuple(positions)
    if not positions:
        raise ValueError(
            "no static positions: the temperature model needs six-position tests at several temperatures"
        )
    if any(p.temp_mean_c is None for p in positions):
        raise ValueError(
            "the session has no temperature column: the temperature model needs the temperature of each position"
        )
    temps = np.array([p.temp_mean_c for p in positions])
    labels = group_temperatures(temps, tolerance_c=tolerance_c)
    rows = []
    for label in range(int(labels.max()) + 1):
        group = [p for p, lab in zip(positions, labels, strict=True) if lab == label]
        t_mean = float(np.mean([p.temp_mean_c for p in group]))
        mean = np.array([p.accel_mean_mps2 for p in group])
        cov = np.array([p.accel_cov_mps2 for p in group])
        try:
            test = six_position_accel(mean, gravity_mps2=gravity_mps2, accel_cov_mps2=cov)
        except ValueError as exc:
            raise ValueError(f"at {t_mean:.1f} °C: {exc}") from None
        rows.append((t_mean, test))
    tests = tuple(r[1] for r in rows)
    return TemperatureSeries(
        temp_c=np.array([r[0] for r in rows]),
        bias_mps2=np.array([t.bias_mps2 for t in tests]),
        scale_error=np.array([t.scale_error for t in tests]),
        bias_std_mps2=np.array([t.std[:, 0] for t in tests]),
        scale_std=np.array([t.std[:, 1] for t in tests]),
        tests=tests,
    )


# --- the simulated chamber ------------------------------------------------------------------------

PAPER_TEMPS_C = tuple(float(t) for t in range(-45, 80, 5))
"""The paper's range, −45…+75 °C, in 5 °C steps (25 chamber temperatures)."""

PAPER_ZERO_ERROR_G = 0.0013
PAPER_SCALE_ERROR = 0.022
"""Largest uncompensated zero error (in g) and scale ("nonlinearity") error the paper shows over its range."""

# Shapes of the hidden dependence in x = (T − 20 °C)/55 °C, powers 1…4: distinct per axis,
# with a quartic part that a cubic cannot follow. Scaled so the largest value over the
# range is the paper's.
_BIAS_SHAPES = np.array([[0.5, -0.6, -0.3, 0.9], [0.2, 0.8, -0.4, -0.9], [-0.6, 0.3, 0.5, 0.7]])
_SCALE_SHAPES = np.array([[0.6, -0.4, -0.5, 0.8], [-0.3, 0.9, 0.2, -0.7], [0.4, 0.2, -0.6, 0.6]])
_SHAPE_SPAN_C = 55.0


def _scaled_coefs(
    shapes: FloatArray, peak: float, t_ref_c: float, temps_c: FloatArray
) -> FloatArray:
    x = (np.asarray(temps_c) - t_ref_c) / _SHAPE_SPAN_C
    values = (x[:, None, None] ** np.arange(1, 5)[None, None] * shapes[None]).sum(-1)
    coefs: FloatArray = shapes / np.max(np.abs(values), axis=0)[:, None] * peak
    return coefs / _SHAPE_SPAN_C ** np.arange(1, 5)[None]


def hidden_quartic_model(
    *, gravity_mps2: float, t_ref_c: float = DEFAULT_REFERENCE_TEMP_C
) -> ErrorModel:
    """A pendulous accelerometer triad with a 4th-degree temperature dependence sized like the paper's (M3).

    Over −45…+75 °C the temperature part of the bias peaks at 0.0013 g and the
    relative scale change at 2.2 % on every axis. Constant errors: bias
    0.5–1 mg, scale 1e-4, axes off by 20 µrad; white noise 10 µg/√Hz; no
    quantization. Gyros: none of interest (noise only).
    """
    from estimators.sim import (
        Bias,
        ErrorModel,
        NonOrthogonality,
        ScaleFactor,
        TemperatureBias,
        TemperatureScale,
        TriadErrorModel,
        WhiteNoise,
    )

    temps = np.linspace(PAPER_TEMPS_C[0], PAPER_TEMPS_C[-1], 241)
    bias_c = _scaled_coefs(_BIAS_SHAPES, PAPER_ZERO_ERROR_G * gravity_mps2, t_ref_c, temps)
    scale_c = _scaled_coefs(_SCALE_SHAPES, PAPER_SCALE_ERROR, t_ref_c, temps)
    accel = TriadErrorModel(
        (
            NonOrthogonality((20e-6, -15e-6, 10e-6, 25e-6, -20e-6, 15e-6)),
            ScaleFactor((1.0e-4, -1.5e-4, 0.8e-4)),
            TemperatureScale(scale_c, t_ref_c),
            Bias(np.array([0.5, -0.8, 1.0]) * 1e-3 * gravity_mps2),
            TemperatureBias(bias_c, t_ref_c),
            WhiteNoise((1e-5 * gravity_mps2,) * 3),
        )
    )
    gyro = TriadErrorModel((WhiteNoise((1e-4,) * 3),))
    return ErrorModel(accel=accel, gyro=gyro)


def temperature_truth(model: ErrorModel, temp_c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """True bias (N, 3), m/s², and six-position scale error (N, 3) of a simulator model at ``temp_c`` (N,).

    ``b(T) = b0 + Σ d_j (T − T_ref)^j`` and ``S(T) = (1 + e0)(1 + Σ k_j (T − T_ref)^j)·s_ii − 1``
    (the effect chain of :mod:`estimators.sim.errors`).
    """
    from estimators.sim import (
        Bias,
        NonOrthogonality,
        ScaleFactor,
        TemperatureBias,
        TemperatureScale,
    )

    chain = model.accel
    t = np.asarray(temp_c, dtype=float).reshape(-1)

    def poly(coefs: ArrayLike, t_ref_c: float) -> FloatArray:
        c = np.asarray(coefs, dtype=np.float64)
        powers: FloatArray = (t - t_ref_c)[:, None, None] ** np.arange(1, c.shape[1] + 1)[
            None, None
        ]
        values: FloatArray = (powers * c[None]).sum(-1)
        return values

    bias = chain.find(Bias)
    scale = chain.find(ScaleFactor)
    nonorth = chain.find(NonOrthogonality)
    temp_bias = chain.find(TemperatureBias)
    temp_scale = chain.find(TemperatureScale)
    b0 = np.zeros(3) if bias is None else np.array(bias.bias_si)
    e0 = np.zeros(3) if scale is None else np.array(scale.scale_err)
    s_ii = np.ones(3) if nonorth is None else np.diag(nonorth.axes)
    d_t = (
        np.zeros((t.size, 3))
        if temp_bias is None
        else poly(temp_bias.coef_si_per_c, temp_bias.t_ref_c)
    )
    k_t = (
        np.zeros((t.size, 3))
        if temp_scale is None
        else poly(temp_scale.coef_per_c, temp_scale.t_ref_c)
    )
    b = b0 + d_t
    e = (1.0 + e0) * (1.0 + k_t) * s_ii - 1.0
    return b, e


def simulate_chamber(
    model: ErrorModel,
    temps_c: Sequence[float],
    *,
    seed: int,
    static_s: float = 20.0,
    rate_hz: float = 100.0,
    latitude_deg: float = 45.0,
    height_m: float = 0.0,
) -> ImuSession:
    """Six-position tests at each chamber temperature, one after the other, as one session with temperature.

    Each test is a simulated session (:func:`estimators.sixpos.six_position_spec`)
    at a constant temperature; the tests follow each other with a 60 s gap
    (the chamber settling), so the static detector never joins two of them.
    """
    from estimators.sim import ConstantTemperature, simulate

    ss = np.random.SeedSequence(seed)
    parts, t0 = [], 0.0
    for temp, child in zip(temps_c, ss.spawn(len(temps_c)), strict=True):
        spec = six_position_spec(
            model,
            static_s=static_s,
            rate_hz=rate_hz,
            latitude_deg=latitude_deg,
            height_m=height_m,
            temperature=ConstantTemperature(float(temp)),
        )
        res = simulate(spec, np.random.default_rng(child))
        s = res.session
        parts.append(ImuSession(s.t_s + t0, s.accel_mps2, s.gyro_rps, s.temp_c))
        t0 = float(parts[-1].t_s[-1]) + 60.0
    return ImuSession(
        np.concatenate([p.t_s for p in parts]),
        np.concatenate([p.accel_mps2 for p in parts]),
        np.concatenate([p.gyro_rps for p in parts]),
        np.concatenate([p.temp_c for p in parts]),
    )
