"""The error model of a simulated IMU: an ordered chain of named effects per triad.

A triad's output is the true input ``x_b`` (N, 3) — specific force in m/s² or
inertial body rate in rad/s, body axes — passed through its effects in order.
Every effect is a small frozen dataclass with a ``name`` (the names the model
audit uses, issue 4), its own parameters in SI units, and ``apply(y, ctx)``.
The chain order is the ``stage`` of each effect (non-decreasing), which is the
physical order of the signal path:

====== ======================== ===========================================================
stage  name                     what it does to ``y`` (per sensor axis ``i``)
====== ======================== ===========================================================
0      ``non_orthogonality``    ``y_i = s_i · x_b``: projection on the sensitive axes (M1)
1      ``nonorthogonality_change`` from ``t_change``: the axes' cosines change by ``Δd`` (a mounting slip)
10     ``scale_nonlinearity``   ``y_i += K2_i y_i² + K3_i y_i³`` (M3's K2, K3)
11     ``cross_axis_nonlinearity`` ``y_i += Kc_i y_j y_k`` (``j, k`` the other two axes)
20     ``scale_factor``         ``y_i *= 1 + e_i``
25     ``temperature_scale``    ``y_i *= 1 + Σ_j k_ij (T − T_ref)^j`` (M3, j ≥ 1)
30     ``bias``                 ``y_i += b_i``
31     ``bias_drift``           ``y_i += Σ_j c_ij (t − t_0)^j`` (j ≥ 1)
31     ``bias_step``            ``y_i += s_i`` from ``t_step`` on (a knock, a turn that shifts the bias)
32     ``temperature_bias``     ``y_i += Σ_j d_ij (T − T_ref)^j`` (M3, j ≥ 1)
32     ``temperature_hysteresis`` ``y_i += h_i sign(dT/dt)`` (heating +h, cooling −h)
33     ``bias_instability``     ``y_i +=`` Gauss–Markov + random walk + flicker noise
34     ``g_sensitivity``        gyros: ``y += G f_b`` (M4's Bg, rad/s per m/s²)
40     ``white_noise``          ``y_i += σ_i n_i``, ``σ_i = density_i·√rate``, ``corr(n) = R``
41     ``coloured_noise``       ``y_i +=`` a sum of short Gauss–Markov terms (noise colour), driven with ``R``
42     ``spectral_line``        ``y_i += A_i sin(2π f_i t + φ_i)`` (mains or rotor pickup; φ from the stream)
44     ``lowpass``              ``y_i`` through the firmware's anti-alias Butterworth low-pass (order ``n``, cut-off ``f_c``)
45     (noise-burst faults)     see :mod:`estimators.sim.faults`
48     ``clipping``             ``y_i`` held on the rails ``±r_i`` (the converter's full scale)
50     ``quantization``         ``y_i = k_i·Entier(y_i / k_i)`` (M2)
====== ======================== ===========================================================

With only ``non_orthogonality``, ``scale_factor`` and ``bias`` the chain is the
exact triad model of :mod:`estimators.conventions` (``y/ref = A u + b``), so
:meth:`TriadErrorModel.nine_params` is the exact truth of the nine parameters.
Constant terms live in ``bias`` and ``scale_factor`` only: the polynomial
effects start at the first power, so the nine parameters are those at
``T = T_ref`` and ``t = t_0``.

Two *environment* effects change the truth rather than a sensor and sit in
:attr:`ErrorModel.environment`: ``gravity_mismatch`` (the true local gravity
differs from the assumed one) and ``nonstatic_positions`` (small motion inside
nominally static intervals).

A new effect is a new subclass of :class:`Effect` with a ``name``, a ``stage``
and ``apply``; nothing else changes.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field, fields, replace
from enum import Enum, StrEnum
from typing import Any, ClassVar, TypeAlias, TypeVar, overload

import numpy as np
from numpy.typing import ArrayLike

# scipy is imported in the functions that use it: it takes a large part of a second to import, and
# `calibrate` imports this module (through the audit) for sessions the audit does not simulate too.
from estimators._typing import FloatArray
from estimators.conventions import Triad, nine_params, sensor_axes

from .motion import Motion, angle_excursion, displacement_accel, random_sinusoids

NOISE_BURST_STAGE = 45
"""Where the noise-burst faults enter the chain: after white noise, before quantization."""


@dataclass(frozen=True)
class EffectContext:
    """What an effect may read besides the signal.

    Attributes
    ----------
    t_s : (N,) sample times, s.
    rate_hz : sample rate, Hz.
    triad : the triad the chain belongs to.
    reference : the triad's true scalar reference (g in m/s², or Ω in rad/s).
    specific_force_b_mps2 : (N, 3) true specific force, body axes (for g-sensitivity).
    temp_c : (N,) true temperature, °C, or None.
    param_delta : (N, 9) parameter changes of injected faults, or None.
    rng : this effect's own random stream.
    """

    t_s: FloatArray
    rate_hz: float
    triad: Triad
    reference: float
    specific_force_b_mps2: FloatArray
    temp_c: FloatArray | None
    param_delta: FloatArray | None
    rng: np.random.Generator

    def delta(self, cols: slice) -> FloatArray | None:
        """(N, k) fault changes of parameters ``cols``, or None if they never change."""
        if self.param_delta is None:
            return None
        d = self.param_delta[:, cols]
        return d if np.any(d) else None

    def temperature(self, effect: str) -> FloatArray:
        if self.temp_c is None:
            raise ValueError(f"effect {effect!r} needs a temperature profile in the session spec")
        return self.temp_c


Floats: TypeAlias = tuple[float, ...]
"""A vector parameter of an effect, stored as a tuple of floats (hashable, frozen)."""

FloatRows: TypeAlias = tuple[Floats, ...]
"""A matrix parameter of an effect (rows of floats)."""


def _finite(value: ArrayLike, shape: tuple[int, ...], name: str) -> FloatArray:
    """``value`` broadcast to ``shape``, all finite."""
    try:
        a = np.broadcast_to(np.asarray(value, dtype=float), shape)
    except ValueError:
        raise ValueError(f"{name} must broadcast to shape {shape}, got {np.shape(value)}") from None
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()!r}")
    return a


def _floats(value: ArrayLike, n: int, name: str) -> Floats:
    """``value`` broadcast to ``(n,)`` as a tuple of finite floats."""
    return tuple(_finite(value, (n,), name).tolist())


def _float_rows(value: ArrayLike, shape: tuple[int, int], name: str) -> FloatRows:
    """``value`` broadcast to ``shape`` as a tuple of rows of finite floats."""
    return tuple(tuple(row) for row in _finite(value, shape, name).tolist())


def _poly_coefs(value: ArrayLike, name: str) -> FloatRows:
    """(3, n) per-axis polynomial coefficients of powers 1…n, n ≥ 1."""
    a = np.asarray(value, dtype=float)
    if a.ndim == 1:
        a = np.broadcast_to(a, (3, a.size))
    if a.ndim != 2 or a.shape[0] != 3 or a.shape[1] < 1:
        raise ValueError(
            f"{name} must have shape (3, n) or (n,) with n >= 1, got {np.shape(value)}"
        )
    return _float_rows(a, (3, a.shape[1]), name)


def _poly(coefs: ArrayLike, x: FloatArray) -> FloatArray:
    """(N, 3) ``Σ_j c_ij x^j`` for j = 1…n (no constant term)."""
    c = np.asarray(coefs)
    powers = x[:, None] ** np.arange(1, c.shape[1] + 1)[None]
    out: FloatArray = powers @ c.T
    return out


@dataclass(frozen=True)
class Effect(abc.ABC):
    """One named term of a triad's error model (see the module docstring)."""

    name: ClassVar[str]
    stage: ClassVar[int]
    triads: ClassVar[tuple[Triad, ...]] = (Triad.ACCEL, Triad.GYRO)

    @abc.abstractmethod
    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        """The signal (N, 3) after this effect; never modifies ``y`` in place."""


_EffectT = TypeVar("_EffectT", bound=Effect)


def _correlation_rows(value: ArrayLike) -> FloatRows:
    """A (3, 3) correlation matrix of the axes' noise (symmetric, unit diagonal, positive definite) as rows."""
    r = _finite(value, (3, 3), "correlation")
    if not np.allclose(r, r.T) or not np.allclose(np.diag(r), 1.0):
        raise ValueError(f"correlation must be symmetric with a unit diagonal, got {r.tolist()!r}")
    try:
        np.linalg.cholesky(r)
    except np.linalg.LinAlgError:
        raise ValueError(f"correlation must be positive definite, got {r.tolist()!r}") from None
    return _float_rows(r, (3, 3), "correlation")


def _correlated_normals(
    rng: np.random.Generator, correlation: ArrayLike, shape: tuple[int, ...], axis: int
) -> FloatArray:
    """Standard normals of ``shape`` whose ``axis`` (the 3 sensor axes) has the correlation ``correlation``.

    Each sensor axis keeps unit variance (the Cholesky factor's rows have unit norm); with the identity
    these are the generator's own draws, unchanged, so a seeded simulation without a correlation is too.
    """
    z = np.moveaxis(rng.standard_normal(shape), axis, 0)
    factor = np.linalg.cholesky(np.array(correlation, dtype=np.float64))
    out: FloatArray = np.moveaxis(np.tensordot(factor, z, axes=(1, 0)), 0, axis)
    return out


@dataclass(frozen=True)
class NonOrthogonality(Effect):
    """Sensitive axes from the six small angles ``[δ_xy, δ_xz, δ_yx, δ_yz, δ_zx, δ_zy]``, rad.

    Uses :func:`estimators.conventions.sensor_axes`. A fault in ``d1…d3``
    changes the Gram matrix ``G = S Sᵀ`` of the axes (the cosines) to ``G'``;
    the faulted axes are ``S' = G'^½ G^−½ S`` (``S' S'ᵀ = G'`` exactly, and
    ``S' → S`` as the change vanishes).
    """

    angles_rad: ArrayLike = (0.0,) * 6
    name: ClassVar[str] = "non_orthogonality"
    stage: ClassVar[int] = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "angles_rad", _floats(self.angles_rad, 6, "angles_rad"))

    @property
    def axes(self) -> FloatArray:
        return sensor_axes(np.array(self.angles_rad, dtype=np.float64))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        s = self.axes
        out = y @ s.T
        d = ctx.delta(slice(6, 9))
        if d is None:
            return out
        hit = np.any(d != 0.0, axis=1)
        rows, inverse = np.unique(d[hit], axis=0, return_inverse=True)
        gram = s @ s.T
        gram_f = np.repeat(gram[None], len(rows), axis=0)
        for col, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
            gram_f[:, i, j] += rows[:, col]
            gram_f[:, j, i] += rows[:, col]
        lam, vec = np.linalg.eigh(gram_f)
        if np.any(lam <= 0):
            raise ValueError(
                "a non-orthogonality fault makes the sensitive axes linearly dependent"
            )
        lam0, vec0 = np.linalg.eigh(gram)
        inv_sqrt = (vec0 / np.sqrt(lam0)) @ vec0.T
        s_f = (vec * np.sqrt(lam)[:, None, :]) @ np.swapaxes(vec, 1, 2) @ inv_sqrt @ s
        out[hit] = np.einsum("nij,nj->ni", s_f[inverse.reshape(-1)], y[hit])
        return out


@dataclass(frozen=True)
class ScaleNonlinearity(Effect):
    """``y_i += K2_i y_i² + K3_i y_i³`` (M3); K2 in 1/SI, K3 in 1/SI² of the triad's unit."""

    k2_per_si: ArrayLike = (0.0,) * 3
    k3_per_si2: ArrayLike = (0.0,) * 3
    name: ClassVar[str] = "scale_nonlinearity"
    stage: ClassVar[int] = 10

    def __post_init__(self) -> None:
        object.__setattr__(self, "k2_per_si", _floats(self.k2_per_si, 3, "k2_per_si"))
        object.__setattr__(self, "k3_per_si2", _floats(self.k3_per_si2, 3, "k3_per_si2"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        return (
            y
            + np.array(self.k2_per_si, dtype=np.float64) * y**2
            + np.array(self.k3_per_si2, dtype=np.float64) * y**3
        )


@dataclass(frozen=True)
class NonOrthogonalityChange(Effect):
    """The axes' cosines ``[d_xy, d_xz, d_yz]`` change by ``cosine_change`` from ``t_change_s`` on (a mounting slip).

    With x on body x and y in the x-y plane (the convention of the nine parameters), axis y turns toward x
    and axis z toward x and y: ``y_y += Δd_xy y_x``, ``y_z += Δd_xz y_x + Δd_yz y_y`` (first order).
    """

    t_change_s: float = 0.0
    cosine_change: ArrayLike = (0.0,) * 3
    name: ClassVar[str] = "nonorthogonality_change"
    stage: ClassVar[int] = 1

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_change_s", float(self.t_change_s))
        object.__setattr__(self, "cosine_change", _floats(self.cosine_change, 3, "cosine_change"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        d_xy, d_xz, d_yz = np.array(self.cosine_change, dtype=np.float64)
        turn = np.array([[0.0, 0.0, 0.0], [d_xy, 0.0, 0.0], [d_xz, d_yz, 0.0]])
        after = (ctx.t_s >= self.t_change_s)[:, None]
        out: FloatArray = y + after * (y @ turn.T)
        return out


@dataclass(frozen=True)
class CrossAxisNonlinearity(Effect):
    """Second-order cross-axis term ``y_i += Kc_i y_j y_k`` (``j < k`` the other two axes), Kc in 1/SI."""

    kc_per_si: ArrayLike = (0.0,) * 3
    name: ClassVar[str] = "cross_axis_nonlinearity"
    stage: ClassVar[int] = 11

    def __post_init__(self) -> None:
        object.__setattr__(self, "kc_per_si", _floats(self.kc_per_si, 3, "kc_per_si"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        cross = np.column_stack([y[:, 1] * y[:, 2], y[:, 0] * y[:, 2], y[:, 0] * y[:, 1]])
        out: FloatArray = y + np.array(self.kc_per_si, dtype=np.float64) * cross
        return out


@dataclass(frozen=True)
class ScaleFactor(Effect):
    """``y_i *= 1 + e_i`` with the relative scale-factor errors ``e`` (3,)."""

    scale_err: ArrayLike = (0.0,) * 3
    name: ClassVar[str] = "scale_factor"
    stage: ClassVar[int] = 20

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale_err", _floats(self.scale_err, 3, "scale_err"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        e = np.array(self.scale_err, dtype=np.float64)
        d = ctx.delta(slice(3, 6))
        return y * (1.0 + (e if d is None else e + d))


@dataclass(frozen=True)
class TemperatureScale(Effect):
    """``y_i *= 1 + Σ_j k_ij (T − t_ref_c)^j``, j = 1…n (M3's ``l_i(t)`` without its constant).

    ``coef_per_c`` (3, n): relative scale change per °C^j.
    """

    coef_per_c: ArrayLike = ((0.0,),) * 3
    t_ref_c: float = 20.0
    name: ClassVar[str] = "temperature_scale"
    stage: ClassVar[int] = 25

    def __post_init__(self) -> None:
        object.__setattr__(self, "coef_per_c", _poly_coefs(self.coef_per_c, "coef_per_c"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        return y * (1.0 + _poly(self.coef_per_c, ctx.temperature(self.name) - self.t_ref_c))


@dataclass(frozen=True)
class Bias(Effect):
    """``y_i += b_i`` with the zero signal ``bias_si`` (3,) in the triad's SI unit.

    The normalized parameter of M1 is ``bias_si / reference``; a bias fault
    adds ``Δb·reference``.
    """

    bias_si: ArrayLike = (0.0,) * 3
    name: ClassVar[str] = "bias"
    stage: ClassVar[int] = 30

    def __post_init__(self) -> None:
        object.__setattr__(self, "bias_si", _floats(self.bias_si, 3, "bias_si"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        b = np.array(self.bias_si, dtype=np.float64)
        d = ctx.delta(slice(0, 3))
        return y + (b if d is None else b + d * ctx.reference)


@dataclass(frozen=True)
class BiasDrift(Effect):
    """Deterministic bias change with time: ``y_i += Σ_j c_ij (t − t_0)^j``, j = 1…n.

    ``coef_si_per_s`` (3, n): SI per s^j; ``t_0`` is the first sample's time.
    """

    coef_si_per_s: ArrayLike = ((0.0,),) * 3
    name: ClassVar[str] = "bias_drift"
    stage: ClassVar[int] = 31

    def __post_init__(self) -> None:
        object.__setattr__(self, "coef_si_per_s", _poly_coefs(self.coef_si_per_s, "coef_si_per_s"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        return y + _poly(self.coef_si_per_s, ctx.t_s - ctx.t_s[0])


@dataclass(frozen=True)
class TemperatureBias(Effect):
    """``y_i += Σ_j d_ij (T − t_ref_c)^j``, j = 1…n (M3's ``D_i(t)`` without its constant).

    ``coef_si_per_c`` (3, n): SI per °C^j.
    """

    coef_si_per_c: ArrayLike = ((0.0,),) * 3
    t_ref_c: float = 20.0
    name: ClassVar[str] = "temperature_bias"
    stage: ClassVar[int] = 32

    def __post_init__(self) -> None:
        object.__setattr__(self, "coef_si_per_c", _poly_coefs(self.coef_si_per_c, "coef_si_per_c"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        return y + _poly(self.coef_si_per_c, ctx.temperature(self.name) - self.t_ref_c)


@dataclass(frozen=True)
class BiasStep(Effect):
    """``y_i += step_si_i`` from ``t_step_s_i`` on (session time, per axis): a bias that jumps in a turn or a knock."""

    t_step_s: ArrayLike = (0.0,) * 3
    step_si: ArrayLike = (0.0,) * 3
    name: ClassVar[str] = "bias_step"
    stage: ClassVar[int] = 31

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_step_s", _floats(self.t_step_s, 3, "t_step_s"))
        object.__setattr__(self, "step_si", _floats(self.step_si, 3, "step_si"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        after = ctx.t_s[:, None] >= np.array(self.t_step_s, dtype=np.float64)
        out: FloatArray = y + after * np.array(self.step_si, dtype=np.float64)
        return out


@dataclass(frozen=True)
class TemperatureHysteresis(Effect):
    """``y_i += h_i sign(dT/dt)``: the bias depends on whether the unit is heating (+h) or cooling (−h).

    The rate's sign is read from the temperature record over ``smooth_s`` (a held temperature: 0).
    """

    offset_si: ArrayLike = (0.0,) * 3
    smooth_s: float = 1.0
    name: ClassVar[str] = "temperature_hysteresis"
    stage: ClassVar[int] = 32

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset_si", _floats(self.offset_si, 3, "offset_si"))
        object.__setattr__(self, "smooth_s", float(self.smooth_s))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        sense = heating_sign(ctx.t_s, ctx.temperature(self.name), self.smooth_s)
        out: FloatArray = y + sense[:, None] * np.array(self.offset_si, dtype=np.float64)
        return out


def heating_sign(t_s: FloatArray, temp_c: FloatArray, smooth_s: float) -> FloatArray:
    """(N,) +1 where the temperature rises over ``smooth_s`` about each sample, −1 where it falls, 0 where it holds."""
    later = np.interp(t_s + 0.5 * smooth_s, t_s, temp_c)
    earlier = np.interp(t_s - 0.5 * smooth_s, t_s, temp_c)
    out: FloatArray = np.sign(later - earlier)
    return out


@dataclass(frozen=True)
class BiasInstability(Effect):
    """Correlated bias noise that does not average down; three independent parts per axis.

    * Gauss–Markov: stationary, standard deviation ``gm_sigma_si``, correlation
      time ``gm_tau_s``: ``β_k = φ β_{k−1} + w_k``, ``φ = exp(−Δt/τ)``,
      ``var w = σ²(1 − φ²)``, ``β_0`` drawn from the stationary law. Process
      ``j`` moves the bias along column ``j`` of ``gm_loading`` (3, 3), the
      identity by default (one process per axis): a process whose column has
      other non-zero entries is a wander common to several axes.
    * Random walk: ``random_walk_si_per_sqrt_s`` (SI/√s, the rate random walk
      coefficient K): ``β_k = β_{k−1} + K √Δt n_k``, ``β_0 = 0``.
    * Flicker (1/f) noise of bias-instability coefficient ``flicker_si`` (B of
      IEEE Std 952: two-sided PSD ``B² / (2π f)``, Allan deviation floor
      ``B·√(2 ln 2 / π) ≈ 0.664 B``): white noise of variance ``B²`` through
      Kasdin's (1995) fractional integrator ``h_0 = 1, h_k = h_{k−1} (k − ½) / k``,
      whose power gain ``|2 sin(π f Δt)|^−1 ≈ 1 / (2π f Δt)`` turns the white
      two-sided PSD ``B² Δt`` into ``B² / (2π f)`` below Nyquist; it starts at 0.
    """

    gm_sigma_si: ArrayLike = (0.0,) * 3
    gm_tau_s: ArrayLike = (100.0,) * 3
    random_walk_si_per_sqrt_s: ArrayLike = (0.0,) * 3
    flicker_si: ArrayLike = (0.0,) * 3
    gm_loading: ArrayLike = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    name: ClassVar[str] = "bias_instability"
    stage: ClassVar[int] = 33

    def __post_init__(self) -> None:
        for f in ("gm_sigma_si", "gm_tau_s", "random_walk_si_per_sqrt_s", "flicker_si"):
            values = _floats(getattr(self, f), 3, f)
            object.__setattr__(self, f, values)
            if min(values) < 0:
                raise ValueError(f"{f} must be non-negative, got {values!r}")
        object.__setattr__(self, "gm_loading", _float_rows(self.gm_loading, (3, 3), "gm_loading"))
        if np.min(self.gm_tau_s) <= 0:
            raise ValueError(f"gm_tau_s must be positive, got {self.gm_tau_s!r}")

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        from scipy.signal import fftconvolve, lfilter

        n = y.shape[0]
        dt = 1.0 / ctx.rate_hz
        beta = np.zeros_like(y)
        white = ctx.rng.standard_normal((3, 3, n))
        start = ctx.rng.standard_normal(3)
        flicker = np.array(self.flicker_si, dtype=np.float64)
        gm_sigma, gm_tau = (
            np.array(self.gm_sigma_si, dtype=np.float64),
            np.array(self.gm_tau_s, dtype=np.float64),
        )
        random_walk = np.array(self.random_walk_si_per_sqrt_s, dtype=np.float64)
        loading = np.array(self.gm_loading, dtype=np.float64)
        if flicker.any():
            kasdin = np.cumprod(np.concatenate([[1.0], (np.arange(1, n) - 0.5) / np.arange(1, n)]))
            beta += fftconvolve(flicker[:, None] * white[2], kasdin[None, :], axes=1)[:, :n].T
        for i in range(3):
            sigma, tau = float(gm_sigma[i]), float(gm_tau[i])
            if sigma > 0:
                phi = np.exp(-dt / tau)
                w = sigma * np.sqrt(1.0 - phi * phi) * white[0, i]
                process = lfilter([1.0], [1.0, -phi], w, zi=[phi * sigma * start[i]])[0]
                beta += process[:, None] * loading[:, i]
            k = float(random_walk[i])
            if k > 0:
                steps = k * np.sqrt(dt) * white[1, i]
                steps[0] = 0.0
                beta[:, i] += np.cumsum(steps)
        return y + beta


@dataclass(frozen=True)
class GSensitivity(Effect):
    """Gyro bias proportional to specific force (M4): ``y += G f_b``.

    ``coef_rps_per_mps2`` (3, 3): row ``i`` holds gyro ``i``'s ``[Bgx, Bgy, Bgz]``
    in rad/s per m/s².
    """

    coef_rps_per_mps2: ArrayLike = ((0.0,) * 3,) * 3
    name: ClassVar[str] = "g_sensitivity"
    stage: ClassVar[int] = 34
    triads: ClassVar[tuple[Triad, ...]] = (Triad.GYRO,)

    def __post_init__(self) -> None:
        object.__setattr__(
            self,
            "coef_rps_per_mps2",
            _float_rows(self.coef_rps_per_mps2, (3, 3), "coef_rps_per_mps2"),
        )

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        return y + ctx.specific_force_b_mps2 @ np.array(self.coef_rps_per_mps2, dtype=np.float64).T


@dataclass(frozen=True)
class WhiteNoise(Effect):
    """Additive white noise; per-sample standard deviation ``density·√rate_hz``.

    ``density_si_per_sqrt_hz`` (3,): SI/√Hz (m/s²/√Hz, or rad/s/√Hz = rad/√s,
    the angle random walk). ``correlation`` (3, 3): the correlation of the axes' noise at the same
    sample (identity: independent axes).
    """

    density_si_per_sqrt_hz: ArrayLike = (0.0,) * 3
    correlation: ArrayLike = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    name: ClassVar[str] = "white_noise"
    stage: ClassVar[int] = 40

    def __post_init__(self) -> None:
        density = _floats(self.density_si_per_sqrt_hz, 3, "density_si_per_sqrt_hz")
        object.__setattr__(self, "density_si_per_sqrt_hz", density)
        object.__setattr__(self, "correlation", _correlation_rows(self.correlation))
        if min(density) < 0:
            raise ValueError(f"noise density must be non-negative, got {density!r}")

    @classmethod
    def from_sample_sd(
        cls, sd_si: ArrayLike, rate_hz: float, correlation: ArrayLike | None = None
    ) -> WhiteNoise:
        """The noise whose per-sample standard deviation at ``rate_hz`` is ``sd_si`` (correlation: identity if None)."""
        density = np.asarray(sd_si, float) / np.sqrt(rate_hz)
        return cls(density) if correlation is None else cls(density, correlation)

    def sample_sd(self, rate_hz: float) -> FloatArray:
        """(3,) per-sample standard deviation at ``rate_hz``, SI."""
        return np.array(self.density_si_per_sqrt_hz, dtype=np.float64) * float(np.sqrt(rate_hz))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        n = _correlated_normals(ctx.rng, self.correlation, y.shape, axis=1)
        return y + self.sample_sd(ctx.rate_hz) * n


@dataclass(frozen=True)
class ColouredNoise(Effect):
    """Short-lag coloured noise: a sum of first-order Gauss–Markov terms per axis (a sensor's own filtering).

    ``sigma_si`` (3, m): per-sample sd of each term, SI; ``tau_s`` (3, m): its
    correlation time, s. Each term is ``β_k = φ β_{k−1} + w_k``,
    ``φ = exp(−Δt/τ)``, ``var w = σ²(1 − φ²)``, started from its stationary
    law, so every sample has the variance ``Σ_j σ_j²`` and a mean of ``n``
    samples averages down as white noise of variance ``Σ_j σ_j² (1 + φ_j)/(1 − φ_j)``
    for ``n ≫ τ/Δt`` (:func:`estimators.noise.fit_noise_colour` fits it). The
    same process as :class:`BiasInstability`'s Gauss–Markov part, kept apart
    from it: this is the noise a model has before any wander is named. ``correlation`` (3, 3): the
    correlation of the axes' driving noise, term by term (the terms' outputs have it at the same sample
    where the axes' correlation times agree; identity: independent axes).
    """

    sigma_si: ArrayLike = ((0.0,),) * 3
    tau_s: ArrayLike = ((1.0,),) * 3
    correlation: ArrayLike = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    name: ClassVar[str] = "coloured_noise"
    stage: ClassVar[int] = 41

    def __post_init__(self) -> None:
        sigma = np.asarray(self.sigma_si, dtype=float)
        sigma = np.broadcast_to(sigma, (3, sigma.size)) if sigma.ndim < 2 else sigma
        shape = (3, sigma.shape[-1])
        object.__setattr__(self, "sigma_si", _float_rows(sigma, shape, "sigma_si"))
        object.__setattr__(self, "tau_s", _float_rows(self.tau_s, shape, "tau_s"))
        object.__setattr__(self, "correlation", _correlation_rows(self.correlation))
        if np.min(self.sigma_si) < 0 or np.min(self.tau_s) <= 0:
            raise ValueError(
                f"sigma_si must be non-negative and tau_s positive, got {self.sigma_si!r}, {self.tau_s!r}"
            )

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        from scipy.signal import lfilter

        sigma = np.array(self.sigma_si, dtype=np.float64)
        phi = np.exp(-1.0 / (ctx.rate_hz * np.array(self.tau_s, dtype=np.float64)))
        white = _correlated_normals(ctx.rng, self.correlation, (*sigma.shape, y.shape[0]), axis=0)
        out = y.copy()
        for i, j in zip(*np.nonzero(sigma > 0), strict=True):
            w = sigma[i, j] * np.sqrt(1.0 - phi[i, j] ** 2) * white[i, j]
            w[0] = sigma[i, j] * white[i, j, 0]
            out[:, i] += lfilter([1.0], [1.0, -phi[i, j]], w)
        return out


class Rounding(StrEnum):
    """How a converter turns ``signal / k`` into a whole number of counts."""

    FLOOR = "floor"
    """M2's Entier: the largest integer ≤ the value. Averaged counts are low by ½."""
    TOWARD_ZERO = "toward_zero"
    """A signed pulse counter: the integer part. Averaged counts are ½ closer to zero."""
    NEAREST = "nearest"
    """Round half to even: no mean offset."""


def half_pulse_correction(mean_counts: FloatArray, rounding: Rounding) -> FloatArray:
    """Averaged counts → unbiased ``signal / k`` (M2: ``N̂ + 0.5·sign N̂`` for a signed counter).

    Valid when the noise before quantization is at least about one count (the
    rounding error is then uniform); for FLOOR the correction is ``+½`` for
    either sign, for TOWARD_ZERO it is M2's ``+½·sign(N̂)``, for NEAREST none.
    """
    n = np.asarray(mean_counts, dtype=np.float64)
    r = Rounding(rounding)
    if r is Rounding.FLOOR:
        return n + 0.5
    if r is Rounding.TOWARD_ZERO:
        return n + 0.5 * np.sign(n)
    return n


@dataclass(frozen=True)
class SpectralLine(Effect):
    """A sinusoid per axis, ``y_i += A_i sin(2π f_i t + φ_i)``: mains or rotor pickup (φ_i uniform from the stream)."""

    freq_hz: ArrayLike = (50.0,) * 3
    amplitude_si: ArrayLike = (0.0,) * 3
    name: ClassVar[str] = "spectral_line"
    stage: ClassVar[int] = 42

    def __post_init__(self) -> None:
        object.__setattr__(self, "freq_hz", _floats(self.freq_hz, 3, "freq_hz"))
        object.__setattr__(self, "amplitude_si", _floats(self.amplitude_si, 3, "amplitude_si"))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        phase = ctx.rng.uniform(0.0, 2.0 * np.pi, 3)
        arg = 2.0 * np.pi * ctx.t_s[:, None] * np.array(self.freq_hz, dtype=np.float64) + phase
        out: FloatArray = y + np.array(self.amplitude_si, dtype=np.float64) * np.sin(arg)
        return out


@dataclass(frozen=True)
class LowPass(Effect):
    """The firmware's anti-alias low-pass: a digital Butterworth filter of ``order`` and ``cutoff_hz`` on every axis.

    The bilinear design of :func:`scipy.signal.butter` (``|H(f)|² = 1/(1 + (tan(πf/f_s)/tan(πf_c/f_s))^{2n})``,
    unit gain at 0 Hz), run causally from its steady state on the first sample, as an IMU's digital
    filter runs; everything before it in the chain (the noise, a line) is filtered, the rail and the
    output grid come after it. ``cutoff_hz`` must lie below the session's Nyquist frequency.
    """

    order: int = 2
    cutoff_hz: float = 20.0
    name: ClassVar[str] = "lowpass"
    stage: ClassVar[int] = 44

    def __post_init__(self) -> None:
        if int(self.order) != self.order or not 1 <= self.order <= 8:
            raise ValueError(f"order must be an integer 1…8, got {self.order!r}")
        if not np.isfinite(self.cutoff_hz) or self.cutoff_hz <= 0:
            raise ValueError(f"cutoff_hz must be positive, got {self.cutoff_hz!r}")
        object.__setattr__(self, "order", int(self.order))
        object.__setattr__(self, "cutoff_hz", float(self.cutoff_hz))

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        from scipy.signal import butter, sosfilt, sosfilt_zi

        if self.cutoff_hz >= 0.5 * ctx.rate_hz:
            raise ValueError(
                f"a {self.cutoff_hz:g} Hz low-pass needs a rate above {2 * self.cutoff_hz:g} Hz, got {ctx.rate_hz:g}"
            )
        sos = butter(self.order, self.cutoff_hz, fs=ctx.rate_hz, output="sos")
        zi = sosfilt_zi(sos)[:, :, None] * y[0]
        out: FloatArray = sosfilt(sos, y, axis=0, zi=zi)[0]
        return out


@dataclass(frozen=True)
class Clipping(Effect):
    """The output held on the rails ``±rail_si`` per axis (the converter's full scale): ``y_i = clip(y_i, −r_i, r_i)``."""

    rail_si: ArrayLike = (np.inf,) * 3
    name: ClassVar[str] = "clipping"
    stage: ClassVar[int] = 48

    def __post_init__(self) -> None:
        rail = tuple(float(v) for v in np.broadcast_to(np.asarray(self.rail_si, float), (3,)))
        if min(rail) <= 0 or any(np.isnan(rail)):
            raise ValueError(f"clipping rail_si must be positive, got {rail!r}")
        object.__setattr__(self, "rail_si", rail)

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        r = np.array(self.rail_si, dtype=np.float64)
        out: FloatArray = np.clip(y, -r, r)
        return out


@dataclass(frozen=True)
class Quantization(Effect):
    """Output on a grid of whole counts (M2): ``N = round(y / k)``, output ``N·k``.

    ``step_si`` (3,) is the count size ``k`` per axis (SI per count, M2's k*);
    ``rounding`` picks the converter (:class:`Rounding`; FLOOR is M2's Entier).
    The output stays in SI on the grid ``k·ℤ``; :func:`half_pulse_correction`
    removes the mean rounding offset from averaged counts.
    """

    step_si: ArrayLike = (1.0,) * 3
    rounding: Rounding = Rounding.FLOOR
    name: ClassVar[str] = "quantization"
    stage: ClassVar[int] = 50

    def __post_init__(self) -> None:
        step = _floats(self.step_si, 3, "step_si")
        object.__setattr__(self, "step_si", step)
        object.__setattr__(self, "rounding", Rounding(self.rounding))
        if min(step) <= 0:
            raise ValueError(f"quantization step_si must be positive, got {step!r}")

    def counts(self, y: FloatArray) -> FloatArray:
        """(N, 3) whole counts of the signal ``y`` (SI)."""
        v: FloatArray = y / np.array(self.step_si, dtype=np.float64)
        if self.rounding is Rounding.FLOOR:
            return np.floor(v)
        if self.rounding is Rounding.TOWARD_ZERO:
            return np.trunc(v)
        return np.round(v)

    def apply(self, y: FloatArray, ctx: EffectContext) -> FloatArray:
        return self.counts(y) * np.array(self.step_si, dtype=np.float64)


# --- environment effects (change the truth, not a sensor) ----------------------


@dataclass(frozen=True)
class EnvironmentEffect(abc.ABC):
    """An effect on the true motion or site rather than on one triad."""

    name: ClassVar[str]

    def gravity_delta_mps2(self) -> float:
        """How much the true local gravity exceeds the assumed one, m/s²."""
        return 0.0

    def perturb(self, motion: Motion, rng: np.random.Generator) -> Motion:
        """The true motion with this effect (default: unchanged)."""
        return motion


@dataclass(frozen=True)
class GravityMismatch(EnvironmentEffect):
    """The true local gravity is the assumed one plus ``delta_mps2``.

    The session spec's gravity is what a user would configure; the truth's
    ``gravity_true_mps2`` drives the physics. Against the assumed value this
    looks like a common scale error ``≈ delta / g`` of the accelerometers: it
    is identifiable only against a passport (or a known reference).
    """

    delta_mps2: float = 0.0
    name: ClassVar[str] = "gravity_mismatch"

    def __post_init__(self) -> None:
        if not np.isfinite(self.delta_mps2):
            raise ValueError(f"delta_mps2 must be finite, got {self.delta_mps2!r}")

    def gravity_delta_mps2(self) -> float:
        return float(self.delta_mps2)


@dataclass(frozen=True)
class NonstaticPositions(EnvironmentEffect):
    """Small motion inside nominally static intervals (hand-held, soft table, vibration).

    In every static interval the attitude wobbles by windowed sinusoids
    (``n_components`` per axis, log-uniform frequencies in ``band_hz``) of RMS
    ``angle_rms_rad`` about each body axis, and the unit translates with
    acceleration RMS ``accel_rms_mps2`` per navigation axis; both fade in and
    out over ``ramp_s``. The rates are the exact derivatives of the wobble, so
    the truth stays consistent; the static flags stay as scheduled.
    """

    angle_rms_rad: float = 1.0e-4
    accel_rms_mps2: float = 0.0
    band_hz: Floats = (0.1, 5.0)
    n_components: int = 4
    ramp_s: float = 0.5
    name: ClassVar[str] = "nonstatic_positions"

    def __post_init__(self) -> None:
        if not (self.angle_rms_rad >= 0 and self.accel_rms_mps2 >= 0):
            raise ValueError(f"nonstatic_positions amplitudes must be non-negative, got {self!r}")
        object.__setattr__(self, "band_hz", _floats(self.band_hz, 2, "band_hz"))

    def perturb(self, motion: Motion, rng: np.random.Generator) -> Motion:
        mat = motion.mat_nb.copy()
        rate = motion.rate_nb_b_rps.copy()
        acc = motion.accel_n_mps2.copy()
        dt = float(motion.t_s[1] - motion.t_s[0]) if motion.t_s.size > 1 else 1.0
        for j in range(int(motion.position_index.max()) + 1):
            idx = np.flatnonzero(motion.position_index == j)
            tau = (idx - idx[0]) * dt
            length = idx.size * dt
            amp, freq, phase = random_sinusoids(
                rng, 3, self.n_components, self.angle_rms_rad, self.band_hz
            )
            dev, dev_rate = angle_excursion(tau, length, self.ramp_s, amp, freq, phase)
            mat[idx] = mat[idx] @ dev
            rate[idx] += dev_rate
            aamp, afreq, aphase = random_sinusoids(
                rng, 3, self.n_components, self.accel_rms_mps2, self.band_hz
            )
            acc[idx] += displacement_accel(tau, length, self.ramp_s, aamp, afreq, aphase)
        return replace(motion, mat_nb=mat, rate_nb_b_rps=rate, accel_n_mps2=acc)


EFFECTS: dict[str, type[Effect] | type[EnvironmentEffect]] = {
    cls.name: cls
    for cls in (
        NonOrthogonality,
        NonOrthogonalityChange,
        ScaleNonlinearity,
        CrossAxisNonlinearity,
        ScaleFactor,
        TemperatureScale,
        Bias,
        BiasDrift,
        BiasStep,
        TemperatureBias,
        TemperatureHysteresis,
        BiasInstability,
        GSensitivity,
        WhiteNoise,
        ColouredNoise,
        SpectralLine,
        LowPass,
        Clipping,
        Quantization,
        GravityMismatch,
        NonstaticPositions,
    )
}
"""Every effect class by its name (the names of the model audit, issue 4)."""


def make_effect(name: str, params: dict[str, Any]) -> Effect | EnvironmentEffect:
    """The effect called ``name`` with ``params`` (its dataclass fields; lists for arrays).

    The inverse of :func:`effect_params`. Unknown names or fields are a ``ValueError``.
    """
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r} (known: {', '.join(sorted(EFFECTS))})")
    cls = EFFECTS[name]
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(
            f"effect {name}: unknown parameter {unknown[0]!r} (known: {', '.join(sorted(known))})"
        )
    return cls(**params)


def effect_params(effect: Effect | EnvironmentEffect) -> dict[str, Any]:
    """The parameters of ``effect`` as plain JSON/TOML types (tuples become lists, enums their value)."""

    def plain(v: Any) -> Any:
        if isinstance(v, Enum):
            return v.value
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v

    return {f.name: plain(getattr(effect, f.name)) for f in fields(effect)}


# --- models -------------------------------------------------------------------

PARAMETER_EFFECT = {0: Bias, 1: ScaleFactor, 2: NonOrthogonality}
"""Which baseline effect carries parameters 0–2, 3–5, 6–8 (``index // 3``)."""


@dataclass(frozen=True)
class TriadErrorModel:
    """The ordered effects of one triad (stages non-decreasing, names unique)."""

    effects: tuple[Effect, ...] = ()

    def __post_init__(self) -> None:
        effs = tuple(self.effects)
        for e in effs:
            if not isinstance(e, Effect):
                raise ValueError(f"not a triad effect: {e!r}")
        names = [e.name for e in effs]
        if len(set(names)) != len(names):
            raise ValueError(f"each effect may appear once per triad, got {names}")
        stages = [e.stage for e in effs]
        if stages != sorted(stages):
            raise ValueError(f"effects must be in signal-path order (by stage), got {names}")
        object.__setattr__(self, "effects", effs)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    @overload
    def find(self, name: type[_EffectT]) -> _EffectT | None: ...
    @overload
    def find(self, name: str) -> Effect | None: ...
    def find(self, name: type[_EffectT] | str) -> _EffectT | Effect | None:
        """The effect of class ``name`` (typed) or called ``name``, or None."""
        key = name if isinstance(name, str) else name.name
        return next((e for e in self.effects if e.name == key), None)

    def with_effect(self, effect: Effect) -> TriadErrorModel:
        """A model with ``effect`` added at its stage, replacing one of the same name."""
        kept = [e for e in self.effects if e.name != effect.name]
        at = next((k for k, e in enumerate(kept) if e.stage > effect.stage), len(kept))
        return TriadErrorModel((*tuple(kept[:at]), effect, *tuple(kept[at:])))

    def without(self, name: str) -> TriadErrorModel:
        """A model without the effect called ``name`` (unchanged if absent)."""
        return TriadErrorModel(tuple(e for e in self.effects if e.name != name))

    def nine_params(self, reference: float) -> FloatArray:
        """(9,) the exact ``[b, e, d]`` of :mod:`estimators.conventions` (absent effects are zero).

        ``reference`` is the triad's true scalar reference (g in m/s² or Ω in rad/s).
        """
        bias = self.find(Bias)
        scale = self.find(ScaleFactor)
        nonorth = self.find(NonOrthogonality)
        return nine_params(
            np.zeros(3) if bias is None else np.array(bias.bias_si) / reference,
            np.zeros(3) if scale is None else np.array(scale.scale_err),
            np.eye(3) if nonorth is None else nonorth.axes,
        )


@dataclass(frozen=True)
class ErrorModel:
    """Both triads' effect chains and the environment effects."""

    accel: TriadErrorModel = field(default_factory=TriadErrorModel)
    gyro: TriadErrorModel = field(default_factory=TriadErrorModel)
    environment: tuple[EnvironmentEffect, ...] = ()

    def __post_init__(self) -> None:
        for triad in Triad:
            for e in self.triad(triad).effects:
                if triad not in e.triads:
                    raise ValueError(f"effect {e.name!r} does not apply to the {triad.value} triad")
        env = tuple(self.environment)
        for env_effect in env:
            if not isinstance(env_effect, EnvironmentEffect):
                raise ValueError(f"not an environment effect: {env_effect!r}")
        names = [e.name for e in env]
        if len(set(names)) != len(names):
            raise ValueError(f"each environment effect may appear once, got {names}")
        object.__setattr__(self, "environment", env)

    def triad(self, triad: Triad) -> TriadErrorModel:
        return self.accel if Triad(triad) is Triad.ACCEL else self.gyro

    def with_effect(
        self, effect: Effect | EnvironmentEffect, triad: Triad | None = None
    ) -> ErrorModel:
        """A model with ``effect`` added (replacing one of the same name).

        Environment effects need no triad; triad effects need ``triad``.
        """
        if isinstance(effect, EnvironmentEffect):
            kept = tuple(e for e in self.environment if e.name != effect.name)
            return replace(self, environment=(*kept, effect))
        if triad is None:
            raise ValueError(f"effect {effect.name!r} needs the triad it applies to")
        if Triad(triad) is Triad.ACCEL:
            return replace(self, accel=self.accel.with_effect(effect))
        return replace(self, gyro=self.gyro.with_effect(effect))

    @property
    def gravity_delta_mps2(self) -> float:
        return float(sum(e.gravity_delta_mps2() for e in self.environment))
