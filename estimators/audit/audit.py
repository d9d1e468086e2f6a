"""The model audit: baseline fit, Monte Carlo of the same session, candidates, extension, gain (issue 4).

:func:`run_audit` is the whole procedure on one session:

1. **Baseline** per triad: the nine parameters of the chain (M1, refined),
   white noise from the per-sample spread within positions
   (:func:`estimators.noise.sample_noise_sd`, quantization variance removed),
   the quantization step when the output is on a grid (M2), and the noise
   level at which averages shrink (:func:`estimators.noise.batch_means_sd`).
2. **Simulate the same session**: the measured position directions (the
   accelerometer means), durations, transitions and rate, through
   :mod:`estimators.sim` with the fitted baseline; ``replicas`` Monte Carlo
   runs through the same chain (:mod:`estimators.audit.statistics`).
3. **Compare**: ratio and tail probability per statistic, triad and axis.
4. **Candidates** (:mod:`estimators.audit.candidates`) and the selection,
   after screening out disturbed positions.
5. **Extend** the simulator with the selected effects at their fitted
   parameters (:func:`extend_model`; a bias instability as a Gauss–Markov
   bias per axis), simulate again, and the **gain**: held-out residuals of the
   calibration and F0 false alarms on the measured data with λ0 from each
   noise model.

Replicas run one after another through the simulator and the whole chain
(static detection included), each vectorized over its samples: the chain is
what the statistics describe, so it must see every replica.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from estimators._typing import BoolArray, FloatArray
from estimators.chain import ChainConfig, ChainResult, run_chain
from estimators.conventions import AXES, EARTH_RATE_RPS, Triad, reference_magnitude
from estimators.ninepar import Verdict
from estimators.noise import (
    batch_means_sd,
    dequantized_white_sd,
    fit_noise_colour,
    gm_mean_variance,
    lowpass_autocovariance,
    lowpass_mean_variance,
    lowpass_spread_share,
    quantization_step,
    rounding_mean_var,
    sample_noise_cov,
)
from estimators.scalar import derive_lambda0, f0_batch
from estimators.session import ImuSession, validate_session
from estimators.sim import (
    Bias,
    BiasDrift,
    BiasInstability,
    BiasStep,
    Clipping,
    ColouredNoise,
    CrossAxisNonlinearity,
    ErrorModel,
    GSensitivity,
    LowPass,
    NonOrthogonality,
    NonOrthogonalityChange,
    NonstaticPositions,
    Quantization,
    RecordedTemperature,
    Rounding,
    ScaleFactor,
    ScaleNonlinearity,
    SessionSpec,
    SpectralLine,
    TemperatureBias,
    TemperatureHysteresis,
    TemperatureScale,
    TriadErrorModel,
    WhiteNoise,
    multi_position_profile,
    simulate,
    tilt_sequence,
)

from . import MIN_POSITIONS
from .candidates import (
    FAMILY_ALPHA,
    TEMPERATURE_ORDERS,
    Candidate,
    ResidualStructure,
    VarianceData,
    accel_records,
    clipping_candidates,
    count_tests,
    disturbed_positions,
    earth_rate_records,
    gyro_records,
    line_candidates,
    lowpass_candidate,
    mean_variance_factor,
    residual_structure,
    temperature_reason,
    variance_candidates,
    variance_effects,
)
from .statistics import (
    INSIDE_POSITION_STATISTICS,
    Comparison,
    PositionTable,
    TriadCurves,
    compare,
    f0_config,
    f0_window_samples,
    position_span,
    position_table,
    scalar_residuals,
    static_mask,
    subset_table,
    triad_curves,
    triad_statistics,
    with_batch_means,
    with_noise_cov,
)

DEFAULT_REPLICAS = 20
SCREENING_ROUNDS = 3
"""Rounds of the disturbed-position screening (each refits without the positions flagged so far)."""
NOISE_WINDOW_S = 0.5
"""Window of the baseline's noise levels, s (the chain's batch length): a sensor filter's short-lag
correlation and any wander faster than this are noise the chain's batch-means covariance already
holds; slower wander is what the candidates look for."""
COLOUR_TERMS = 2
"""Most Gauss–Markov terms of a triad's noise colour per axis (:func:`estimators.noise.fit_noise_colour`)."""
COLOUR_SEGMENT_WINDOWS = 2
"""Length of the colour's periodogram pieces, in noise windows: its lowest frequency is half the window's
rate, where a wander slower than the window (the candidates' business) has fallen off."""
F0_FALSE_ALARM_PROB = 1.0e-3
"""Stated per-test false-alarm probability of the F0 gain check (1 s window means)."""


@dataclass(frozen=True)
class TriadBaseline:
    """The fitted noise and error model of one triad (the baseline, or the extended model's surviving parameters).

    Attributes
    ----------
    params : (9,) ``[b, e, d]`` normalized (zeros but the bias for a gyro whose scalar is unobservable).
    white_sd_si : (3,) per-sample noise before quantization (white plus colour), SI.
    quant_step_si : (3,) output grid step, SI, or None.
    rate_hz : the session's sample rate, Hz.
    mean_noise_sd_si : (3,) the noise level at which averages shrink (:func:`estimators.noise.batch_means_sd`,
        rounding included), SI: the candidates' reference for a position mean, ``diag(σ²)/n``.
    excess_sd_norm : (3,) normalized sd of the bias wander between positions beyond white noise
        (what a position's covariance lacks: :attr:`estimators.passport.TriadPassport.bias_instability_std`);
        0 in the baseline.
    gm_sigma_norm, gm_tau_s : (3,) the Gauss–Markov bias behind that wander (normalized sd, correlation
        time in s); sd 0 where none was named.
    gm_loading : (3, 3) column ``i``: the sensor axes the wander of axis ``i`` moves (1 on its own axis; a
        non-zero entry elsewhere is a wander common to both, :func:`estimators.audit.candidates.fit_loading`).
    colour_sigma_si, colour_tau_s : (3, m) the short-lag colour of the noise (:func:`estimators.noise.fit_noise_colour`):
        per-sample sd and correlation time of each Gauss–Markov term, SI and s; sd 0 for a term not selected.
        Part of ``white_sd_si``: the white part is the rest.
    colour_lr : (3, m) the likelihood ratio with which each term joined (0: not selected); its threshold
        is :func:`colour_threshold`.
    noise_correlation : (3, 3) correlation of the axes' per-sample noise at the same sample, white and colour
        alike (on a grid, of the output: the rounding, independent per axis, dilutes it by its share of the
        variance). F0 sees it: it projects the noise on the gravity direction, ``uᵀ Σ u``.
    scalar_resolved : the triad takes its scalar path (the accelerometers: the chain resolved all nine
        parameters against g, always so when the audit goes on; a gyro: :func:`earth_rate_resolved`, :func:`grade_path`).
    resolution_reason : the chain's observability verdict, one line.
    lowpass_order, lowpass_cutoff_hz : the firmware low-pass the noise went through (the ``lowpass`` candidate,
        :class:`estimators.sim.LowPass`), order 0 for none. With it the white part of ``white_sd_si`` is the
        filtered noise: its input (:attr:`white_input_sd_si`) is what averages keep.
    """

    params: FloatArray
    white_sd_si: FloatArray
    quant_step_si: FloatArray | None
    rate_hz: float
    mean_noise_sd_si: FloatArray
    excess_sd_norm: FloatArray = field(default_factory=lambda: np.zeros(3))
    gm_sigma_norm: FloatArray = field(default_factory=lambda: np.zeros(3))
    gm_tau_s: FloatArray = field(default_factory=lambda: np.ones(3))
    gm_loading: FloatArray = field(default_factory=lambda: np.eye(3))
    colour_sigma_si: FloatArray = field(default_factory=lambda: np.zeros((3, 0)))
    colour_tau_s: FloatArray = field(default_factory=lambda: np.ones((3, 0)))
    colour_lr: FloatArray = field(default_factory=lambda: np.zeros((3, 0)))
    noise_correlation: FloatArray = field(default_factory=lambda: np.eye(3))
    scalar_resolved: bool = True
    resolution_reason: str = ""
    lowpass_order: int = 0
    lowpass_cutoff_hz: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "params": [float(v) for v in self.params],
            "white_sd_si": [float(v) for v in self.white_sd_si],
            "quant_step_si": None
            if self.quant_step_si is None
            else [float(v) for v in self.quant_step_si],
            "rate_hz": float(self.rate_hz),
            "mean_noise_sd_si": [float(v) for v in self.mean_noise_sd_si],
            "excess_sd_norm": [float(v) for v in self.excess_sd_norm],
            "gm_sigma_norm": [float(v) for v in self.gm_sigma_norm],
            "gm_tau_s": [float(v) for v in self.gm_tau_s],
            "gm_loading": [[float(v) for v in row] for row in self.gm_loading],
            "rounding_mean_sd_si": [float(v) for v in np.sqrt(self.rounding_mean_var_si)],
            "colour_sigma_si": [[float(v) for v in row] for row in self.colour_sigma_si],
            "colour_tau_s": [[float(v) for v in row] for row in self.colour_tau_s],
            "colour_lr": [[float(v) for v in row] for row in self.colour_lr],
            "lowpass_order": int(self.lowpass_order),
            "lowpass_cutoff_hz": float(self.lowpass_cutoff_hz),
            "noise_correlation": [[float(v) for v in row] for row in self.noise_correlation],
        }

    @property
    def colour_level_sd_si(self) -> FloatArray:
        """(3,) the level at which long averages of white plus colour shrink, ``√(σ_w² + Σ σ_c² (1 + φ)/(1 − φ))``, SI
        (``σ_w`` the white noise before a low-pass: the filter keeps the spectrum at 0)."""
        phi = np.exp(-1.0 / (self.rate_hz * self.colour_tau_s))
        gain = np.sum(self.colour_sigma_si**2 * (1.0 + phi) / (1.0 - phi), axis=1)
        out: FloatArray = np.sqrt(self.white_input_sd_si**2 + gain)
        return out

    @property
    def lowpass_variance_share(self) -> float:
        """The per-sample variance the low-pass leaves of white noise, ``∫|H|² = r(0)`` (1 without one)."""
        if self.lowpass_order == 0:
            return 1.0
        r = lowpass_autocovariance(self.lowpass_order, self.lowpass_cutoff_hz, self.rate_hz, 1)
        return float(r[0])

    @property
    def white_input_sd_si(self) -> FloatArray:
        """(3,) the white noise before the low-pass, SI (:attr:`white_only_sd_si` without one)."""
        out: FloatArray = self.white_only_sd_si / np.sqrt(self.lowpass_variance_share)
        return out

    @property
    def white_only_sd_si(self) -> FloatArray:
        """(3,) the white part of the per-sample noise (``white_sd_si`` less the colour), SI."""
        out: FloatArray = np.sqrt(
            np.clip(self.white_sd_si**2 - np.sum(self.colour_sigma_si**2, axis=1), 0.0, None)
        )
        return out

    @property
    def rounding_mean_var_si(self) -> FloatArray:
        """(3,) variance of the rounding error a position mean keeps on the grid (zeros off a grid), SI²."""
        if self.quant_step_si is None:
            return np.zeros(3)
        return rounding_mean_var(self.white_sd_si, self.quant_step_si)


def effective_noise_std_norm(baseline: TriadBaseline, reference: float, n_avg: int) -> FloatArray:
    """(3,) per-sample noise to give :func:`estimators.scalar.derive_lambda0` for windows of ``n_avg`` samples.

    ``derive_lambda0`` divides the variance by ``n_avg`` (white noise). The
    Gauss–Markov bias of the audited model averages down only as
    ``σ²·V(T/τ)`` over a window of ``T = n_avg / rate`` (:func:`mean_variance_factor`),
    so it enters as ``n_avg·σ²·V(T/τ)``, on every axis its loading moves
    (``Σ_i L_ji² σ_i² V(T/τ_i)`` on axis ``j``); each colour term likewise as
    ``n_avg·σ_c²·V_n(φ)`` (:func:`estimators.noise.gm_mean_variance`):
    ``σ_eff² = σ_w² + n_avg·Σ σ_c² V_n(φ) + n_avg·σ_gm²·V(T/τ)``. Through a low-pass the white term is
    ``n_avg·σ_in²·V_lp(n_avg)`` (:func:`estimators.noise.lowpass_mean_variance`): a window's mean keeps the
    input's level, not the filtered per-sample one (``σ_w² = σ_in² r(0)`` at ``n_avg = 1``).
    """
    white = baseline.white_only_sd_si / reference
    if baseline.lowpass_order:
        white = (
            baseline.white_input_sd_si
            / reference
            * np.sqrt(
                n_avg
                * lowpass_mean_variance(
                    baseline.lowpass_order, baseline.lowpass_cutoff_hz, baseline.rate_hz, n_avg
                )
            )
        )
    phi = np.exp(-1.0 / (baseline.rate_hz * baseline.colour_tau_s))
    colour = np.sum(
        (baseline.colour_sigma_si / reference) ** 2 * gm_mean_variance(phi, n_avg), axis=1
    )
    window_s = n_avg / baseline.rate_hz
    wander = baseline.gm_loading**2 @ np.array(
        [
            s * s * float(mean_variance_factor(np.array([window_s]), float(t))[0])
            for s, t in zip(baseline.gm_sigma_norm, baseline.gm_tau_s, strict=True)
        ]
    )
    var: FloatArray = white**2 + n_avg * (colour + wander)
    return np.sqrt(var)


def _angles_from_cosines(d: FloatArray) -> FloatArray:
    """Six angles ``[δ_xy, δ_xz, δ_yx, δ_yz, δ_zx, δ_zy]`` whose axes have the cosines ``d`` (x on body x, y in the x-y plane)."""
    return np.array([0.0, 0.0, 0.0, -d[0], -(d[2] - d[0] * d[1]), d[1]])


def triad_samples(session: ImuSession, triad: Triad) -> FloatArray:
    """The session's (N, 3) samples of ``triad``, SI."""
    x = session.accel_mps2 if triad is Triad.ACCEL else session.gyro_rps
    if x is None:
        raise ValueError(f"the session has no {triad.value} samples")
    return x


def fit_baseline(
    session: ImuSession,
    chain: ChainResult,
    triad: Triad,
    *,
    window_s: float = NOISE_WINDOW_S,
    colour: bool = True,
    left_out: tuple[int, ...] = (),
) -> TriadBaseline:
    """Baseline model of ``triad`` (module docstring, step 1).

    ``left_out``: positions whose samples the noise is not read from (disturbed: their motion is not the
    sensor's noise, and would move every replica position).

    White noise: the per-sample spread about a ``window_s`` moving mean
    (:func:`estimators.noise.sample_noise_sd`), pooled over the positions, the
    rounding variance ``q²/12`` removed; the level at which averages shrink
    from ``window_s`` batch means (:func:`estimators.noise.batch_means_sd`); the
    grid step from every static sample (:func:`estimators.noise.quantization_step`,
    all three axes or none). On a grid the white noise is the level before it
    (:func:`estimators.noise.dequantized_white_sd`, exact also below one step,
    where Sheppard's ``q²/12`` is not). The noise's short-lag colour
    (:func:`estimators.noise.fit_noise_colour`) from the periodogram of
    :data:`COLOUR_SEGMENT_WINDOWS`-window pieces, its correlation times up to
    one window (a slower wander is the candidates' business), as shares of the
    per-sample noise above (the periodogram's total differs from it by a percent
    or two: bins, rounding); ``colour=False``
    leaves it out (white noise only: the candidates do not use it, the simulation does).
    """
    x = triad_samples(session, triad)
    spans = [position_span(p) for k, p in enumerate(chain.positions) if k not in left_out]
    window = max(2, round(window_s * session.rate_hz))
    usable = [(a, b) for a, b in spans if b - a >= 2 * window]
    if not usable:
        raise ValueError(
            f"no position holds two {window_s} s windows: the white noise cannot be read"
        )
    # Pooled over positions, weighted by their sample counts: each position's own mean and slow wander drop out.
    n = np.array([b - a for a, b in usable], float)
    cov = (
        np.sum(
            [k * sample_noise_cov(x[a:b], window) for k, (a, b) in zip(n, usable, strict=True)],
            axis=0,
        )
        / n.sum()
    )
    sd = np.sqrt(np.diag(cov))
    # An axis frozen on one count has no noise to correlate: its row is 0 and its diagonal stays 1.
    correlation = cov / np.maximum(np.outer(sd, sd), 1e-300) + np.diag(sd == 0)
    mean_sd = batch_means_sd([x[a:b] for a, b in usable], window)
    static = x[static_mask(x.shape[0], np.array(spans))]
    steps = [quantization_step(static[:, i]) for i in range(3)]
    quant = None if any(s is None for s in steps) else np.array(steps, float)
    white = sd if quant is None else dequantized_white_sd(sd, quant)
    fit = (
        fit_noise_colour(
            [x[a:b] for a, b in usable],
            session.rate_hz,
            COLOUR_SEGMENT_WINDOWS * window,
            colour_threshold(),
            max_tau_s=window / session.rate_hz,
            max_terms=COLOUR_TERMS,
        )
        if colour
        else None
    )
    est = chain.triads[triad].estimate
    if est.params is not None:
        params = np.array(est.params, float)
    else:
        ref = reference_magnitude(triad, chain.gravity_mps2)
        params = np.zeros(9)
        params[:3] = np.median([p.mean(triad) for p in chain.positions], axis=0) / ref
    resolved = (
        earth_rate_resolved(chain)
        if triad is Triad.GYRO
        else est.params is not None and est.verdict is Verdict.OBSERVABLE
    )
    out = TriadBaseline(
        params,
        white,
        quant,
        session.rate_hz,
        mean_sd,
        noise_correlation=correlation,
        scalar_resolved=resolved,
        resolution_reason=est.reason,
    )
    if fit is None:
        return out
    return replace(
        out,
        colour_sigma_si=fit.sigma_si
        * (white / np.maximum(np.sqrt(fit.white_sd_si**2 + fit.variance_si), 1e-300))[:, None],
        colour_tau_s=fit.tau_s,
        colour_lr=fit.lr,
    )


EARTH_RATE_RESOLVED_SD = 0.2
"""Largest noise of a typical gyro position mean, per axis as a share of Ω, at which the Earth rate counts as
resolved per position and the gyro takes the scalar path ``|ω − b − G f| = Ω``. Up to it the norm's noise
bias (≈ σ²/Ω, the same at every position, taken by the scale) stays within a fifth of the scalar's sd, and
the scalar's power exceeds the position means' with the Earth rate as noise (variance Ω²/3) by
``√(σ² + Ω²/3)/σ`` ≥ 3; the nine parameters' σ only set how much of an effect they take in
(:func:`estimators.audit.statistics.scalar_residuals`' Jacobian), never which path."""


def earth_rate_resolved(chain: ChainResult) -> bool:
    """The gyro's position means resolve the Earth rate (:data:`EARTH_RATE_RESOLVED_SD`) and the chain fitted its
    nine parameters with a finite covariance (however wide: a continuous path, not a verdict on their σ)."""
    result = chain.triads.get(Triad.GYRO)
    if result is None:
        return False
    est = result.estimate
    if est.params is None or est.cov is None or not np.all(np.isfinite(np.diag(est.cov))):
        return False
    sd = [
        np.sqrt(np.max(np.diag(p.gyro_cov_rps)))
        for p in chain.positions
        if p.gyro_cov_rps is not None
    ]
    return bool(sd) and float(np.median(sd)) <= EARTH_RATE_RESOLVED_SD * EARTH_RATE_RPS


def colour_threshold() -> float:
    """Likelihood ratio a colour term must exceed: χ² with two degrees of freedom (its variance and correlation
    time) at the family-wise false-naming rate split over the terms tried on one triad's three axes (Bonferroni,
    as the candidates)."""
    from scipy.stats import chi2

    return float(chi2.isf(FAMILY_ALPHA / (3 * COLOUR_TERMS), 2))


def grade_path(
    triad: Triad, base: TriadBaseline, n_typical: float, reference: float
) -> dict[str, str | float]:
    """Which candidate path a triad took and why (issue 13): the audit JSON's ``grade_paths``.

    * ``gravity_scalar`` (accelerometers): effects on the exact scalar residual of M1;
    * ``earth_rate_scalar`` (a gyro whose position means resolve the Earth rate, :func:`earth_rate_resolved`): effects on
      ``|ω − b − G f| = Ω``, the heading of each position eliminated
      (:func:`estimators.audit.candidates.earth_rate_records`);
    * ``earth_rate_as_noise`` (a gyro whose position means do not resolve it, MEMS): position means regressed per
      axis, the Earth rate's unknown horizontal projection an extra variance ``Ω²/3``
      (:func:`estimators.audit.candidates.gyro_records`); what that path cannot see is in the audit's statements.

    ``n_typical``: a typical position's sample count; ``reference``: g or Ω.
    """
    noise = float(np.max(base.mean_noise_sd_si) / np.sqrt(n_typical) / reference)
    where = (
        f"a position mean's noise is {noise:.2g} of the reference; chain: {base.resolution_reason}"
    )
    if triad is Triad.ACCEL:
        return {"path": "gravity_scalar", "mean_noise_over_reference": noise, "reason": where}
    if base.scalar_resolved:
        return {
            "path": "earth_rate_scalar",
            "mean_noise_over_reference": noise,
            "reason": "the Earth rate is resolved per position: effects on |ω − b − G f| = Ω, "
            f"each position's heading eliminated; {where}",
        }
    return {
        "path": "earth_rate_as_noise",
        "mean_noise_over_reference": noise,
        "reason": f"the Earth rate is not resolved (a position mean's noise above {EARTH_RATE_RESOLVED_SD:g} Ω): position means per axis, its unknown projection "
        f"a variance Ω²/3; {where}",
    }


def triad_model(base: TriadBaseline, reference: float) -> TriadErrorModel:
    """The simulator chain of a baseline (non-orthogonality, scale, bias, white and coloured noise with the axes'
    correlation, the firmware's low-pass, quantization)."""
    p = base.params
    effects = [
        NonOrthogonality(_angles_from_cosines(p[6:9])),
        ScaleFactor(p[3:6]),
        Bias(p[:3] * reference),
    ]
    effects.append(WhiteNoise.from_sample_sd(base.white_input_sd_si, 1.0, base.noise_correlation))
    if np.any(base.colour_sigma_si > 0):
        effects.append(
            ColouredNoise(base.colour_sigma_si, base.colour_tau_s, base.noise_correlation)
        )
    if base.lowpass_order:
        effects.append(LowPass(base.lowpass_order, base.lowpass_cutoff_hz))
    if base.quant_step_si is not None:
        effects.append(Quantization(base.quant_step_si, Rounding.NEAREST))
    return TriadErrorModel(tuple(effects))


def baseline_error_model(baselines: dict[Triad, TriadBaseline], g: float) -> ErrorModel:
    """The simulator's model of the baselines (:func:`triad_model` per triad; no gyro model without a gyro)."""
    gyro = baselines.get(Triad.GYRO)
    return ErrorModel(
        accel=triad_model(baselines[Triad.ACCEL], g),
        gyro=TriadErrorModel() if gyro is None else triad_model(gyro, EARTH_RATE_RPS),
    )


def same_session_spec(chain: ChainResult, session: ImuSession, model: ErrorModel) -> SessionSpec:
    """The measured session's geometry and timing as a simulator spec (module docstring, step 2).

    Position directions are the measured accelerometer means; headings and the
    latitude come from the gyros when they resolve the Earth rate
    (:func:`measured_attitudes`), else the positions are reached by tilts (the
    heading does not matter to the accelerometer statistics nor to a MEMS
    gyro's); each hold is the averaged span plus the chain's trims, each turn
    the gap in between.
    """
    attitudes, latitude_deg = measured_attitudes(chain)
    hold, turns = simulated_timing(chain)
    profile = multi_position_profile(attitudes, static_s=hold, transition_s=turns)
    # White noise density is per √Hz: scale the per-sample level to the session's rate.
    rate = session.rate_hz
    model = ErrorModel(
        accel=_at_rate(model.accel, rate),
        gyro=_at_rate(model.gyro, rate),
        environment=model.environment,
    )
    return SessionSpec(
        profile,
        model,
        rate_hz=rate,
        gravity_mps2=chain.gravity_mps2,
        temperature=replayed_temperature(chain, session, hold, turns),
        latitude_deg=latitude_deg,
    )


TURN_MAX_S = 120.0
"""Longest turn of the simulated twin, s. A longer gap between two positions is a break in the
recording, not a turn: simulating it would cost its samples at the session's rate in every
replica (a session with an 11-day break took 18 GB), and ``run_audit`` says where it cut one."""
_TRIM_S = 2.0 * 0.25


def position_gaps_s(chain: ChainResult) -> FloatArray:
    """(P − 1,) time between consecutive positions, s, less the chain's trims."""
    out: FloatArray = (
        np.array(
            [
                b.t_start_s - a.t_end_s
                for a, b in zip(chain.positions[:-1], chain.positions[1:], strict=True)
            ]
        )
        - _TRIM_S
    )
    return out


def simulated_timing(chain: ChainResult) -> tuple[FloatArray, FloatArray]:
    """(P,) hold and (P − 1,) turn lengths, s, of the simulated twin of the chain's positions.

    Each hold is the averaged span plus the chain's trims, each turn the gap in between
    (0.5 s to :data:`TURN_MAX_S`).
    """
    hold = np.array([p.duration_s for p in chain.positions]) + _TRIM_S
    return hold, np.clip(position_gaps_s(chain), 0.5, TURN_MAX_S)


def simulated_hold_starts_s(hold_s: FloatArray, turn_s: FloatArray) -> FloatArray:
    """(P,) start of each simulated hold, s from the simulated session's start (the profile begins with one)."""
    out: FloatArray = np.concatenate([[0.0], np.cumsum(hold_s[:-1] + turn_s)])
    return out


def measured_attitudes(chain: ChainResult) -> tuple[np.ndarray, float]:
    """(P, 3, 3) ``mat_nb`` of the measured positions and the latitude, degrees (45 when unknown).

    Up is each position's accelerometer mean. When the gyro's position means
    resolve the Earth rate (:func:`earth_rate_resolved`), each position's heading is
    gyrocompassed: north is the horizontal part of its bias-free gyro mean and
    ``sin φ`` the median vertical share of the Earth rate — so the replicas see
    the Earth rate on each axis as the unit did. Otherwise the positions are
    reached by tilts from an arbitrary heading at 45°.
    """
    up = np.array([p.accel_mean_mps2 for p in chain.positions], float)
    if not earth_rate_resolved(chain):
        return tilt_sequence(up), 45.0
    est = chain.triads[Triad.GYRO].estimate
    assert est.params is not None
    u = up / np.linalg.norm(up, axis=1, keepdims=True)
    w = (
        np.array([p.gyro_mean_rps for p in chain.positions], float)
        - est.params[:3] * EARTH_RATE_RPS
    )
    vertical = np.einsum("ki,ki->k", w, u)
    north = w - vertical[:, None] * u
    north /= np.linalg.norm(north, axis=1, keepdims=True)
    east = np.cross(north, u)
    sin_lat = float(np.median(vertical / np.linalg.norm(w, axis=1)))
    return np.stack([east, north, u], axis=1), float(np.degrees(np.arcsin(np.clip(sin_lat, -1, 1))))


def replayed_temperature(
    chain: ChainResult, session: ImuSession, hold_s: FloatArray, turn_s: FloatArray
) -> RecordedTemperature | None:
    """The session's temperature record on the simulated timeline, or None without one (issue 13).

    The simulated session holds each position as long as the measured one but
    its turns may differ (clipped, and nothing before the first position): the
    measured times are mapped piecewise linearly, each simulated hold onto its
    measured hold, so every simulated position sees the temperatures its
    measured twin saw — a temperature effect re-simulated on the record lands
    on the same positions with the same regressor.
    """
    temp_c = session.temp_c
    if temp_c is None:
        return None
    start_sim = simulated_hold_starts_s(hold_s, turn_s)
    start_meas = np.array([p.t_start_s for p in chain.positions]) - 0.5 * (
        hold_s - np.array([p.duration_s for p in chain.positions])
    )
    knots_meas = np.column_stack([start_meas, start_meas + hold_s]).ravel()
    knots_sim = np.column_stack([start_sim, start_sim + hold_s]).ravel()
    # Overlapping measured holds (turns shorter than the trims) would fold time back: keep each new maximum
    # (the simulated knots always increase: holds are positive, turns at least 0.5 s).
    keep = knots_meas > np.maximum.accumulate(np.concatenate([[-np.inf], knots_meas[:-1]]))
    t_sim = np.interp(session.t_s, knots_meas[keep], knots_sim[keep])
    inside = np.concatenate([[True], np.diff(t_sim) > 0])
    return RecordedTemperature(t_sim[inside], temp_c[inside])


def _at_rate(chain: TriadErrorModel, rate_hz: float) -> TriadErrorModel:
    wn = chain.find(WhiteNoise)
    if wn is None:
        return chain
    return chain.with_effect(
        replace(wn, density_si_per_sqrt_hz=np.array(wn.density_si_per_sqrt_hz) / np.sqrt(rate_hz))
    )


def replica_statistics(
    spec: SessionSpec,
    config: ChainConfig,
    triads: tuple[Triad, ...],
    replicas: int,
    seed: int,
    left_out_s: FloatArray | None = None,
    progress: Callable[[str], None] | None = None,
    label: str = "baseline",
) -> tuple[dict[Triad, list[dict[str, float]]], dict[Triad, list[TriadCurves]], list[str]]:
    """Statistics and plotted curves of ``replicas`` simulated sessions, per triad, and the replicas the chain
    refused (``"replica r: reason"``), which the statistics leave out.

    A model the audit extended can make sessions the chain refuses (an axis clipped flat at a position):
    that is the model's outcome, counted and stated by :func:`run_audit`, not the session's fault.

    ``left_out_s`` (m, 2): simulated holds ``[start, end)``, s from the session's start, whose positions the
    statistics inside a position leave out (:func:`triad_statistics`' ``described``): a replica position
    is matched to its measured twin by the hold its middle falls in, not by its index, which a position the
    replica's static detector splits or misses would shift. ``progress`` hears of each replica done
    (the ``label``'d model's), for a command to show on long sessions.
    """
    stats: dict[Triad, list[dict[str, float]]] = {t: [] for t in triads}
    curves: dict[Triad, list[TriadCurves]] = {t: [] for t in triads}
    refused: list[str] = []
    for r in range(replicas):
        sim = simulate(spec, np.random.SeedSequence([seed, r]).generate_state(1)[0])
        s = sim.session
        if Triad.GYRO not in triads:
            s = ImuSession(s.t_s, s.accel_mps2, None, s.temp_c)
        try:
            chain = run_chain(s, config)
        except ValueError as e:
            refused.append(f"replica {r}: {e}")
            continue
        described = None
        if left_out_s is not None:
            mid = np.array([0.5 * (p.t_start_s + p.t_end_s) for p in chain.positions]) - s.t_s[0]
            described = ~np.any(
                (mid[:, None] >= left_out_s[:, 0]) & (mid[:, None] < left_out_s[:, 1]), axis=1
            )
        for t in triads:
            x = triad_samples(s, t)
            stats[t].append(triad_statistics(chain, x, s.t_s, t, s.rate_hz, described))
            curves[t].append(triad_curves(chain, x, s.t_s, t, s.rate_hz))
        if progress is not None:
            progress(f"{label} model: {r + 1} of {replicas} replicas simulated")
    return stats, curves, refused


def refused_statement(label: str, refused: list[str], replicas: int) -> str:
    """What the chain's refusal of a model's replicas leaves of its check (:func:`replica_statistics`)."""
    rest = (
        "the model is not checked against the session (the comparison is the baseline's)"
        if len(refused) == replicas
        else f"its band is of the other {replicas - len(refused)}"
    )
    return f"{label} model: the chain refused {len(refused)} of its {replicas} replicas ({refused[0]}): {rest}"


@dataclass(frozen=True)
class AuditConfig:
    """Settings of an audit: the chain, the replica count and the seed."""

    chain: ChainConfig
    replicas: int = DEFAULT_REPLICAS
    seed: int = 0


@dataclass
class AuditResult:
    """Everything the audit found (``to_dict`` is the JSON of the ``audit`` command).

    ``replica_stats`` / ``replica_curves``: ``{"baseline" | "extended": {Triad: [per replica]}}``;
    ``measured_stats``: ``{"baseline" | "extended": {Triad: ...}}`` (the extended model's without the
    ``left_out`` positions, see :func:`left_out_positions`); ``measured_curves``: ``{Triad: ...}``
    (:class:`TriadCurves`, for the report).
    """

    statements: list[str]
    n_positions: int
    gravity_mps2: float
    baseline: dict[Triad, TriadBaseline] = field(default_factory=dict)
    extended_model: dict[Triad, TriadBaseline] = field(default_factory=dict)
    baseline_cmp: list[Comparison] = field(default_factory=list)
    extended_cmp: list[Comparison] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)
    gain: dict[str, float] = field(default_factory=dict)
    replicas: int = 0
    # Per model ("baseline", "extended"), per triad: the replicas' statistics and curves.
    replica_stats: dict[str, dict[Triad, list[dict[str, float]]]] = field(default_factory=dict)
    measured_stats: dict[str, dict[Triad, dict[str, float]]] = field(default_factory=dict)
    replica_curves: dict[str, dict[Triad, list[TriadCurves]]] = field(default_factory=dict)
    measured_curves: dict[Triad, TriadCurves] = field(default_factory=dict)
    extension: list[dict[str, Any]] = field(default_factory=list)
    # The positions the extended comparison's statistics inside a position leave out, and why.
    left_out: tuple[int, ...] = ()
    left_out_reason: str = ""
    grade_paths: dict[Triad, dict[str, str | float]] = field(default_factory=dict)
    # Per triad on a scalar path: its residual's structure between and inside positions.
    structure: list[ResidualStructure] = field(default_factory=list)

    @property
    def named(self) -> list[Candidate]:
        return [c for c in self.candidates if c.selected]

    def headline(self, cmp: list[Comparison]) -> Comparison | None:
        return next((c for c in cmp if c.statistic == "chi2_per_dof"), None)

    def to_dict(self) -> dict[str, Any]:
        def block(cmp: list[Comparison], models: dict[Triad, TriadBaseline]) -> dict[str, Any]:
            head = self.headline(cmp)
            return {
                "headline": "chi2_per_dof",
                "ratio": None if head is None else head.ratio,
                "tail_prob": None if head is None else head.tail_prob,
                "inside_band": None if head is None else head.inside,
                "models": {t.value: m.to_dict() for t, m in models.items()},
                "statistics": [c.to_dict() for c in cmp],
            }

        return {
            "statements": self.statements,
            "n_positions": self.n_positions,
            "grade_paths": {t.value: p for t, p in self.grade_paths.items()},
            "gravity_mps2": self.gravity_mps2,
            "replicas": self.replicas,
            "baseline": block(self.baseline_cmp, self.baseline),
            "candidates": [c.to_dict() for c in self.candidates],
            "structured_residual": [st.to_dict() for st in self.structure],
            "named_causes": [
                {
                    "effect": c.effect,
                    "triad": c.triad.value,
                    "axis": c.axis,
                    "evidence": c.reason,
                    "params": c.params,
                }
                for c in self.named
            ],
            "extended": {
                **block(self.extended_cmp, self.extended_model),
                "effects_added": self.extension,
                "positions_left_out": {
                    "positions": list(self.left_out),
                    "statistics": list(INSIDE_POSITION_STATISTICS) if self.left_out else [],
                    "reason": self.left_out_reason,
                },
            },
            "gain": self.gain,
        }


def _present(session: ImuSession) -> tuple[Triad, ...]:
    return tuple(
        t
        for t, a in ((Triad.ACCEL, session.accel_mps2), (Triad.GYRO, session.gyro_rps))
        if a is not None
    )


def fit_baselines(
    session: ImuSession,
    chain: ChainResult,
    *,
    window_s: float = NOISE_WINDOW_S,
    colour: bool = True,
    left_out: tuple[int, ...] = (),
) -> dict[Triad, TriadBaseline]:
    """:func:`fit_baseline` of every triad the session has."""
    return {
        t: fit_baseline(session, chain, t, window_s=window_s, colour=colour, left_out=left_out)
        for t in _present(session)
    }


def quantization_candidate(triad: Triad, base: TriadBaseline, n_typical: float) -> Candidate:
    """The grid read by the baseline (M2): part of the baseline, named with its step and what it does to the means.

    ``n_typical`` is a typical position's sample count. Below about half a step
    of noise (M2's ``Entier`` without dithering) every position mean keeps a
    rounding error that does not average down (:func:`estimators.noise.rounding_mean_var`):
    the baseline's replicas reproduce it with the exact quantizer and the
    candidates expect it, so it is the grid's doing and no other effect's.
    Above that, M2's half-pulse correction holds: the rounding's mean offset
    is a constant (half a step for ``Entier``), which the bias takes in.
    """
    q = base.quant_step_si
    if q is None:
        return Candidate("quantization", triad, None, True, reason="output not on a grid")
    share = q / np.sqrt(12.0) / np.maximum(base.white_sd_si, 1e-300)
    kept = np.sqrt(base.rounding_mean_var_si)
    ratio = kept / (base.mean_noise_sd_si / np.sqrt(n_typical))
    half_pulse = bool(np.all(base.white_sd_si >= 0.5 * q))
    how = (
        "noise ≥ ½ step: M2's half-pulse correction holds (a constant offset, in the bias)"
        if half_pulse
        else f"noise below ½ step: each position mean keeps a rounding error of sd up to {float(np.max(kept)):.3g} SI "
        f"({float(np.max(ratio)):.2g}× a mean's noise), reproduced by the exact quantizer and expected by the candidates"
    )
    return Candidate(
        "quantization",
        triad,
        None,
        True,
        params={
            "step_si": [float(v) for v in q],
            "white_over_step": [float(v) for v in base.white_sd_si / q],
            "rounding_mean_sd_si": [float(v) for v in kept],
            "rounding_over_mean_noise": [float(v) for v in ratio],
            "half_pulse_correction_holds": half_pulse,
        },
        in_baseline=True,
        reason=f"output on a grid of {', '.join(f'{v:.4g}' for v in q)} SI (M2), in the baseline; rounding sd is "
        f"{100 * float(np.max(share)):.0f} % of the white noise; {how}",
    )


def candidate_table(
    chain: ChainResult,
    session: ImuSession,
    triad: Triad,
    base: TriadBaseline,
    batch_s: float = NOISE_WINDOW_S,
) -> PositionTable:
    """The position table of ``triad`` with the covariance of each mean from the baseline's noise for averages,
    the rounding variance the baseline's grid leaves in every mean, and the means of its noise windows
    (``batch_s``) with the variance of one from the baseline's white noise, colour and rounding alone."""
    x = triad_samples(session, triad)
    tab = position_table(chain, x, session.t_s, triad, session.temp_c)
    ref = reference_magnitude(triad, chain.gravity_mps2)
    tab = with_noise_cov(tab, base.mean_noise_sd_si / ref, base.rounding_mean_var_si / ref**2)
    batch = max(1, round(batch_s * session.rate_hz))
    # The per-sample rounding error that is not kept by a whole position's mean averages down like white noise.
    rounding = (
        np.zeros(3) if base.quant_step_si is None else base.quant_step_si**2 / 12.0
    ) - base.rounding_mean_var_si
    return with_batch_means(
        tab, x, batch, ref, (base.colour_level_sd_si**2 + np.clip(rounding, 0.0, None)) / batch
    )


def find_candidates(
    session: ImuSession,
    chain: ChainResult,
    baselines: dict[Triad, TriadBaseline],
    *,
    batch_s: float = NOISE_WINDOW_S,
) -> list[Candidate]:
    """Every candidate effect of :mod:`estimators.audit.candidates` on a session with ≥ MIN_POSITIONS positions.

    ``session`` is the validated session the chain ran on (position spans index it);
    ``batch_s`` the window of the baselines' noise for averages, s (what of a wander it already holds).
    """
    if len(chain.positions) < MIN_POSITIONS:
        raise ValueError(
            f"candidates need at least {MIN_POSITIONS} static positions, got {len(chain.positions)}"
        )
    g = chain.gravity_mps2
    triads = _present(session)
    gyro = Triad.GYRO in triads
    tab_a = candidate_table(chain, session, Triad.ACCEL, baselines[Triad.ACCEL], batch_s)
    tab_g = (
        candidate_table(chain, session, Triad.GYRO, baselines[Triad.GYRO], batch_s)
        if gyro
        else None
    )
    n = tab_a.n_samples.size
    n_tests = count_tests(
        gyro,
        temperature_reason(tab_a) is None,
        gyro and baselines[Triad.GYRO].scalar_resolved,
    )
    keep = np.ones(n, bool)

    def fit(rows: BoolArray) -> tuple[list[Candidate], list[VarianceData], tuple[FloatArray, ...]]:
        return _fit_candidates(
            subset_table(tab_a, rows),
            None if tab_g is None else subset_table(tab_g, rows),
            baselines,
            g,
            n_tests,
            batch_s,
        )

    # Screen for disturbed positions, refit without them, until none is left (a few rounds at most).
    # A position is flagged against the sensor-axis wander alone (a wobble fitted with it still in could
    # take its motion for a wobble of all), and confirmed against the model of the other positions,
    # their common wobble included (a wobble of every position is not a few disturbed ones).
    cands, records, final = fit(keep)
    for _ in range(SCREENING_ROUNDS):
        m = int(keep.sum())
        flagged = disturbed_positions(records, final, m, n_tests, common_motion=False)
        if not flagged.any() or m - int(flagged.sum()) < MIN_POSITIONS:
            break
        trial = keep.copy()
        trial[np.flatnonzero(keep)[flagged]] = False
        others = fit(trial)
        confirmed = flagged & disturbed_positions(records, others[2], m, n_tests)
        if not confirmed.any():
            break
        keep[np.flatnonzero(keep)[confirmed]] = False
        cands, records, final = others if confirmed.sum() == flagged.sum() else fit(keep)
    if not keep.all():
        cands = [
            _with_disturbed(c, tab_a, ~keep) if c.effect == "nonstatic_positions" else c
            for c in cands
        ]
    if not gyro:
        cands.append(
            Candidate(
                "g_sensitivity",
                Triad.GYRO,
                None,
                False,
                reason="not identifiable: the session has no gyro triad",
            )
        )
    n_typical = float(np.median(tab_a.n_samples))
    cands += [quantization_candidate(t, baselines[t], n_typical) for t in triads]
    for t in triads:
        cands += clipping_candidates(
            t,
            triad_samples(session, t),
            tab_a.spans,
            baselines[t].white_sd_si,
            baselines[t].quant_step_si,
            n_tests,
        )
        cands += line_candidates(
            t, triad_samples(session, t), tab_a.spans, session.rate_hz, n_tests
        )
        q = baselines[t].quant_step_si
        cands.append(
            lowpass_candidate(
                t,
                triad_samples(session, t),
                tab_a.spans,
                session.rate_hz,
                COLOUR_SEGMENT_WINDOWS * max(2, round(batch_s * session.rate_hz)),
                np.zeros(3) if q is None else q**2 / 12.0,
                n_tests,
            )
        )
    return cands


def _fit_candidates(
    tab_a: PositionTable,
    tab_g: PositionTable | None,
    baselines: dict[Triad, TriadBaseline],
    g: float,
    n_tests: int,
    batch_s: float,
) -> tuple[list[Candidate], list[VarianceData], tuple[FloatArray, ...]]:
    """Mean and variance candidates of both triads on the given tables; the records and the selected variance model."""
    resid, sigma, jac, _ = scalar_residuals(baselines[Triad.ACCEL].params, tab_a)
    acc = accel_records(tab_a, jac, resid, sigma, n_tests)
    cands, records = list(acc.candidates), [acc.between, acc.halves]
    if tab_g is not None:
        base_g = baselines[Triad.GYRO]
        if base_g.scalar_resolved:
            r_g, s_g, j_g, _ = scalar_residuals(base_g.params, tab_g)
            gyr = earth_rate_records(tab_g, j_g, r_g, s_g, tab_a.mean * g, n_tests)
        else:
            gyr = gyro_records(tab_g, tab_a.mean * g, n_tests)
        cands += gyr.candidates
        records += [gyr.between, gyr.halves]
    tables = {Triad.ACCEL: tab_a} | ({} if tab_g is None else {Triad.GYRO: tab_g})
    var_cands, final = variance_candidates(
        variance_effects(tab_g is not None),
        records,
        tab_a.duration_s,
        n_tests,
        batch_s,
        tables=tables,
    )
    return cands + var_cands, records, final


def _with_disturbed(c: Candidate, tab_a: PositionTable, disturbed: BoolArray) -> Candidate:
    """``nonstatic_positions`` selected for the positions the screening took out (their times in the evidence)."""
    t0 = tab_a.t_mid_s[disturbed] - 0.5 * tab_a.duration_s[disturbed]
    where = ", ".join(
        f"#{k} ({t:.1f} s)" for k, t in zip(np.flatnonzero(disturbed), t0, strict=True)
    )
    params = c.params | {
        "common_wobble": c.selected,
        "disturbed_positions": [int(k) for k in np.flatnonzero(disturbed)],
        "disturbed_t_start_s": [float(t) for t in t0],
    }
    reason = (
        f"{int(disturbed.sum())} of {disturbed.size} positions move inside: their half-to-half differences lie beyond the fitted noise "
        f"at the family-wise rate ({where}); left out of every other fit"
    )
    reason += (
        f"; besides, {c.reason}"
        if c.selected
        else f"; no wobble common to every position (LR {c.lr:.1f}, threshold {c.threshold:.1f})"
    )
    return replace(c, identifiable=True, params=params, selected=True, reason=reason)


def run_audit(
    session: ImuSession, config: AuditConfig, *, progress: Callable[[str], None] | None = None
) -> AuditResult:
    """The audit of one session (module docstring). Never names a cause it could not test: see ``statements``.

    ``progress`` hears of each replica simulated (:func:`replica_statistics`)."""
    # The chain's position spans index the validated samples: every later step uses the same ones.
    session, _ = validate_session(
        session,
        accel_limit_mps2=config.chain.accel_limit_mps2,
        gyro_limit_rps=config.chain.gyro_limit_rps,
    )
    chain_config = replace(config.chain, bias_instability_std=None)
    chain = run_chain(session, chain_config)
    n = len(chain.positions)
    triads = _present(session)
    res = AuditResult([], n, chain.gravity_mps2, replicas=config.replicas)
    if Triad.ACCEL not in triads:
        res.statements.append(
            "no accelerometer triad: position directions and the scalar equation are unknown; nothing can be concluded"
        )
        return res
    if n == 0:
        res.statements.append(
            "no static interval found: the scalar equation has nothing to test; no statistic, no candidate, no cause can be concluded"
        )
        return res
    if n < MIN_POSITIONS:
        res.statements.append(
            f"{n} static positions (need ≥ {MIN_POSITIONS}: 9 parameters plus degrees of freedom): no statistic, no candidate, no cause can be concluded"
        )
        return res
    if Triad.GYRO not in triads:
        res.statements.append(
            "single triad (no gyro): gyro effects (g_sensitivity) are not identifiable"
        )
    breaks = np.flatnonzero(position_gaps_s(chain) > TURN_MAX_S)
    if breaks.size:
        res.statements.append(
            f"{breaks.size} break(s) in the recording between positions (after position(s) "
            f"{', '.join(str(int(k)) for k in breaks[:5])}{', …' if breaks.size > 5 else ''}; longest "
            f"{float(position_gaps_s(chain).max()):.4g} s): the simulated twin turns in {TURN_MAX_S:.0f} s "
            "there, so a statistic across a break compares unlike spans"
        )
    tab_a = position_table(
        chain, triad_samples(session, Triad.ACCEL), session.t_s, Triad.ACCEL, session.temp_c
    )
    temp_reason = temperature_reason(tab_a)
    if temp_reason is not None:
        res.statements.append(
            f"temperature effects (temperature_bias, temperature_scale, temperature_hysteresis) are {temp_reason}"
        )
    if chain.triads[Triad.ACCEL].estimate.params is None:
        res.statements.append(
            f"the accelerometer parameters are not observable ({chain.triads[Triad.ACCEL].estimate.reason}): no cause can be concluded"
        )
        return res
    res.baseline = fit_baselines(session, chain)
    g = chain.gravity_mps2
    n_typical = float(np.median([p.n_samples for p in chain.positions]))
    res.grade_paths = {
        t: grade_path(t, b, n_typical, reference_magnitude(t, g)) for t, b in res.baseline.items()
    }
    model = baseline_error_model(res.baseline, g)
    res.measured_stats["baseline"] = {}
    for t in triads:
        x = triad_samples(session, t)
        res.measured_stats["baseline"][t] = triad_statistics(
            chain, x, session.t_s, t, session.rate_hz
        )
        res.measured_curves[t] = triad_curves(chain, x, session.t_s, t, session.rate_hz)
    spec = same_session_spec(chain, session, model)
    reps, res.replica_curves["baseline"], refused = replica_statistics(
        spec, chain_config, triads, config.replicas, config.seed, progress=progress
    )
    if refused:
        # Without a baseline band there is nothing to compare the session or an extension with.
        if len(refused) == config.replicas:
            raise ValueError(refused_statement("baseline", refused, config.replicas))
        res.statements.append(refused_statement("baseline", refused, config.replicas))
    res.replica_stats["baseline"] = reps
    # Every position: the baseline's comparison shows what it misses, disturbed positions included.
    res.baseline_cmp = [
        c for t in triads for c in compare(t, res.measured_stats["baseline"][t], reps[t])
    ]

    res.candidates = find_candidates(session, chain, res.baseline)
    res.structure = structure_of(session, chain, res.baseline)
    res.statements += detectable_statements(res.candidates)
    if res.grade_paths.get(Triad.GYRO, {}).get("path") == "earth_rate_as_noise":
        res.statements.append(earth_rate_blind_spot(res.grade_paths[Triad.GYRO]))
    res.statements += [structure_statement(st, res.named) for st in res.structure if st.structured]
    hold, turns = simulated_timing(chain)
    turn_mid_s = simulated_hold_starts_s(hold, turns)[1:] - 0.5 * turns
    res.left_out, res.left_out_reason = left_out_positions(res.candidates)
    # The extension's noise is read without the disturbed positions: their motion, taken for noise, would
    # move every replica position (no replica moves them; they are left out on both sides).
    ext_base = (
        fit_baselines(session, chain, left_out=res.left_out) if res.left_out else res.baseline
    )
    ext_model, res.extended_model = extend_model(
        baseline_error_model(ext_base, g) if res.left_out else model,
        ext_base,
        res.candidates,
        tab_a,
        g,
        turn_mid_s,
    )
    res.extension = [
        {"effect": c.effect, "triad": c.triad.value, "axis": c.axis, "params": c.params}
        for c in res.named
    ]
    ext_checked = False
    if res.named:
        start = simulated_hold_starts_s(hold, turns)
        left_out_s = np.column_stack([start, start + hold])[list(res.left_out)]
        ext_reps, ext_curves, refused = replica_statistics(
            same_session_spec(chain, session, ext_model),
            chain_config,
            triads,
            config.replicas,
            config.seed + 1,
            left_out_s,
            progress,
            "extended",
        )
        if refused:
            res.statements.append(refused_statement("extended", refused, config.replicas))
        ext_checked = len(refused) < config.replicas
    if ext_checked:
        described = np.ones(n, bool)
        described[list(res.left_out)] = False
        res.measured_stats["extended"] = {
            t: triad_statistics(
                chain, triad_samples(session, t), session.t_s, t, session.rate_hz, described
            )
            for t in triads
        }
        res.replica_curves["extended"] = ext_curves
        res.replica_stats["extended"] = ext_reps
        res.extended_cmp = [
            c
            for t in triads
            for c in compare(t, res.measured_stats["extended"][t], ext_reps[t], res.left_out)
        ]
    else:
        res.extended_cmp = res.baseline_cmp
    excess = unexplained_excess(res.extended_cmp)
    if excess:
        res.statements.append(excess)
    res.gain = _gain(
        session, candidate_table(chain, session, Triad.ACCEL, res.baseline[Triad.ACCEL]), res, g
    )
    return res


def detectable_statements(cands: list[Candidate]) -> list[str]:
    """Per triad, what each identifiable effect needs to be named on this session (95 % power): no blind spot unsaid.

    Each candidate's ``*_min_detectable`` parameters (:func:`estimators.audit.candidates.min_detectable`), the
    first of each effect and axis; the grade path a triad took decides which are there.
    """
    out = []
    for t in Triad:
        parts = []
        for c in cands:
            if c.triad is not t or not c.identifiable:
                continue
            for k, v in c.params.items():
                if k.endswith("_min_detectable") or k.endswith("_min_detectable_norm2"):
                    best = c.params.get(f"{k}_best")
                    # A change's size depends on the turn it falls in: the range, the hardest turn first.
                    by_turn = "" if best is None else f" (at the easiest turn {best:.2g})"
                    # A change named for the triad states the size of the axis it was fitted on.
                    axis = c.axis or c.params.get("fitted_axis")
                    parts.append(
                        f"{c.effect}{'' if axis is None else ' ' + axis} {k.replace('_min_detectable', '')} {v:.2g}{by_turn}"
                    )
                    break
        if parts:
            out.append(
                f"minimum detectable on this session ({t.value}, 95 % power; units in each name): "
                + "; ".join(parts)
                + _step_competes(cands, t)
            )
    return out


def _step_competes(cands: list[Candidate], t: Triad) -> str:
    """What a drift's stated power does not account for, where a bias step is also a candidate of the triad.

    Each size is the power of one effect's test against none. A drift and a step at a middle turn both move
    the later positions' means one way, and the forward selection ranks a profiled step on a single test's
    margin (:func:`estimators.audit.candidates.forward_select`, so that a real step is not lost to a drift):
    a step can then be named in the drift's place, the drift no longer passing beside it.
    """
    kinds = {c.effect for c in cands if c.triad is t and c.identifiable}
    if not {"bias_drift", "bias_step"} <= kinds:
        return ""
    return (
        "; not accounted for: a bias_drift's size is its power against no effect, not against a bias_step "
        "profiled over the turns, which competes with it (a drift of that size can be named as a step)"
    )


def earth_rate_blind_spot(path: dict[str, str | float]) -> str:
    """What the gyro's ``earth_rate_as_noise`` path cannot see (:func:`grade_path`): said, with where its sizes are."""
    return (
        f"gyro blind spot: a position mean's noise is {float(path['mean_noise_over_reference']):.2g} Ω (the Earth rate "
        f"is resolved per position below {EARTH_RATE_RESOLVED_SD:g} Ω), so each axis carries the Earth rate's unknown "
        "projection as noise (Ω²/3): a gyro drift, g-sensitivity, bias step, temperature bias, temperature "
        "hysteresis or bias instability smaller than the gyro's minimum detectable sizes stated here is invisible, "
        "and its temperature scale and scale nonlinearity are not identifiable (clipping is read from the samples "
        "on either path)"
    )


def unexplained_excess(cmp: list[Comparison]) -> str | None:
    """``unexplained excess`` when the extended model's headline lies outside its replicas' band, with every
    statistic outside it (the named effects do not account for the data: never a silent headline)."""
    head = next((c for c in cmp if c.statistic == "chi2_per_dof"), None)
    if head is None or head.inside:
        return None
    out = [c for c in cmp if not c.inside]
    return (
        f"unexplained excess: with the named effects the headline χ²/dof is {head.measured:.3g} against the replicas' "
        f"{head.simulated_p05:.3g}–{head.simulated_p95:.3g}; outside the band: "
        + ", ".join(
            f"{c.statistic} ({c.triad.value}{'' if c.axis is None else ' ' + c.axis}: ratio {c.ratio:.2g})"
            for c in out
        )
    )


def structure_of(
    session: ImuSession, chain: ChainResult, baselines: dict[Triad, TriadBaseline]
) -> list[ResidualStructure]:
    """:func:`estimators.audit.candidates.residual_structure` of every triad on a scalar path (the
    accelerometers; a gyro that resolves the Earth rate), on the candidates' tables."""
    out = []
    tab_a = candidate_table(chain, session, Triad.ACCEL, baselines[Triad.ACCEL])
    gyro = baselines.get(Triad.GYRO)
    n_tests = count_tests(
        gyro is not None,
        temperature_reason(tab_a) is None,
        gyro is not None and gyro.scalar_resolved,
    )
    for t, b in baselines.items():
        if not b.scalar_resolved:
            continue
        tab = tab_a if t is Triad.ACCEL else candidate_table(chain, session, t, b)
        r, sd, jac, _ = scalar_residuals(b.params, tab)
        out.append(residual_structure(t, tab, jac, r, sd, n_tests))
    return out


def structure_statement(st: ResidualStructure, named: list[Candidate]) -> str:
    """What the audit made of a structured residual: the deterministic effects named on its triad, or that none was."""
    own = [c for c in named if c.triad is st.triad and c.effect not in ("quantization",)]
    det = [c for c in own if c.effect not in ("bias_instability", "nonstatic_positions")]
    if det:
        return f"{st.sentence}; explained by {', '.join(f'{c.effect} ({c.axis or st.triad.value})' for c in det)}"
    wander = [c for c in own if c.effect == "bias_instability"]
    if wander:
        return (
            f"{st.sentence}; no listed deterministic candidate passed, and the {', '.join(c.axis or '' for c in wander)} "
            "bias_instability named rests on scatter between positions: a deterministic effect the audit does not "
            "list would leave the same"
        )
    return f"{st.sentence}; no listed candidate passed its threshold"


def left_out_positions(cands: list[Candidate]) -> tuple[tuple[int, ...], str]:
    """The positions the extended model does not describe inside, and why: those ``nonstatic_positions`` names
    as moved by hand (the simulator moves every position or none, so no replica moves them).

    The extended comparison computes the statistics inside a position without them, on the measured
    session and on every replica alike (:data:`INSIDE_POSITION_STATISTICS`); empty when none is named.
    """
    c = next((c for c in cands if c.effect == "nonstatic_positions" and c.selected), None)
    left = () if c is None else tuple(int(k) for k in c.params.get("disturbed_positions", ()))
    if not left:
        return (), ""
    return left, (
        f"positions {', '.join(f'#{k}' for k in left)} move inside (nonstatic_positions) and the replicas do not "
        f"move single positions: {', '.join(INSIDE_POSITION_STATISTICS)} are computed without them, measured and "
        "simulated; the scalar fit's statistics keep them (a turn changes the direction of a mean, not its norm)"
    )


def extend_model(
    model: ErrorModel,
    baseline: dict[Triad, TriadBaseline],
    cands: list[Candidate],
    tab_a: PositionTable,
    g: float,
    turn_mid_s: FloatArray | None = None,
) -> tuple[ErrorModel, dict[Triad, TriadBaseline]]:
    """The simulator's error model with every selected effect at its fitted parameters, and the surviving noise per triad.

    Physical units of the simulator (:mod:`estimators.sim.errors`) from the
    candidates' normalized fits: a bias instability becomes a Gauss–Markov bias
    per axis, moving the other axes it loads too; temperature polynomials refer to the session's mean temperature.
    A change between positions (bias step, non-orthogonality change) happens in the middle of the
    simulated turn before its position, ``turn_mid_s`` (P − 1,) (the measured turn's without it); the
    cross-axis term, whose axis the norm does not tell, is shared equally by the three axes; a rail
    is a symmetric clip; a spectral line is simulated and its variance ``A²/2`` leaves the white noise; a
    low-pass filters white noise of the level averages keep, in place of the baseline's colour.
    """
    ext = model
    base = dict(baseline)
    drift = {t: np.zeros(3) for t in Triad}
    temp_bias = {t: np.zeros((3, len(TEMPERATURE_ORDERS))) for t in Triad}
    temp_scale = {t: np.zeros(3) for t in Triad}
    k2, k3, kc = np.zeros(3), np.zeros(3), np.zeros(3)
    gsens = np.zeros((3, 3))
    step = {t: np.zeros(3) for t in Triad}
    t_step = {t: np.zeros(3) for t in Triad}
    hysteresis = {t: np.zeros(3) for t in Triad}
    cosine_change, t_cosine = np.zeros(3), 0.0
    rails = {t: np.full(3, np.inf) for t in Triad}
    line_hz = {t: np.zeros(3) for t in Triad}
    line_amp = {t: np.zeros(3) for t in Triad}
    lowpass: dict[Triad, Candidate] = {}

    def change_time(c: Candidate) -> float:
        if turn_mid_s is None:
            return float(c.params["t_change_s"])
        return float(turn_mid_s[c.params["after_position"] - 1])

    excess = {t: np.zeros(3) for t in Triad}
    gm_sigma = {t: np.zeros(3) for t in Triad}
    gm_tau = {t: np.ones(3) for t in Triad}
    gm_loading = {t: np.eye(3) for t in Triad}
    for c in cands:
        if not c.selected:
            continue
        # A change whose axis is not identifiable is re-simulated on the alike axis of the smallest step
        # (candidates.smallest_alike): the tie's winner could need many times the step and show it as excess.
        axis = c.axis or c.params.get("simulated_axis")
        i = None if axis is None else AXES.index(axis)
        ref = g if c.triad is Triad.ACCEL else EARTH_RATE_RPS
        if c.effect == "bias_instability":
            excess[c.triad][i] = c.params["between_sd_norm"]
            gm_sigma[c.triad][i] = c.params["gm_sigma_norm"]
            gm_tau[c.triad][i] = c.params["gm_tau_s"]
            for ax, lv in c.params.get("gm_loading", {}).items():
                gm_loading[c.triad][AXES.index(ax), i] = lv
        elif c.effect == "bias_drift":
            drift[c.triad][i] = (
                c.params["rate_norm_per_s"] * g
                if c.triad is Triad.ACCEL
                else c.params["rate_rps_per_s"]
            )
        elif c.effect == "temperature_bias" and c.triad is Triad.ACCEL:
            # The polynomial's powers 1…n (candidates.temperature_bias_order).
            for k in range(len(TEMPERATURE_ORDERS)):
                key = "coef_norm_per_c" if k == 0 else f"coef{k + 1}_norm_per_c{k + 1}"
                temp_bias[c.triad][i, k] = c.params.get(key, 0.0) * g
        elif c.effect == "temperature_bias":
            temp_bias[c.triad][i, 0] = c.params["coef_rps_per_c"]
        elif c.effect == "temperature_scale":
            temp_scale[c.triad][i] = c.params["coef_per_c"]
        elif c.effect == "scale_nonlinearity":
            k2[i], k3[i] = c.params["k2_norm"] / g, c.params["k3_norm"] / g**2
        elif c.effect == "g_sensitivity":
            gsens[i] = [c.params[f"g{a}_rps_per_mps2"] for a in AXES]
        elif c.effect == "cross_axis_nonlinearity":
            kc[:] = c.params["kc_norm"] / g / 3.0
        elif c.effect == "bias_step":
            key = "step_norm" if c.triad is Triad.ACCEL else "step_rps"
            value = float(c.params[f"simulated_{key}" if c.axis is None else key])
            step[c.triad][i] = value * g if c.triad is Triad.ACCEL else value
            t_step[c.triad][i] = change_time(c)
        elif c.effect == "nonorthogonality_change":
            cosine_change = np.array([c.params[f"d_{p}_change"] for p in ("xy", "xz", "yz")])
            t_cosine = change_time(c)
        elif c.effect == "temperature_hysteresis":
            hysteresis[c.triad][i] = (
                c.params["offset_norm"] * g if c.triad is Triad.ACCEL else c.params["offset_rps"]
            )
        elif c.effect == "clipping":
            rails[c.triad][i] = abs(c.params["rail_si"])
        elif c.effect == "spectral_line":
            line_hz[c.triad][i] = c.params["freq_hz"]
            line_amp[c.triad][i] = c.params["amplitude_si"]
        elif c.effect == "lowpass":
            lowpass[c.triad] = c
        elif (
            c.effect == "nonstatic_positions"
            and c.params.get("common_wobble", True)
            and c.params["angle_rms_rad"] > 0
        ):
            # Disturbed single positions are not simulated (left out on both sides): the simulator moves every
            # position or none, and only a wobble common to every position, itself selected, moves them all.
            ext = ext.with_effect(
                NonstaticPositions(
                    angle_rms_rad=c.params["angle_rms_rad"], band_hz=tuple(c.params["band_hz"])
                )
            )
    t_ref = float(np.mean(tab_a.temp_c)) if tab_a.temp_c is not None else 20.0
    for t, b in list(base.items()):
        ref = g if t is Triad.ACCEL else EARTH_RATE_RPS
        base[t] = replace(
            b,
            excess_sd_norm=excess[t],
            gm_sigma_norm=gm_sigma[t],
            gm_tau_s=gm_tau[t],
            gm_loading=gm_loading[t],
        )
        if np.any(gm_sigma[t] > 0):
            ext = ext.with_effect(
                BiasInstability(
                    gm_sigma_si=gm_sigma[t] * ref, gm_tau_s=gm_tau[t], gm_loading=gm_loading[t]
                ),
                t,
            )
        if np.any(drift[t]):
            ext = ext.with_effect(BiasDrift(drift[t][:, None]), t)
        if np.any(temp_bias[t]):
            ext = ext.with_effect(TemperatureBias(temp_bias[t], t_ref_c=t_ref), t)
        if np.any(temp_scale[t]):
            ext = ext.with_effect(TemperatureScale(temp_scale[t][:, None], t_ref_c=t_ref), t)
        if np.any(np.isfinite(rails[t])):
            ext = ext.with_effect(Clipping(rails[t]), t)
        if np.any(step[t]):
            ext = ext.with_effect(BiasStep(t_step[t], step[t]), t)
        if np.any(hysteresis[t]):
            ext = ext.with_effect(TemperatureHysteresis(hysteresis[t]), t)
        wn = ext.triad(t).find(WhiteNoise)
        if np.any(line_amp[t]) and wn is not None:
            # The line's variance A²/2 was read as white noise: it moves to the line.
            line_var = 0.5 * line_amp[t] ** 2
            white = np.sqrt(np.clip(wn.sample_sd(1.0) ** 2 - line_var, 0.0, None))
            ext = ext.with_effect(SpectralLine(line_hz[t], line_amp[t]), t).with_effect(
                WhiteNoise.from_sample_sd(white, 1.0, wn.correlation), t
            )
            base[t] = replace(
                base[t], white_sd_si=np.sqrt(np.clip(b.white_sd_si**2 - line_var, 0.0, None))
            )
        if t in lowpass:
            # The filter is the noise's colour: it replaces the Gauss–Markov terms that stood in for it. The
            # spread about the baseline's moving mean read the filtered noise short by about the mean's share
            # (r(0) − 1/w, not r(0)(1 − 1/w): 2 % in sd at 20 Hz on 200 Hz): the input's level is what it read
            # over what it reads of the filter.
            lp = replace(
                base[t],
                colour_sigma_si=np.zeros((3, 0)),
                colour_tau_s=np.ones((3, 0)),
                colour_lr=np.zeros((3, 0)),
                lowpass_order=int(lowpass[t].params["order"]),
                lowpass_cutoff_hz=float(lowpass[t].params["cutoff_hz"]),
            )
            read = lowpass_spread_share(
                lp.lowpass_order,
                lp.lowpass_cutoff_hz,
                lp.rate_hz,
                max(2, round(NOISE_WINDOW_S * lp.rate_hz)),
            )
            base[t] = replace(
                lp, white_sd_si=lp.white_sd_si * np.sqrt(lp.lowpass_variance_share / read)
            )
            wn = ext.triad(t).find(WhiteNoise)
            chain_t = (
                ext.triad(t)
                .without(ColouredNoise.name)
                .with_effect(
                    WhiteNoise.from_sample_sd(
                        base[t].white_input_sd_si, 1.0, None if wn is None else wn.correlation
                    )
                )
                .with_effect(LowPass(base[t].lowpass_order, base[t].lowpass_cutoff_hz))
            )
            ext = replace(ext, accel=chain_t) if t is Triad.ACCEL else replace(ext, gyro=chain_t)
    if np.any(k2) or np.any(k3):
        ext = ext.with_effect(ScaleNonlinearity(k2, k3), Triad.ACCEL)
    if np.any(kc):
        ext = ext.with_effect(CrossAxisNonlinearity(kc), Triad.ACCEL)
    if np.any(cosine_change):
        ext = ext.with_effect(NonOrthogonalityChange(t_cosine, cosine_change), Triad.ACCEL)
    if np.any(gsens):
        ext = ext.with_effect(GSensitivity(gsens), Triad.GYRO)
    return ext, base


def _gain(
    session: ImuSession, tab_a: PositionTable, res: AuditResult, g: float
) -> dict[str, float]:
    """Held-out residual of the calibration and F0 false alarms, baseline versus extended (step 5).

    ``tab_a`` is the accelerometer table of :func:`candidate_table` (the noise reference the excess is fitted against).

    Held-out: each position's residual when the nine parameters are fitted
    without it (exact leave-one-out of the weighted least squares), over the sd
    each noise model predicts for it; the mean square is ≈ 1 for a model that
    states the calibration's real uncertainty. F0: the share of 1 s windows of
    the measured static data that fail with λ0 derived from each model.
    """
    base = res.baseline[Triad.ACCEL]
    ext = res.extended_model.get(Triad.ACCEL, base)
    resid, sigma, jac, _ = scalar_residuals(base.params, tab_a)
    out = {}
    for name, model in (("baseline", base), ("extended", ext)):
        var = sigma**2 + jac[:, :3] ** 2 @ model.excess_sd_norm**2
        w = 1.0 / np.sqrt(var)
        a = jac * w[:, None]
        q, _ = np.linalg.qr(a)
        coef, *_ = np.linalg.lstsq(a, resid * w, rcond=None)
        h = np.einsum("ij,ij->i", q, q)
        loo = (resid - jac @ coef) / np.clip(1.0 - h, 1e-9, None)
        out[f"heldout_rms_norm_{name}"] = float(np.sqrt(np.mean(loo**2)))
        # The held-out residual's variance is the datum's plus the prediction's: var / (1 − h).
        out[f"heldout_chi2_{name}"] = float(np.mean(loo**2 * (1.0 - h) / var))
    n_avg = f0_window_samples(session.rate_hz)
    mask = static_mask(session.n_samples, tab_a.spans)
    for name, model in (("baseline", base), ("extended", ext)):
        std = effective_noise_std_norm(model, g, n_avg)
        lam = derive_lambda0(
            noise_std_norm=std,
            false_alarm_prob=F0_FALSE_ALARM_PROB,
            quantization_norm=None if model.quant_step_si is None else model.quant_step_si / g,
            n_avg=n_avg,
        )
        r = f0_batch(
            triad_samples(session, Triad.ACCEL), mask, f0_config(base.params, g, lam.lambda0, n_avg)
        )
        out[f"f0_lambda0_{name}"] = float(lam.lambda0)
        out[f"f0_false_alarm_rate_{name}"] = float(r.n_fail / max(r.n_tests, 1))
        out[f"f0_tests_{name}"] = int(r.n_tests)
    out["f0_stated_false_alarm_prob"] = F0_FALSE_ALARM_PROB
    out["f0_window_samples"] = n_avg
    return out
