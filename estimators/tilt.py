"""Passport of a single-axis accelerometer on a tilt table (methods.md M2).

Uspensky & Khatsko's bench: a table tilts the sensitive axis by set angles
``α``; each 50 Hz sample is a whole number of pulses (M2 eq. 1)::

    N* = Entier[(g·sin α* + δa* + ξ) / k*]

``Entier`` is taken as the integer part towards zero (a signed pulse counter,
:attr:`Rounding.TOWARD_ZERO` of the simulator's quantizer): that is the
quantizer whose cell centre is ``N* + 0.5·sign N*``, the paper's half-pulse
correction (eq. 3); other converters have their own correction
(:func:`estimators.sim.half_pulse_correction`). Averaging ``N*`` over 30 s
(with noise of at least about half a pulse to dither the quantizer) and
adding the half pulse gives an unbiased count, and with ``α* = α + δα``,
``k* = k0 (1 + Δk)`` the linearized equation per angle is (eq. 6)::

    δa + g·cos α·δα − g·sin α·Δk = (N̂* + 0.5·sign N̂*)·k0 − g·sin α

solved by least squares for ``θ = [δa, δα, Δk]`` (m/s², rad, dimensionless).
``k0 = 2g / (N↑ − N↓)`` (eq. 7) comes from the raw averaged counts with the
axis pointing up and down; with a truncating converter that span is one
pulse short, which ``Δk`` absorbs (``k* = k0 (1 + Δk)`` stays right).

The credibility checks (stabilization, residuals, reproducibility over runs)
are those of :mod:`estimators.repeatability`. A bench simulator specific to
this method (:class:`TiltBench`, :func:`simulate_runs`) reproduces the paper's
protocol: 60 angles in 1° steps, 50 Hz, 30 s averages, several runs; it
quantizes with the simulator's :class:`~estimators.sim.Quantization`.
:func:`bench_session` and :func:`run_from_session` turn a run into a session
file's samples and back, so the same passport comes from a user's CSV.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import FloatArray, IntArray
from estimators.conventions import (
    AXES,
    N_PARAMS,
    STANDARD_GRAVITY_MPS2,
    Grade,
    Triad,
    normal_gravity_mps2,
)
from estimators.ninepar import Method
from estimators.passport import (
    Provenance,
    TriadPassport,
    default_tolerance_rule,
    reference_kind,
)
from estimators.plateaus import find_plateaus
from estimators.repeatability import (
    LinearFit,
    RunEstimate,
    RunSpread,
    Stabilization,
    fit_linear,
    run_spread,
    stabilization,
    t_quantile,
)
from estimators.session import ImuSession
from estimators.sim.errors import Quantization, Rounding, half_pulse_correction

TILT_PARAM_NAMES = ("zero_offset_mps2", "misalignment_rad", "scale_error")
"""Order of the estimated parameters ``[δa, δα, Δk]`` (M2 eq. 6)."""

TILT_PARAM_SYMBOLS = ("δa", "δα", "Δk")

MIN_ANGLES = 4
"""Three unknowns plus one equation to estimate the noise level."""

KHARKIV_GRAVITY_MPS2 = normal_gravity_mps2(50.0, 150.0)
"""Normal gravity at the paper's laboratory (Kharkiv, 50.0° N, about 150 m), m/s²."""


class HalfPulse(StrEnum):
    """Whether the averaged counts get the half-pulse correction of M2 eq. 3."""

    APPLY = "apply"
    OMIT = "omit"


def nominal_scale(counts_up: float, counts_down: float, gravity_mps2: float) -> float:
    """``k0 = 2g / (N↑ − N↓)`` (M2 eq. 7), m/s² per pulse, from averaged raw counts."""
    span = float(counts_up) - float(counts_down)
    if not span > 0:
        raise ValueError(
            f"the axis-up count ({counts_up:g}) must exceed the axis-down count ({counts_down:g}): is the axis reversed?"
        )
    return 2.0 * float(gravity_mps2) / span


@dataclass(frozen=True, kw_only=True)
class TiltRun:
    """One run (one power-up of the sensor) of the tilt protocol.

    Attributes
    ----------
    angles_rad : (M,) table angles as set, rad, in the order measured.
    counts_mean : (M,) averaged raw counts ``N̂*`` at each angle, pulses.
    counts_std : (M,) standard deviation of the single samples at each angle, pulses.
    n_samples : (M,) number of samples averaged per angle.
    counts_up, counts_down : averaged raw counts with the axis up and down, pulses.
    rounding : how the converter makes whole pulses (selects the half-pulse correction).
    """

    angles_rad: FloatArray
    counts_mean: FloatArray
    counts_std: FloatArray
    n_samples: IntArray
    counts_up: float
    counts_down: float
    rounding: Rounding = Rounding.TOWARD_ZERO

    def __post_init__(self) -> None:
        a = np.asarray(self.angles_rad, dtype=float)
        n = np.asarray(self.counts_mean, dtype=float)
        if (
            a.ndim != 1
            or n.shape != a.shape
            or np.shape(self.counts_std) != a.shape
            or np.shape(self.n_samples) != a.shape
        ):
            raise ValueError(
                f"angles, counts, their spread and sample numbers must be (M,) arrays of one length, got "
                f"{a.shape}, {n.shape}, {np.shape(self.counts_std)}, {np.shape(self.n_samples)}"
            )
        if a.size < MIN_ANGLES:
            raise ValueError(
                f"a tilt run needs at least {MIN_ANGLES} angles (3 unknowns δa, δα, Δk and the noise level), got {a.size}"
            )
        distinct = np.unique(np.round(a, 9)).size
        if distinct < 3:
            raise ValueError(
                f"a tilt run needs at least 3 different angles to separate δa, δα and Δk, got {distinct}"
            )
        if np.any(np.abs(a) >= np.pi / 2):
            raise ValueError("table angles must lie within (−90°, 90°)")
        if not (
            np.all(np.isfinite(n)) and np.isfinite(self.counts_up) and np.isfinite(self.counts_down)
        ):
            raise ValueError("tilt counts must be finite")
        object.__setattr__(self, "angles_rad", a)
        object.__setattr__(self, "counts_mean", n)
        object.__setattr__(self, "counts_std", np.asarray(self.counts_std, dtype=float))
        object.__setattr__(self, "n_samples", np.asarray(self.n_samples, dtype=int))
        object.__setattr__(self, "rounding", Rounding(self.rounding))

    def corrected(self, correction: HalfPulse) -> FloatArray:
        """(M,) averaged counts with the converter's half-pulse correction (M2 eq. 3), or raw with OMIT."""
        if HalfPulse(correction) is HalfPulse.OMIT:
            return self.counts_mean
        return half_pulse_correction(self.counts_mean, self.rounding)


def tilt_equations(
    run: TiltRun, k0_mps2: float, gravity_mps2: float, *, correction: HalfPulse = HalfPulse.APPLY
) -> tuple[FloatArray, FloatArray]:
    """The design ``H`` (M, 3) and right-hand side ``y`` (M,), m/s², of M2 eq. 6."""
    a = run.angles_rad
    g = float(gravity_mps2)
    h = np.column_stack([np.ones_like(a), g * np.cos(a), -g * np.sin(a)])
    return h, run.corrected(correction) * k0_mps2 - g * np.sin(a)


def modelled_counts(
    angles_rad: FloatArray, params: FloatArray, k0_mps2: float, gravity_mps2: float
) -> FloatArray:
    """Noise-free (unquantized) counts ``(g sin(α + δα) + δa) / (k0 (1 + Δk))`` of M2 eq. 3, pulses."""
    da, dalpha, dk = np.asarray(params, dtype=float)
    counts: FloatArray = (gravity_mps2 * np.sin(np.asarray(angles_rad) + dalpha) + da) / (
        k0_mps2 * (1.0 + dk)
    )
    return counts


@dataclass(frozen=True)
class TiltFit:
    """Estimate of one run (M2 eq. 6) with its stabilization (check 1) and residuals (check 2).

    Attributes
    ----------
    fit : values ``[δa, δα, Δk]`` (m/s², rad, 1), covariance, residuals in m/s².
    residuals_pulses : (M,) measured corrected counts minus the counts modelled with the estimate.
    stabilization : estimates from the first m equations.
    """

    fit: LinearFit
    residuals_pulses: FloatArray
    stabilization: Stabilization


def fit_run(
    run: TiltRun,
    k0_mps2: float,
    gravity_mps2: float,
    *,
    correction: HalfPulse = HalfPulse.APPLY,
    level: float = 0.95,
) -> TiltFit:
    """Least squares of M2 eq. 6 for one run; the noise level comes from the residuals."""
    h, y = tilt_equations(run, k0_mps2, gravity_mps2, correction=correction)
    fit = fit_linear(h, y, names=TILT_PARAM_SYMBOLS)
    resid = run.corrected(correction) - modelled_counts(
        run.angles_rad, fit.values, k0_mps2, gravity_mps2
    )
    return TiltFit(
        fit=fit,
        residuals_pulses=resid,
        stabilization=stabilization(h, y, level=level, names=TILT_PARAM_SYMBOLS),
    )


@dataclass(frozen=True)
class TiltErrors:
    """RMS over all runs and angles of the measurement error, in pulses (the paper's Fig. 4).

    Attributes
    ----------
    raw : averaged counts against ``g·sin α / k0`` (no correction at all).
    half_pulse : with the half-pulse correction only (the sensor's own errors).
    in_run : residuals of each run's own fit.
    passport : with the passport values (from the intersection) applied to every run.
    """

    raw: float
    half_pulse: float
    in_run: float
    passport: float


@dataclass(frozen=True)
class TiltPassportResult:
    """The whole M2 procedure over several runs.

    Attributes
    ----------
    gravity_mps2 : local gravity used, m/s².
    k0_mps2 : nominal scale from the up/down counts of all runs (eq. 7), m/s² per pulse.
    correction : whether the half-pulse correction was applied.
    fits : one :class:`TiltFit` per run.
    spread : per-run intervals, across-run statistics, the intersection and the passport value.
    scale_mps2 : the passport pulse weight ``k* = k0 (1 + Δk)``, m/s² per pulse.
    errors : measurement error before and after compensation.
    noise_pulses : median per-sample standard deviation of the counts, pulses.
    """

    gravity_mps2: float
    k0_mps2: float
    correction: HalfPulse
    fits: tuple[TiltFit, ...]
    spread: RunSpread
    scale_mps2: float
    errors: TiltErrors
    noise_pulses: float


def tilt_passport(
    runs: Sequence[TiltRun],
    *,
    gravity_mps2: float,
    correction: HalfPulse = HalfPulse.APPLY,
    level: float = 0.95,
) -> TiltPassportResult:
    """Passport of one accelerometer axis from repeated tilt runs (M2 steps 2–4).

    ``k0`` comes from the pooled up/down counts (eq. 7), each run is solved by
    least squares (eq. 6), and :func:`estimators.repeatability.run_spread`
    intersects the runs' confidence intervals (``level``) into the passport
    value. At least two runs are needed for the reproducibility check.
    """
    runs = tuple(runs)
    if len(runs) < 2:
        raise ValueError(
            f"the tilt passport needs at least 2 runs to check reproducibility, got {len(runs)}"
        )
    g = float(gravity_mps2)
    k0 = nominal_scale(
        float(np.mean([r.counts_up for r in runs])),
        float(np.mean([r.counts_down for r in runs])),
        g,
    )
    fits = tuple(fit_run(r, k0, g, correction=correction, level=level) for r in runs)
    spread = run_spread(
        [RunEstimate.from_fit(f.fit) for f in fits], names=TILT_PARAM_NAMES, level=level
    )

    def rms(parts: list[FloatArray]) -> float:
        v = np.concatenate(parts)
        return float(np.sqrt(np.mean(v * v)))

    nominal = [g * np.sin(r.angles_rad) / k0 for r in runs]
    errors = TiltErrors(
        raw=rms([r.counts_mean - n for r, n in zip(runs, nominal, strict=True)]),
        half_pulse=rms(
            [r.corrected(HalfPulse.APPLY) - n for r, n in zip(runs, nominal, strict=True)]
        ),
        in_run=rms([f.residuals_pulses for f in fits]),
        passport=rms(
            [
                r.corrected(correction) - modelled_counts(r.angles_rad, spread.value, k0, g)
                for r in runs
            ]
        ),
    )
    return TiltPassportResult(
        gravity_mps2=g,
        k0_mps2=k0,
        correction=HalfPulse(correction),
        fits=fits,
        spread=spread,
        scale_mps2=k0 * (1.0 + float(spread.value[2])),
        errors=errors,
        noise_pulses=float(np.median(np.concatenate([r.counts_std for r in runs]))),
    )


def half_pulse_bias(
    runs: Sequence[TiltRun], *, gravity_mps2: float, level: float = 0.95
) -> FloatArray:
    """(3,) passport values without the half-pulse correction minus those with it (``[δa, δα, Δk]``).

    What M2 eq. 3 protects against: with every angle on one side of zero the
    missing half pulse is a constant and lands entirely in ``δa`` (−½ pulse for
    a truncating converter); with angles of both signs it is an odd step that
    also biases ``Δk``.
    """
    with_it = tilt_passport(
        runs, gravity_mps2=gravity_mps2, correction=HalfPulse.APPLY, level=level
    )
    without = tilt_passport(runs, gravity_mps2=gravity_mps2, correction=HalfPulse.OMIT, level=level)
    return without.spread.value - with_it.spread.value


def tilt_triad_passport(
    result: TiltPassportResult,
    *,
    axis: int,
    lsb_mps2: float,
    sample_rate_hz: float,
    grade: Grade = Grade.MEMS,
) -> TriadPassport:
    """The accelerometer :class:`TriadPassport` holding one calibrated axis (M2 → M1 format).

    The session's SI output of the axis is ``N·lsb_mps2`` (whole pulses times
    the pulse weight the logger used), so in the convention of
    :mod:`estimators.conventions` the axis has scale error ``e = lsb/k* − 1``
    and normalized bias ``b = δa·(lsb/k*)/g``. Their nominal values are the
    passport values of the run intersection, their intervals its bounds, their
    tolerance the envelope of the run intervals (the unit's measured
    reproducibility). A parameter whose run intervals do not intersect is
    marked not observable, so the diagnosis does not judge it. The other
    seven parameters were not calibrated: nominal 0, the grade's default
    tolerance, not observable. ``δα`` belongs to the bench, not the sensor,
    and is not in the passport.
    """
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    if not lsb_mps2 > 0:
        raise ValueError(f"lsb_mps2 must be positive, got {lsb_mps2!r}")
    sp = result.spread
    g, k0 = result.gravity_mps2, result.k0_mps2
    z = float(t_quantile(sp.level, np.inf))

    def e_of(dk: float) -> float:
        return float(lsb_mps2 / (k0 * (1.0 + dk)) - 1.0)

    def b_of(da: float, dk: float) -> float:
        return float(da * (lsb_mps2 / (k0 * (1.0 + dk))) / g)

    dk = float(sp.value[2])
    e_lo, e_hi = sorted((e_of(sp.common_upper[2]), e_of(sp.common_lower[2])))
    b_lo, b_hi = b_of(sp.common_lower[0], dk), b_of(sp.common_upper[0], dk)
    if not sp.reproducible[2]:
        e_lo, e_hi = sorted(
            (e_of(sp.value[2] + sp.tolerance[2]), e_of(sp.value[2] - sp.tolerance[2]))
        )
    if not sp.reproducible[0]:
        b_lo, b_hi = (
            b_of(sp.value[0] - sp.tolerance[0], dk),
            b_of(sp.value[0] + sp.tolerance[0], dk),
        )
    nominal = np.zeros(N_PARAMS)
    nominal[axis], nominal[3 + axis] = b_of(sp.value[0], dk), e_of(dk)
    rule = default_tolerance_rule(Triad.ACCEL, grade, g)
    tolerance = rule.floor.copy()
    tolerance[axis] = b_of(sp.tolerance[0], dk)
    tolerance[3 + axis] = abs(e_of(dk + sp.tolerance[2]) - e_of(dk))
    ci_low, ci_high = nominal.copy(), nominal.copy()
    ci_low[axis], ci_high[axis] = b_lo, b_hi
    ci_low[3 + axis], ci_high[3 + axis] = e_lo, e_hi
    sigma = np.zeros(N_PARAMS)
    sigma[axis] = (b_hi - b_lo) / (2.0 * z)
    sigma[3 + axis] = (e_hi - e_lo) / (2.0 * z)
    observable = np.zeros(N_PARAMS, dtype=bool)
    observable[axis], observable[3 + axis] = bool(sp.reproducible[0]), bool(sp.reproducible[2])
    noise = np.zeros(3)
    noise[axis] = result.noise_pulses * lsb_mps2 / g
    n_equations = int(sum(f.fit.residuals.size for f in result.fits))
    return TriadPassport(
        triad=Triad.ACCEL,
        reference=g,
        reference_kind=reference_kind(Triad.ACCEL),
        nominal=nominal,
        tolerance=tolerance,
        sigma=sigma,
        observable=observable,
        noise_std=noise,
        sample_rate_hz=sample_rate_hz,
        provenance=Provenance(
            Method.LINEAR,
            n_equations,
            sp.level,
            ci_low,
            ci_high,
            procedure=f"M2 tilt table, axis {'xyz'[axis]}",
            n_runs=len(result.fits),
            # Only this axis' zero and scale were tested; the other seven entries are not claimed.
            reproducible=observable.copy(),
        ),
    )


# --- the bench simulator ------------------------------------------------------------------------


def _paper_angles_deg() -> tuple[float, ...]:
    return tuple(float(a) for a in range(5, 65))


@dataclass(frozen=True, kw_only=True)
class TiltBench:
    """The paper's bench and one simulated ADXL203-like unit (M2).

    Defaults: true pulse weight ``k*`` 0.00769 m/s² (the paper's k0); the
    logger writes SI values with a nominal pulse weight of 0.0077 m/s²; zero
    offset 0.37 pulse (the paper's unit 2, reading its table in pulses); white
    noise 0.0068 m/s² per sample (110 µg/√Hz over a 25 Hz single-pole
    bandwidth, so more than half a pulse: the quantizer is dithered); a
    truncating converter (eq. 3); 60 angles 5°…64° in 1° steps (inside the
    table's ±65°; away from 0° the sign in eq. 3 is never in doubt, and cos α
    spans 1…0.44 so δa and δα separate); a mounting/levelling error δα of 0.8′
    and a random setting error of each angle of 0.7′ (the table sets angles
    "to a few arc minutes"); 50 Hz, 30 s per angle, 60 s up and down; 5 runs,
    each a new power-up whose zero offset repeats to 0.1 pulse.

    Attributes (SI)
    ---------------
    gravity_mps2, pulse_mps2 (k*), lsb_mps2 (the logger's nominal pulse
    weight), zero_offset_mps2 (δa*), turn_on_sigma_mps2, noise_mps2 (ξ per
    sample), misalignment_rad (δα), setting_sigma_rad, angles_deg (the set
    angles, degrees, in measuring order), rounding, rate_hz, average_s,
    updown_s, n_runs.
    """

    gravity_mps2: float = KHARKIV_GRAVITY_MPS2
    pulse_mps2: float = 0.00769
    lsb_mps2: float = 0.0077
    zero_offset_mps2: float = 0.37 * 0.00769
    turn_on_sigma_mps2: float = 0.1 * 0.00769
    noise_mps2: float = 0.0068
    misalignment_rad: float = float(np.radians(0.8 / 60.0))
    setting_sigma_rad: float = float(np.radians(0.7 / 60.0))
    angles_deg: tuple[float, ...] = field(default_factory=_paper_angles_deg)
    rounding: Rounding = Rounding.TOWARD_ZERO
    rate_hz: float = 50.0
    average_s: float = 30.0
    updown_s: float = 60.0
    n_runs: int = 5

    def __post_init__(self) -> None:
        for name in ("gravity_mps2", "pulse_mps2", "lsb_mps2", "rate_hz", "average_s", "updown_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"TiltBench.{name} must be positive, got {getattr(self, name)!r}")
        for name in ("turn_on_sigma_mps2", "noise_mps2", "setting_sigma_rad"):
            if not getattr(self, name) >= 0:
                raise ValueError(
                    f"TiltBench.{name} must be non-negative, got {getattr(self, name)!r}"
                )
        object.__setattr__(self, "angles_deg", tuple(float(a) for a in self.angles_deg))
        object.__setattr__(self, "rounding", Rounding(self.rounding))
        if self.n_runs < 1:
            raise ValueError(f"TiltBench.n_runs must be at least 1, got {self.n_runs}")

    @property
    def samples_per_angle(self) -> int:
        return max(1, round(self.average_s * self.rate_hz))

    @property
    def samples_updown(self) -> int:
        return max(1, round(self.updown_s * self.rate_hz))

    @property
    def true_scale_error(self) -> float:
        """``Δk`` of the true pulse weight relative to the noise-free eq. 7 value of ``k0``.

        The dithered raw counts are low by the converter's half-pulse offset,
        so the up/down span is ``2g/k*`` minus the difference of the two
        offsets (one pulse for a truncating converter, none for floor or
        nearest rounding).
        """
        g, k = self.gravity_mps2, self.pulse_mps2
        exact = np.array([g / k, -g / k])
        offset = half_pulse_correction(exact, self.rounding) - exact
        k0 = 2.0 * g / (2.0 * g / k - (offset[0] - offset[1]))
        return float(k / k0 - 1.0)

    @property
    def true_params(self) -> FloatArray:
        """(3,) ``[δa, δα, Δk]`` that the method should recover (Δk as :attr:`true_scale_error`)."""
        return np.array([self.zero_offset_mps2, self.misalignment_rad, self.true_scale_error])


@dataclass(frozen=True)
class TiltSamples:
    """Raw counts of one simulated run: ``up`` (n_updown,), ``down`` (n_updown,), ``angles`` (M, n_per_angle).

    ``zero_offset_mps2`` is the run's true zero offset (with its turn-on part).
    """

    up: FloatArray
    down: FloatArray
    angles: FloatArray
    zero_offset_mps2: float


def _whole_pulses(quantizer: Quantization, x_mps2: FloatArray) -> FloatArray:
    """Counts of any-shaped ``x_mps2`` through the simulator's quantizer (same step on its three axes).

    The quantizer works on (N, 3) triad samples; one axis's samples are packed
    three to a row (padded) so each value is quantized once.
    """
    flat = np.ravel(x_mps2)
    pad = (-flat.size) % 3
    counts = quantizer.counts(np.concatenate([flat, np.zeros(pad)]).reshape(-1, 3)).ravel()
    return counts[: flat.size].reshape(np.shape(x_mps2))


def simulate_samples(bench: TiltBench, rng: np.random.Generator) -> list[TiltSamples]:
    """Whole-pulse samples (M2 eq. 1) of every run of ``bench``.

    Per run: a new turn-on zero offset; per angle and run: a new table setting
    error; per sample: white noise. δα is the same in every run (one
    installation of the module on the table).
    """
    g = bench.gravity_mps2
    quantizer = Quantization(step_si=(bench.pulse_mps2,) * 3, rounding=bench.rounding)
    set_rad = np.radians(np.asarray(bench.angles_deg))
    out = []
    for _ in range(bench.n_runs):
        da = bench.zero_offset_mps2 + bench.turn_on_sigma_mps2 * rng.standard_normal()
        true_rad = (
            set_rad
            + bench.misalignment_rad
            + bench.setting_sigma_rad * rng.standard_normal(set_rad.size)
        )

        def pulses(specific_force_mps2: ArrayLike, n: int, da: float = da) -> FloatArray:
            f = np.asarray(specific_force_mps2, dtype=float)[..., None]
            return _whole_pulses(
                quantizer, f + da + bench.noise_mps2 * rng.standard_normal((*f.shape[:-1], n))
            )

        out.append(
            TiltSamples(
                up=pulses(g, bench.samples_updown),
                down=pulses(-g, bench.samples_updown),
                angles=pulses(g * np.sin(true_rad), bench.samples_per_angle),
                zero_offset_mps2=float(da),
            )
        )
    return out


def runs_from_samples(bench: TiltBench, samples: Sequence[TiltSamples]) -> list[TiltRun]:
    """Average the samples of each run into :class:`TiltRun` (the paper's 30 s and 60 s averages)."""
    set_rad = np.radians(np.asarray(bench.angles_deg))
    return [
        TiltRun(
            angles_rad=set_rad,
            counts_mean=s.angles.mean(axis=1),
            counts_std=s.angles.std(axis=1, ddof=1),
            n_samples=np.full(set_rad.size, s.angles.shape[1]),
            counts_up=float(s.up.mean()),
            counts_down=float(s.down.mean()),
            rounding=bench.rounding,
        )
        for s in samples
    ]


def simulate_runs(bench: TiltBench, rng: np.random.Generator) -> list[TiltRun]:
    """The averaged runs of ``bench`` (:func:`simulate_samples` then :func:`runs_from_samples`)."""
    return runs_from_samples(bench, simulate_samples(bench, rng))


# --- session samples ⇄ runs ----------------------------------------------------------------------

TRANSITION_S = 2.0
"""Time the simulated table takes between two settings, s."""


def bench_session(
    bench: TiltBench, samples: TiltSamples, *, axis: int = 0, rng: np.random.Generator
) -> ImuSession:
    """One simulated run as session samples: the axis column is ``counts · lsb``, the others zero.

    Order of the protocol: axis up, axis down, then the angles; between two
    settings the table moves for :data:`TRANSITION_S` (quantized noisy samples
    along a straight angle ramp, which the plateau finder must skip).
    """
    quantizer = Quantization(step_si=(bench.pulse_mps2,) * 3, rounding=bench.rounding)
    n_move = max(1, round(TRANSITION_S * bench.rate_hz))
    setpoints = np.radians(np.concatenate([[90.0, -90.0], bench.angles_deg]))
    holds = [samples.up, samples.down, *samples.angles]
    parts = []
    for k, hold in enumerate(holds):
        parts.append(hold)
        if k + 1 < len(holds):
            ramp = np.linspace(setpoints[k], setpoints[k + 1], n_move + 2)[1:-1]
            x = (
                bench.gravity_mps2 * np.sin(ramp)
                + samples.zero_offset_mps2
                + bench.noise_mps2 * rng.standard_normal(n_move)
            )
            parts.append(_whole_pulses(quantizer, x))
    counts = np.concatenate(parts)
    accel = np.zeros((counts.size, 3))
    accel[:, axis] = counts * bench.lsb_mps2
    t = np.arange(counts.size) / bench.rate_hz
    return ImuSession(t, accel, None, None)


def detect_lsb(values: FloatArray) -> float:
    """The pulse weight of a quantized channel: the smallest step between its distinct values.

    Raises ValueError if the values are not whole multiples of that step.
    """
    v = np.unique(np.asarray(values, dtype=float))
    if v.size < 2:
        raise ValueError("the axis never changes: not a tilt record")
    steps = np.diff(v)
    lsb = float(np.min(steps))
    counts = v / lsb
    if np.max(np.abs(counts - np.round(counts))) > 1e-3:
        raise ValueError(
            f"the axis values are not whole multiples of one pulse (smallest step {lsb:.6g} m/s²): "
            "give the logger's pulse weight with --lsb-mps2"
        )
    return lsb


def run_from_session(
    session: ImuSession,
    *,
    angles_rad: FloatArray,
    axis: int = 0,
    hold_s: float = 30.0,
    lsb_mps2: float | None = None,
    rounding: Rounding = Rounding.TOWARD_ZERO,
) -> tuple[TiltRun, float]:
    """One run of the protocol (up, down, the angles in order) from a session's axis column.

    The holds are the plateaus of the axis (:func:`estimators.plateaus.find_plateaus`)
    lasting at least half of ``hold_s``; there must be exactly ``2 + M`` of
    them. Returns the run and the pulse weight used (``lsb_mps2`` or the one
    :func:`detect_lsb` finds).
    """
    if session.accel_mps2 is None:
        raise ValueError("the session has no accelerometer columns")
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    angles = np.asarray(angles_rad, dtype=float)
    x = session.accel_mps2[:, axis]
    lsb = detect_lsb(x) if lsb_mps2 is None else float(lsb_mps2)
    counts = x / lsb
    if np.max(np.abs(counts - np.round(counts))) > 1e-3:
        raise ValueError(f"the {AXES[axis]} values are not whole multiples of --lsb-mps2 {lsb:g}")
    counts = np.round(counts)
    levels_mps2 = STANDARD_GRAVITY_MPS2 * np.sin(np.concatenate([[np.pi / 2, -np.pi / 2], angles]))
    min_step = 0.5 * float(np.min(np.abs(np.diff(levels_mps2)))) / lsb
    holds = find_plateaus(session.t_s, counts, min_step=min_step, min_duration_s=0.5 * hold_s)
    if len(holds) != 2 + angles.size:
        raise ValueError(
            f"found {len(holds)} holds of the {AXES[axis]} axis lasting at least {0.5 * hold_s:g} s, but the protocol "
            f"has {2 + angles.size} (axis up, axis down and {angles.size} angles): check --angles-deg, --hold-s and --axis"
        )
    means = np.array([counts[s].mean() for s in holds])
    stds = np.array([counts[s].std(ddof=1) for s in holds])
    sizes = np.array([s.stop - s.start for s in holds])
    run = TiltRun(
        angles_rad=angles,
        counts_mean=means[2:],
        counts_std=stds[2:],
        n_samples=sizes[2:],
        counts_up=float(means[0]),
        counts_down=float(means[1]),
        rounding=rounding,
    )
    return run, lsb
