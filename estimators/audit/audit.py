"""The model audit: baseline fit, Monte Carlo of the same session, candidates, extension, gain (issue 4).

:func:`run_audit` is the whole procedure on one session:

1. **Baseline** per triad: the nine parameters of the chain (M1, refined),
   white noise from the within-position first differences
   (:func:`estimators.noise.white_noise_sd`, quantization variance removed),
   the quantization step when the output is on a grid (M2).
2. **Simulate the same session**: the measured position directions (the
   accelerometer means), durations, transitions and rate, through
   :mod:`estimators.sim` with the fitted baseline; ``replicas`` Monte Carlo
   runs through the same chain (:mod:`estimators.audit.statistics`).
3. **Compare**: ratio and tail probability per statistic, triad and axis.
4. **Candidates** (:mod:`estimators.audit.candidates`) and the selection.
5. **Extend** the simulator with the selected effects (fitted parameters),
   simulate again, and the **gain**: held-out residuals of the calibration and
   F0 false alarms on the measured data with λ0 from each noise model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimators.chain import ChainConfig, ChainResult, run_chain
from estimators.conventions import AXES, EARTH_RATE_RPS, Triad, reference_magnitude
from estimators.noise import quantization_step, white_noise_sd
from estimators.scalar import derive_lambda0, f0_batch
from estimators.session import ImuSession
from estimators.sim import (
    Bias,
    BiasDrift,
    BiasInstability,
    ErrorModel,
    GSensitivity,
    NonOrthogonality,
    NonstaticPositions,
    Quantization,
    Rounding,
    ScaleFactor,
    ScaleNonlinearity,
    SessionSpec,
    TriadErrorModel,
    WhiteNoise,
    multi_position_profile,
    simulate,
    tilt_sequence,
)

from .candidates import Candidate, _loo_rss, accel_candidates, gyro_candidates, temperature_reason
from .statistics import (
    MIN_POSITIONS,
    Comparison,
    TriadCurves,
    compare,
    f0_config,
    f0_window_samples,
    position_table,
    scalar_residuals,
    static_mask,
    triad_curves,
    triad_statistics,
)

DEFAULT_REPLICAS = 20
F0_FALSE_ALARM_PROB = 1.0e-3
"""Stated per-test false-alarm probability of the F0 gain check (1 s window means)."""


@dataclass(frozen=True)
class TriadBaseline:
    """The fitted baseline of one triad.

    Attributes
    ----------
    params : (9,) ``[b, e, d]`` normalized (zeros but the bias for a gyro whose scalar is unobservable).
    white_sd_si : (3,) per-sample white noise before quantization, SI.
    quant_step_si : (3,) output grid step, SI, or None.
    excess_sd_norm : (3,) extra bias standard deviation that does not average down (0 in the baseline).
    """

    params: np.ndarray
    white_sd_si: np.ndarray
    quant_step_si: np.ndarray | None
    excess_sd_norm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to_dict(self) -> dict:
        return {
            "params": [float(v) for v in self.params],
            "white_sd_si": [float(v) for v in self.white_sd_si],
            "quant_step_si": None if self.quant_step_si is None else [float(v) for v in self.quant_step_si],
            "excess_sd_norm": [float(v) for v in self.excess_sd_norm],
        }


def effective_noise_std_norm(baseline: TriadBaseline, reference: float, n_avg: int) -> np.ndarray:
    """(3,) per-sample noise to give :func:`estimators.scalar.derive_lambda0` for windows of ``n_avg`` samples.

    ``derive_lambda0`` divides the variance by ``n_avg``; a bias excess that does
    not average down must survive that division: ``σ_eff² = σ_w² + n_avg·v``.
    """
    white = baseline.white_sd_si / reference
    return np.sqrt(white**2 + n_avg * baseline.excess_sd_norm**2)


def _angles_from_cosines(d: np.ndarray) -> np.ndarray:
    """Six angles ``[δ_xy, δ_xz, δ_yx, δ_yz, δ_zx, δ_zy]`` whose axes have the cosines ``d`` (x on body x, y in the x-y plane)."""
    return np.array([0.0, 0.0, 0.0, -d[0], -(d[2] - d[0] * d[1]), d[1]])


def fit_baseline(session: ImuSession, chain: ChainResult, triad: Triad) -> TriadBaseline:
    """Baseline model of ``triad`` (module docstring, step 1)."""
    x = session.accel_mps2 if triad is Triad.ACCEL else session.gyro_rps
    spans = [(p.index_start, p.index_stop) for p in chain.positions]
    # Pooled over positions (weighted by their differences): each position's own mean and wander drop out.
    dof = np.array([b - a - 1 for a, b in spans], float)
    sd = np.sqrt(np.sum([d * white_noise_sd(x[a:b]) ** 2 for d, (a, b) in zip(dof, spans)], axis=0) / dof.sum())
    a, b = spans[0]
    steps = [quantization_step(x[a:b, i]) for i in range(3)]
    quant = None if any(s is None for s in steps) else np.array(steps, float)
    white = sd if quant is None else np.sqrt(np.clip(sd**2 - quant**2 / 12.0, (0.1 * sd) ** 2, None))
    est = chain.triads[triad].estimate
    if est.params is not None:
        params = np.array(est.params, float)
    else:
        ref = reference_magnitude(triad, chain.gravity_mps2)
        params = np.zeros(9)
        params[:3] = np.median([p.mean(triad) for p in chain.positions], axis=0) / ref
    return TriadBaseline(params, white, quant)


def triad_model(base: TriadBaseline, reference: float) -> TriadErrorModel:
    """The simulator chain of a baseline (non-orthogonality, scale, bias, white noise, quantization)."""
    p = base.params
    effects = [NonOrthogonality(_angles_from_cosines(p[6:9])), ScaleFactor(p[3:6]), Bias(p[:3] * reference)]
    effects.append(WhiteNoise.from_sample_sd(base.white_sd_si, 1.0))
    if base.quant_step_si is not None:
        effects.append(Quantization(base.quant_step_si, Rounding.NEAREST))
    return TriadErrorModel(tuple(effects))


def same_session_spec(chain: ChainResult, session: ImuSession, model: ErrorModel) -> SessionSpec:
    """The measured session's geometry and timing as a simulator spec (module docstring, step 2).

    Position directions are the measured accelerometer means (headings are not
    observable and do not matter to the accelerometer statistics); each hold is
    the averaged span plus the chain's trims, each turn the gap in between.
    """
    up = np.array([p.accel_mean_mps2 for p in chain.positions], float)
    trim = 2.0 * 0.25
    hold = np.array([p.duration_s for p in chain.positions]) + trim
    gaps = np.array([b.t_start_s - a.t_end_s for a, b in zip(chain.positions[:-1], chain.positions[1:])]) - trim
    profile = multi_position_profile(tilt_sequence(up), static_s=hold, transition_s=np.clip(gaps, 0.5, None))
    # White noise density is per √Hz: scale the per-sample level to the session's rate.
    rate = session.rate_hz
    model = ErrorModel(
        accel=_at_rate(model.accel, rate), gyro=_at_rate(model.gyro, rate), environment=model.environment
    )
    return SessionSpec(profile, model, rate_hz=rate, gravity_mps2=chain.gravity_mps2)


def _at_rate(chain: TriadErrorModel, rate_hz: float) -> TriadErrorModel:
    wn = chain.find("white_noise")
    if wn is None:
        return chain
    return chain.with_effect(WhiteNoise(np.array(wn.density_si_per_sqrt_hz) / np.sqrt(rate_hz)))


def replica_statistics(
    spec: SessionSpec, config: ChainConfig, triads: tuple[Triad, ...], replicas: int, seed: int
) -> tuple[dict[Triad, list[dict]], dict[Triad, list[TriadCurves]]]:
    """Statistics and plotted curves of ``replicas`` simulated sessions, per triad."""
    stats: dict[Triad, list[dict]] = {t: [] for t in triads}
    curves: dict[Triad, list[TriadCurves]] = {t: [] for t in triads}
    for r in range(replicas):
        sim = simulate(spec, np.random.SeedSequence([seed, r]).generate_state(1)[0])
        s = sim.session
        if Triad.GYRO not in triads:
            s = ImuSession(s.t_s, s.accel_mps2, None, s.temp_c)
        chain = run_chain(s, config)
        for t in triads:
            x = s.accel_mps2 if t is Triad.ACCEL else s.gyro_rps
            stats[t].append(triad_statistics(chain, x, s.t_s, t, s.rate_hz))
            curves[t].append(triad_curves(chain, x, s.t_s, t, s.rate_hz))
    return stats, curves


def gm_sigma_for_between(between_var: float, length_s: float, tau_s: float) -> float:
    """Gauss–Markov standard deviation whose position means vary by ``between_var``.

    For ``σ² e^{−|Δ|/τ}`` the mean over a position of length ``L`` varies by
    ``σ² V``, ``V = 2(τ/L)²(L/τ − 1 + e^{−L/τ})``; ``τ`` is taken as the spacing
    of the positions (the time scale the position residuals resolve).
    """
    x = length_s / tau_s
    v = 2.0 / x**2 * (x - 1.0 + np.exp(-x))
    return float(np.sqrt(between_var / v))


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
    ``measured_stats`` / ``measured_curves``: ``{Triad: ...}`` (curves: :class:`TriadCurves`, for the report).
    """

    statements: list[str]
    n_positions: int
    baseline: dict[Triad, TriadBaseline] = field(default_factory=dict)
    extended_model: dict[Triad, TriadBaseline] = field(default_factory=dict)
    baseline_cmp: list[Comparison] = field(default_factory=list)
    extended_cmp: list[Comparison] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)
    gain: dict = field(default_factory=dict)
    replicas: int = 0
    replica_stats: dict = field(default_factory=dict)
    measured_stats: dict = field(default_factory=dict)
    replica_curves: dict = field(default_factory=dict)
    measured_curves: dict = field(default_factory=dict)
    extension: list[dict] = field(default_factory=list)

    @property
    def named(self) -> list[Candidate]:
        return [c for c in self.candidates if c.selected]

    def headline(self, cmp: list[Comparison]) -> Comparison | None:
        return next((c for c in cmp if c.statistic == "chi2_per_dof"), None)

    def to_dict(self) -> dict:
        def block(cmp, models):
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
            "replicas": self.replicas,
            "baseline": block(self.baseline_cmp, self.baseline),
            "candidates": [c.to_dict() for c in self.candidates],
            "named_causes": [{"effect": c.effect, "triad": c.triad.value, "axis": c.axis, "evidence": c.reason, "params": c.params} for c in self.named],
            "extended": {**block(self.extended_cmp, self.extended_model), "effects_added": self.extension},
            "gain": self.gain,
        }


def _present(session: ImuSession) -> tuple[Triad, ...]:
    return tuple(t for t, a in ((Triad.ACCEL, session.accel_mps2), (Triad.GYRO, session.gyro_rps)) if a is not None)


def find_candidates(session: ImuSession, chain: ChainResult, accel_baseline: TriadBaseline) -> list[Candidate]:
    """Every candidate effect of :mod:`estimators.audit.candidates` fitted on a session with ≥ MIN_POSITIONS positions."""
    if len(chain.positions) < MIN_POSITIONS:
        raise ValueError(f"candidates need at least {MIN_POSITIONS} static positions, got {len(chain.positions)}")
    g = chain.gravity_mps2
    triads = _present(session)
    tab_a = position_table(chain, session.accel_mps2, session.t_s, Triad.ACCEL)
    params = accel_baseline.params
    resid, sigma, jac, _ = scalar_residuals(params, tab_a)
    n_tests = 12 + (15 if Triad.GYRO in triads else 0)
    cands = accel_candidates(tab_a, params, jac, resid, sigma, n_tests)
    if Triad.GYRO in triads:
        tab_g = position_table(chain, session.gyro_rps, session.t_s, Triad.GYRO)
        cands += gyro_candidates(tab_g, tab_a.mean * g, n_tests)
    else:
        cands.append(Candidate("g_sensitivity", Triad.GYRO, None, False, reason="not identifiable: the session has no gyro triad"))
    q = accel_baseline.quant_step_si
    qsd = None if q is None else q / np.sqrt(12.0) / accel_baseline.white_sd_si
    cands.append(
        Candidate("quantization", Triad.ACCEL, None, q is not None, 0.0, float("inf"), 1.0,
                  {} if q is None else {"step_si": [float(v) for v in q]}, False,
                  "output not on a grid" if q is None else
                  f"output on a grid of {q[0]:.4g} SI (M2); in the baseline; rounding sd is {100 * float(np.max(qsd)):.0f} % of the white noise")
    )
    return cands


def run_audit(session: ImuSession, config: AuditConfig) -> AuditResult:
    """The audit of one session (module docstring). Never names a cause it could not test: see ``statements``."""
    chain = run_chain(session, config.chain)
    n = len(chain.positions)
    triads = _present(session)
    res = AuditResult([], n, replicas=config.replicas)
    if Triad.ACCEL not in triads:
        res.statements.append("no accelerometer triad: position directions and the scalar equation are unknown; nothing can be concluded")
        return res
    if n == 0:
        res.statements.append("no static interval found: the scalar equation has nothing to test; no statistic, no candidate, no cause can be concluded")
        return res
    if n < MIN_POSITIONS:
        res.statements.append(
            f"{n} static positions (need ≥ {MIN_POSITIONS}: 9 parameters plus degrees of freedom): no statistic, no candidate, no cause can be concluded"
        )
        return res
    if Triad.GYRO not in triads:
        res.statements.append("single triad (no gyro): gyro effects (g_sensitivity) are not identifiable")
    temp_reason = temperature_reason(position_table(chain, session.accel_mps2, session.t_s, Triad.ACCEL))
    if temp_reason is not None:
        res.statements.append(f"temperature effects (temperature_bias, temperature_scale) are {temp_reason}")
    res.baseline = {t: fit_baseline(session, chain, t) for t in triads}
    g = config.chain.gravity_mps2
    model = ErrorModel(
        accel=triad_model(res.baseline[Triad.ACCEL], g),
        gyro=triad_model(res.baseline[Triad.GYRO], EARTH_RATE_RPS) if Triad.GYRO in triads else TriadErrorModel(),
    )
    spec = same_session_spec(chain, session, model)
    for t in triads:
        x = session.accel_mps2 if t is Triad.ACCEL else session.gyro_rps
        res.measured_stats[t] = triad_statistics(chain, x, session.t_s, t, session.rate_hz)
        res.measured_curves[t] = triad_curves(chain, x, session.t_s, t, session.rate_hz)
    reps, res.replica_curves["baseline"] = replica_statistics(spec, config.chain, triads, config.replicas, config.seed)
    res.replica_stats["baseline"] = reps
    res.baseline_cmp = [c for t in triads for c in compare(t, res.measured_stats[t], reps[t])]

    tab_a = position_table(chain, session.accel_mps2, session.t_s, Triad.ACCEL)
    resid, sigma, jac, _ = scalar_residuals(res.baseline[Triad.ACCEL].params, tab_a)
    cands = find_candidates(session, chain, res.baseline[Triad.ACCEL])
    res.candidates = cands

    # Extension
    ext_model, ext_base = _extend(model, res.baseline, cands, tab_a, g)
    res.extension = [{"effect": c.effect, "triad": c.triad.value, "axis": c.axis, "params": c.params} for c in res.named]
    if res.named:
        ext_reps, ext_curves = replica_statistics(same_session_spec(chain, session, ext_model), config.chain, triads, config.replicas, config.seed + 1)
        head = res.measured_stats[Triad.ACCEL].get("chi2_per_dof")
        sims = [r["chi2_per_dof"] for r in ext_reps[Triad.ACCEL] if "chi2_per_dof" in r]
        if any(c.effect == "bias_instability" and c.triad is Triad.ACCEL for c in res.named) and head is not None and sims:
            # The position-level excess is a moment of the residuals, not of the sampled process:
            # one simulated-moment step matches the headline's excess (χ²/dof − 1) by scaling it.
            scale = float(np.sqrt(max(head - 1.0, 0.0) / max(float(np.median(sims)) - 1.0, 1e-6)))
            ext_model, ext_base = _extend(model, res.baseline, cands, tab_a, g, scale)
            res.extension.append({"effect": "bias_instability", "triad": "accel", "axis": None, "params": {"simulated_moment_scale": scale}})
            ext_reps, ext_curves = replica_statistics(same_session_spec(chain, session, ext_model), config.chain, triads, config.replicas, config.seed + 2)
        res.replica_stats["extended"] = ext_reps
        res.replica_curves["extended"] = ext_curves
        res.extended_cmp = [c for t in triads for c in compare(t, res.measured_stats[t], ext_reps[t])]
    else:
        res.extended_cmp = res.baseline_cmp
    res.extended_model = ext_base
    res.gain = _gain(session, chain, tab_a, res, sigma, jac, resid, g)
    return res


def _extend(model: ErrorModel, baseline: dict, cands: list[Candidate], tab_a, g: float, accel_excess_scale: float = 1.0):
    """The error model with the selected effects and the surviving noise parameters per triad.

    ``accel_excess_scale`` multiplies the accelerometers' fitted excess (the
    simulated-moment refinement of :func:`run_audit`).
    """
    ext = model
    base = dict(baseline)
    drift = {Triad.ACCEL: np.zeros(3), Triad.GYRO: np.zeros(3)}
    k2, k3 = np.zeros(3), np.zeros(3)
    gsens = np.zeros((3, 3))
    for c in cands:
        if not c.selected:
            continue
        i = None if c.axis is None else AXES.index(c.axis)
        ref = g if c.triad is Triad.ACCEL else EARTH_RATE_RPS
        if c.effect == "bias_instability":
            excess = np.zeros(3)
            if i is None:
                excess[:] = c.params["excess_sd_norm"] * accel_excess_scale
            else:
                excess[i] = c.params["excess_sd_norm"]
            old = base[c.triad]
            base[c.triad] = TriadBaseline(old.params, old.white_sd_si, old.quant_step_si, np.maximum(old.excess_sd_norm, excess))
        elif c.effect == "bias_drift":
            drift[c.triad][i] = c.params["rate_norm_per_s"] * g if c.triad is Triad.ACCEL else c.params["rate_rps_per_s"]
        elif c.effect == "scale_nonlinearity":
            k2[i], k3[i] = c.params["k2_norm"] / g, c.params["k3_norm"] / g**2
        elif c.effect == "g_sensitivity":
            gsens[i] = [c.params[f"g{a}_rps_per_mps2"] for a in AXES]
        elif c.effect == "nonstatic_positions":
            ext = ext.with_effect(NonstaticPositions(angle_rms_rad=c.params["angle_rms_rad"]))
    length_s = float(np.median(tab_a.duration_s))
    tau_s = float(np.median(np.diff(tab_a.t_mid_s)))
    for t, b in base.items():
        if np.any(b.excess_sd_norm > 0):
            ref = g if t is Triad.ACCEL else EARTH_RATE_RPS
            sigma = [gm_sigma_for_between(float(v) ** 2, length_s, tau_s) * ref for v in b.excess_sd_norm]
            ext = ext.with_effect(BiasInstability(gm_sigma_si=sigma, gm_tau_s=np.full(3, tau_s)), t)
        if np.any(drift[t]):
            ext = ext.with_effect(BiasDrift(drift[t][:, None]), t)
    if np.any(k2) or np.any(k3):
        ext = ext.with_effect(ScaleNonlinearity(k2, k3), Triad.ACCEL)
    if np.any(gsens):
        ext = ext.with_effect(GSensitivity(gsens), Triad.GYRO)
    return ext, base


def _gain(session: ImuSession, chain: ChainResult, tab_a, res: AuditResult, sigma, jac, resid, g: float) -> dict:
    """Held-out residual of the calibration and F0 false alarms, baseline versus extended (step 5)."""
    base = res.baseline[Triad.ACCEL]
    ext = res.extended_model.get(Triad.ACCEL, base)
    v = float(np.max(ext.excess_sd_norm)) ** 2
    out = {}
    for name, var in (("baseline", sigma**2), ("extended", sigma**2 + v)):
        w = 1.0 / np.sqrt(var)
        _, _, coef = _loo_rss(jac * w[:, None], resid * w)
        q, _ = np.linalg.qr(jac * w[:, None])
        h = np.einsum("ij,ij->i", q, q)
        e = resid - jac @ coef
        loo = e / np.clip(1.0 - h, 1e-9, None)
        out[f"heldout_rms_norm_{name}"] = float(np.sqrt(np.mean(loo**2)))
        out[f"heldout_chi2_{name}"] = float(np.mean(loo**2 / var))
    n_avg = f0_window_samples(session.rate_hz)
    mask = static_mask(session.n_samples, tab_a.spans)
    for name, model in (("baseline", base), ("extended", ext)):
        std = effective_noise_std_norm(model, g, n_avg)
        lam = derive_lambda0(noise_std_norm=std, false_alarm_prob=F0_FALSE_ALARM_PROB,
                             quantization_norm=None if model.quant_step_si is None else model.quant_step_si / g, n_avg=n_avg)
        r = f0_batch(session.accel_mps2, mask, f0_config(base.params, g, lam.lambda0, n_avg))
        out[f"f0_lambda0_{name}"] = float(lam.lambda0)
        out[f"f0_false_alarm_rate_{name}"] = float(r.n_fail / max(r.n_tests, 1))
        out[f"f0_tests_{name}"] = int(r.n_tests)
    out["f0_stated_false_alarm_prob"] = F0_FALSE_ALARM_PROB
    out["f0_window_samples"] = n_avg
    return out
