"""Audit on bad input: a clear statement, never a made-up cause."""

import numpy as np

from estimators.audit import MIN_POSITIONS, AuditConfig, find_candidates, fit_baseline, run_audit
from estimators.audit.audit import gm_sigma_for_between
from estimators.audit.statistics import position_table, scalar_residuals
from estimators.chain import ChainConfig, run_chain
from estimators.conventions import AXES, Triad
from estimators.session import ImuSession
from estimators.sim import (
    Bias,
    BiasDrift,
    BiasInstability,
    CycleTemperature,
    ErrorModel,
    Grade,
    GSensitivity,
    NonOrthogonality,
    OrientationScheme,
    ScaleFactor,
    ScaleNonlinearity,
    TemperatureBias,
    TriadErrorModel,
    WhiteNoise,
    multi_position_spec,
    simulate,
)

G = 9.80665


def test_too_few_positions_names_nothing():
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=6, static_s=6.0, rate_hz=50.0, gravity_mps2=G)
    res = run_audit(simulate(spec, 3).session, AuditConfig(ChainConfig(gravity_mps2=G), replicas=5))
    assert res.n_positions < MIN_POSITIONS
    assert res.named == [] and res.to_dict()["named_causes"] == []
    assert "no cause can be concluded" in res.statements[0]


def test_no_static_interval_names_nothing():
    rng = np.random.default_rng(4)
    t = np.arange(2000) / 50.0
    moving = np.column_stack([np.sin(t), np.cos(t), np.sin(0.3 * t)]) * 5.0 + rng.standard_normal((2000, 3))
    res = run_audit(ImuSession(t, moving, 0.5 * rng.standard_normal((2000, 3))), AuditConfig(ChainConfig(gravity_mps2=G), replicas=5))
    assert res.n_positions == 0 and res.named == []


def test_single_triad_and_no_temperature_are_stated_not_absent():
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=18, static_s=6.0, rate_hz=50.0, gravity_mps2=G)
    s = simulate(spec, 5).session
    res = run_audit(ImuSession(s.t_s, s.accel_mps2, None), AuditConfig(ChainConfig(gravity_mps2=G), replicas=5))
    assert any("single triad" in m for m in res.statements)
    g_sens = [c for c in res.candidates if c.effect == "g_sensitivity"]
    assert g_sens and not g_sens[0].identifiable and "no gyro" in g_sens[0].reason
    temp = [c for c in res.candidates if c.effect.startswith("temperature")]
    assert temp and all(not c.identifiable and "no temperature" in c.reason for c in temp)
    assert all(not c.identifiable for c in res.candidates if c.effect == "gravity_mismatch")


# --- hidden-effect batch -------------------------------------------------------
# A session of 27 random positions (5 s, 3 s turns, 50 Hz) with a non-monotone
# temperature cycle, so time and temperature effects can be told apart. The
# magnitude of a hidden effect is stated in units of its own detection standard
# error (the candidate's coefficient sd on the effect-free session of the same
# seed; for bias_instability the median predicted residual sd): "resolvable"
# means ≥ 8 of them (the Bonferroni F threshold is ≈ 4 for one parameter).

HIDDEN = ("bias_drift", "temperature_bias", "scale_nonlinearity", "bias_instability", "g_sensitivity")
RATE_HZ, HOLD_S = 50.0, 5.0


def _baseline_model(rng):
    acc = TriadErrorModel((NonOrthogonality(rng.normal(0, 1e-3, 6)), ScaleFactor(rng.normal(0, 2e-3, 3)), Bias(rng.normal(0, 0.05, 3)),
                           WhiteNoise.from_sample_sd(np.full(3, 0.01), RATE_HZ)))
    gyr = TriadErrorModel((Bias(rng.normal(0, 2e-3, 3)), WhiteNoise.from_sample_sd(np.full(3, 2e-3), RATE_HZ)))
    return ErrorModel(accel=acc, gyro=gyr)


def _session(model, seed):
    spec = multi_position_spec(model=model, n_positions=27, scheme=OrientationScheme.RANDOM, orientation_rng=np.random.default_rng(seed),
                               static_s=HOLD_S, transition_s=3.0, rate_hz=RATE_HZ, gravity_mps2=G, temperature=CycleTemperature(20.0, 40.0, 110.0))
    s = simulate(spec, seed).session
    return s, run_chain(s, ChainConfig(gravity_mps2=G))


def _named(model, seed):
    s, chain = _session(model, seed)
    return {(c.effect, c.triad, c.axis) for c in find_candidates(s, chain, fit_baseline(s, chain, Triad.ACCEL)) if c.selected}, (s, chain)


def _hide(model, effect, axis, size, seed, rng):
    """``model`` with ``effect`` of ``size`` detection standard errors (sign random) on ``axis``."""
    s, chain = _session(model, seed)
    sign = rng.choice([-1.0, 1.0])
    i = AXES.index(axis)
    if effect == "bias_instability":
        tab = position_table(chain, s.accel_mps2, s.t_s, Triad.ACCEL)
        sd = np.median(scalar_residuals(fit_baseline(s, chain, Triad.ACCEL).params, tab)[1])
        # τ = 3 s < the 8 s spacing: positions nearly independent; "size" counts the median sd of the position residual.
        sigma = gm_sigma_for_between((0.5 * size * sd) ** 2, HOLD_S, 3.0) * G
        return model.with_effect(BiasInstability(gm_sigma_si=np.full(3, sigma), gm_tau_s=np.full(3, 3.0)), Triad.ACCEL), None
    triad = Triad.GYRO if effect == "g_sensitivity" else Triad.ACCEL
    cand = next(c for c in find_candidates(s, chain, fit_baseline(s, chain, Triad.ACCEL)) if c.effect == effect and c.triad is triad and c.axis == axis)
    key = {"bias_drift": "rate_norm_per_s", "temperature_bias": "coef_norm_per_c", "scale_nonlinearity": "k2_norm", "g_sensitivity": f"g{axis}_rps_per_mps2"}[effect]
    value = sign * size * cand.params[f"{key}_se"]
    if effect == "bias_drift":
        coef = np.zeros((3, 1))
        coef[i, 0] = value * G
        return model.with_effect(BiasDrift(coef), triad), axis
    if effect == "temperature_bias":
        coef = np.zeros((3, 1))
        coef[i, 0] = value * G
        return model.with_effect(TemperatureBias(coef), triad), axis
    if effect == "scale_nonlinearity":
        k2 = np.zeros(3)
        k2[i] = value / G
        return model.with_effect(ScaleNonlinearity(k2, np.zeros(3)), triad), axis
    gs = np.zeros((3, 3))
    gs[i, i] = value
    return model.with_effect(GSensitivity(gs), triad), axis


def test_hidden_effect_at_resolvable_size_is_named_and_nothing_else():
    hits = []
    for trial in range(40):
        seed = 5000 + trial
        rng = np.random.default_rng(seed)
        effect = HIDDEN[trial % len(HIDDEN)]
        axis = AXES[int(rng.integers(3))]
        model, named_axis = _hide(_baseline_model(np.random.default_rng(seed)), effect, axis, float(rng.choice([8.0, 10.0])), seed, rng)
        triad = Triad.GYRO if effect == "g_sensitivity" else Triad.ACCEL
        named, _ = _named(model, seed)
        hits.append(named == {(effect, triad, named_axis)})
    assert np.mean(hits) >= 0.95, f"hit rate {np.mean(hits):.3f}"


def test_effect_free_sessions_name_nothing():
    clean = [not _named(_baseline_model(np.random.default_rng(7000 + k)), 7000 + k)[0] for k in range(40)]
    assert np.mean(clean) >= 0.95, f"clean rate {np.mean(clean):.3f}"
