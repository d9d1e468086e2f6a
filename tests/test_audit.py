"""Audit on bad input (a clear statement, never a made-up cause), hidden effects named, and the report's plots."""

import re

import numpy as np
import pytest

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
    ConstantTemperature,
    CycleTemperature,
    ErrorModel,
    Grade,
    GSensitivity,
    NonOrthogonality,
    NonstaticPositions,
    OrientationScheme,
    ScaleFactor,
    ScaleNonlinearity,
    TemperatureBias,
    TemperatureScale,
    TriadErrorModel,
    WhiteNoise,
    multi_position_spec,
    simulate,
)
from protocols.session_file import write_csv_session
from service.audit_report import PLOTS
from service.cli import main

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
    assert res.n_positions == 0 and res.named == [] and res.candidates == []
    assert res.statements == ["no static interval found: the scalar equation has nothing to test; no statistic, no candidate, no cause can be concluded"]


def test_constant_temperature_makes_temperature_effects_not_identifiable_with_the_reason():
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=18, static_s=6.0, rate_hz=50.0, gravity_mps2=G, temperature=ConstantTemperature(25.0))
    res = run_audit(simulate(spec, 6).session, AuditConfig(ChainConfig(gravity_mps2=G), replicas=5))
    temp = [c for c in res.candidates if c.effect.startswith("temperature")]
    assert {(c.effect, c.triad) for c in temp} == {(e, t) for e in ("temperature_bias", "temperature_scale") for t in (Triad.ACCEL, Triad.GYRO)}
    assert all(not c.identifiable and not c.selected for c in temp)
    # A gyro's temperature scale is out of reach anyway (no known rate); every other one for the constant temperature.
    by_span = [c for c in temp if not (c.triad is Triad.GYRO and c.effect == "temperature_scale")]
    assert len(by_span) == 9 and all("temperature spans 0.00 °C" in c.reason for c in by_span)
    assert not any(c.effect.startswith("temperature") for c in res.named)
    assert any(m.startswith("temperature effects") and "not identifiable" in m for m in res.statements)


def test_gyro_only_session_concludes_nothing_and_says_why():
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=18, static_s=6.0, rate_hz=50.0, gravity_mps2=G)
    s = simulate(spec, 8).session
    res = run_audit(ImuSession(s.t_s, None, s.gyro_rps), AuditConfig(ChainConfig(gravity_mps2=G), replicas=5))
    assert res.named == [] and res.candidates == [] and res.baseline_cmp == []
    assert "no accelerometer triad" in res.statements[0] and "nothing can be concluded" in res.statements[0]


def test_candidates_on_too_few_positions_are_refused():
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=6, static_s=6.0, rate_hz=50.0, gravity_mps2=G)
    s = simulate(spec, 3).session
    chain = run_chain(s, ChainConfig(gravity_mps2=G))
    with pytest.raises(ValueError, match="at least 12 static positions"):
        find_candidates(s, chain, fit_baseline(s, chain, Triad.ACCEL))


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

# nonstatic_positions: a slow wobble (0.05–0.5 Hz, the sag of a soft table) that the static detector
# keeps; its size counts the predicted sd of a position's half-to-half difference (a turn of rms θ moves the
# perpendicular half means by ≈ √2 θ).

HIDDEN = ("bias_drift", "temperature_bias", "temperature_scale", "scale_nonlinearity", "bias_instability", "g_sensitivity", "nonstatic_positions")
WOBBLE_BAND_HZ = (0.05, 0.5)
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
    if effect == "nonstatic_positions":
        tab = position_table(chain, s.accel_mps2, s.t_s, Triad.ACCEL)
        sd_half = 2.0 * np.sqrt(np.median(np.einsum("kii->ki", tab.cov)))
        return model.with_effect(NonstaticPositions(angle_rms_rad=size * sd_half / np.sqrt(2.0), band_hz=WOBBLE_BAND_HZ)), None
    triad = Triad.GYRO if effect == "g_sensitivity" else Triad.ACCEL
    cand = next(c for c in find_candidates(s, chain, fit_baseline(s, chain, Triad.ACCEL)) if c.effect == effect and c.triad is triad and c.axis == axis)
    key = {"bias_drift": "rate_norm_per_s", "temperature_bias": "coef_norm_per_c", "temperature_scale": "coef_per_c", "scale_nonlinearity": "k2_norm",
           "g_sensitivity": f"g{axis}_rps_per_mps2"}[effect]
    value = sign * size * cand.params[f"{key}_se"]
    if effect == "bias_drift":
        coef = np.zeros((3, 1))
        coef[i, 0] = value * G
        return model.with_effect(BiasDrift(coef), triad), axis
    if effect == "temperature_bias":
        coef = np.zeros((3, 1))
        coef[i, 0] = value * G
        return model.with_effect(TemperatureBias(coef), triad), axis
    if effect == "temperature_scale":
        coef = np.zeros((3, 1))
        coef[i, 0] = value
        return model.with_effect(TemperatureScale(coef), triad), axis
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


def test_temperature_cycle_is_not_a_proxy_for_time():
    # Time and temperature effects are told apart only when the position temperatures do not follow time.
    s, chain = _session(_baseline_model(np.random.default_rng(1)), 5000)
    tab = position_table(chain, s.accel_mps2, s.t_s, Triad.ACCEL)
    steps = np.diff(tab.temp_c)
    assert np.any(steps > 0) and np.any(steps < 0)
    assert abs(np.corrcoef(tab.t_mid_s, tab.temp_c)[0, 1]) < 0.5


def test_effect_free_sessions_name_nothing():
    clean = [not _named(_baseline_model(np.random.default_rng(7000 + k)), 7000 + k)[0] for k in range(40)]
    assert np.mean(clean) >= 0.95, f"clean rate {np.mean(clean):.3f}"


def test_report_writes_the_plots_the_markdown_shows(tmp_path, capsys):
    rng = np.random.default_rng(11)
    model = _baseline_model(rng)
    # An obvious drift, so the extended model exists and its bands are drawn too.
    model = model.with_effect(BiasDrift(np.array([[0.0], [0.0], [2e-4]])), Triad.ACCEL)
    spec = multi_position_spec(model=model, n_positions=16, scheme=OrientationScheme.RANDOM, orientation_rng=rng, static_s=HOLD_S,
                               transition_s=3.0, rate_hz=RATE_HZ, gravity_mps2=G)
    write_csv_session(tmp_path / "s.csv", simulate(spec, 11).session)
    out = tmp_path / "report"
    assert main(["audit", str(tmp_path / "s.csv"), "--gravity", str(G), "--replicas", "5", "--report", str(out)]) == 0
    assert "CAUSE bias_drift accel z" in capsys.readouterr().out
    md = (out / "audit.md").read_text()
    shown = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert shown == list(PLOTS)
    for name in shown:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_report_of_an_unusable_session_states_why_and_draws_nothing(tmp_path):
    spec = multi_position_spec(grade=Grade.MEMS, n_positions=6, static_s=6.0, rate_hz=50.0, gravity_mps2=G)
    write_csv_session(tmp_path / "s.csv", simulate(spec, 3).session)
    assert main(["audit", str(tmp_path / "s.csv"), "--gravity", str(G), "--replicas", "5", "--report", str(tmp_path / "r")]) == 0
    md = (tmp_path / "r" / "audit.md").read_text()
    assert "no cause can be concluded" in md and ".png" not in md
    assert not list((tmp_path / "r").glob("*.png"))
