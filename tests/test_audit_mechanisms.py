"""The audit names the mechanism (issue 31): deterministic effects are candidates of their own, not wander.

Hidden-effect trials of :mod:`estimators.audit.hidden` at 10 detection standard errors. Each class
gets 8 seeded trials here (benchmarks/bench_audit.py runs 20 and prints the rates): the issue asks
≥ 90 %; a class that met it would fall to 5 or fewer of 8 with probability ≤ 3.8 % (binomial,
p = 0.9), so ≥ 6 of 8 fails a class that misses most of the time without failing a sound one.
"""

import numpy as np
import pytest

from estimators.audit import AuditConfig, run_audit
from estimators.audit.audit import detectable_statements, unexplained_excess
from estimators.audit.candidates import (
    Candidate,
    batch_mean_covariance,
    count_tests,
    forward_select,
)
from estimators.audit.hidden import (
    LINE_KIND,
    MECHANISM_KINDS,
    PAIRS,
    baseline_model,
    draw,
    hide,
    hide_pair,
    pair_trial,
    quadratic_temperature_named,
    session_of,
    trial,
    trial_chain_config,
    window_mean_covariance,
)
from estimators.audit.statistics import Comparison
from estimators.chain import ChainConfig
from estimators.conventions import Triad
from estimators.session import ImuSession
from estimators.sim import (
    BiasStep,
    Clipping,
    CrossAxisNonlinearity,
    ErrorModel,
    Grade,
    NonOrthogonalityChange,
    NonstaticPositions,
    TemperatureHysteresis,
    TriadErrorModel,
    simulate,
    static_spec,
)
from service.audit_report import write_report

G = 9.80665
TRIALS = 8
REQUIRED = 6


@pytest.mark.parametrize("kind", MECHANISM_KINDS, ids=[k for k, _ in MECHANISM_KINDS])
def test_each_deterministic_class_is_named_as_its_mechanism_on_its_axis(kind):
    hits = [trial(draw(9100 + t, 10.0, kind), 9100 + t) for t in range(TRIALS)]
    assert sum(hits) >= REQUIRED, [t for t, h in enumerate(hits) if not h]


def test_the_named_change_carries_its_size_and_the_turn_it_happened_in(tmp_path):
    h = hide(9300, "bias_step", Triad.ACCEL, "y", 10.0)
    s, chain = session_of(h.model, 9300)
    res = run_audit(s, AuditConfig(ChainConfig(gravity_mps2=G), replicas=3))
    (c,) = res.named
    assert (c.effect, c.axis) == ("bias_step", "y")
    p = c.params
    # The fitted step within 4 of its standard errors of the hidden one; the hidden time inside the named turn.
    assert abs(p["step_norm"] - h.value) < 4.0 * p["step_norm_se"], p
    t0 = s.t_s[0]
    step_t = h.model.accel.find(BiasStep).t_step_s[1] - t0
    assert abs(step_t - p["t_change_s"]) <= p["t_change_se_s"], (step_t, p)
    assert np.isfinite(chain.positions[p["after_position"]].t_start_s)
    assert [e["effect"] for e in res.extension] == ["bias_step"]
    said = [m for m in res.statements if m.startswith("structured_residual")]
    assert len(said) == 1 and "explained by bias_step (y)" in said[0], res.statements
    # Every triad says what it can see on this session: a step's figure is se (√threshold + 1.645) at the
    # turn it is hardest to see in, and at the easiest; the named turn's lies between.
    stated = [m for m in res.statements if m.startswith("minimum detectable on this session (")]
    assert [m.split("(")[1].split(",")[0] for m in stated] == ["accel", "gyro"]
    here = p["step_norm_se"] * (np.sqrt(c.threshold) + 1.645)
    assert p["step_norm_min_detectable_best"] <= here * (1 + 1e-9), p
    assert here <= p["step_norm_min_detectable"] * (1 + 1e-9), p
    assert "bias_step y step_norm" in stated[0] and "bias_drift x" in stated[1]
    # The report shows the mechanism: the residual against time (the turn marked) and orientation.
    md = write_report(res, tmp_path, title="step").read_text()
    assert "![mechanism_bias_step_accel_y](mechanism_bias_step_accel_y.png)" in md
    assert (tmp_path / "mechanism_bias_step_accel_y.png").stat().st_size > 0


def test_a_profiled_change_that_explains_more_wins_over_a_single_test_with_a_lower_threshold():
    # 30 data: a step at 15 of 10 standard errors; a linear trend correlates with it (ρ ≈ 0.87).
    n = 30
    rng = np.random.default_rng(3)
    step = (np.arange(n) >= 15).astype(float)
    z = 10.0 * step / np.sqrt(np.sum((step - step.mean()) ** 2)) + rng.standard_normal(n)
    base = np.ones((n, 1))
    trend = (np.arange(n) - 14.5)[:, None]
    regs = {0: trend} | {b: (np.arange(n) >= b).astype(float)[:, None] for b in range(1, n)}
    tests = forward_select(base, z, regs, 10, {0: 1} | {b: n - 1 for b in range(1, n)})
    assert [k for k, t in tests.items() if t.selected] == [15]
    # The multiplicity raises the step's threshold above the trend's single test.
    assert tests[15].threshold > tests[0].threshold


def test_the_bonferroni_split_counts_the_new_candidates():
    # accel: drift, K2/K3, bias step, instability per axis (+ temperature bias, scale, hysteresis);
    # cross-axis, non-orthogonality change, nonstatic, clipping, a line, a low-pass; gyro: drift,
    # g-sensitivity, bias step, instability per axis (+ temperature bias and hysteresis, and
    # temperature scale where the gyro resolves the Earth rate), clipping, a line and a low-pass.
    assert count_tests(True, True) == 3 * 7 + 6 + 3 * 6 + 3
    assert count_tests(True, True, earth_rate=True) == 3 * 7 + 6 + 3 * 7 + 3
    assert count_tests(False, False) == 3 * 4 + 6


def test_the_new_simulator_effects_do_what_they_say():
    t = np.arange(10) * 1.0
    y = np.tile([[1.0, 2.0, 3.0]], (10, 1))
    rng = np.random.default_rng(0)

    def run(effect, temp=None):
        from estimators.sim.errors import EffectContext

        ctx = EffectContext(t, 1.0, Triad.ACCEL, G, y, temp, None, rng)
        return effect.apply(y, ctx)

    out = run(BiasStep((5.0, 2.0, 99.0), (0.5, -1.0, 7.0)))
    np.testing.assert_allclose(out[4], [1.0, 1.0, 3.0])
    np.testing.assert_allclose(out[6], [1.5, 1.0, 3.0])
    out = run(NonOrthogonalityChange(5.0, (0.1, 0.2, 0.3)))
    np.testing.assert_allclose(out[4], y[4])
    np.testing.assert_allclose(out[5], [1.0, 2.0 + 0.1, 3.0 + 0.2 + 0.3 * 2.0])
    np.testing.assert_allclose(run(CrossAxisNonlinearity((0.1, 0.0, 0.01)))[0], [1.6, 2.0, 3.02])
    np.testing.assert_allclose(run(Clipping((0.5, 9.0, 2.5)))[0], [0.5, 2.0, 2.5])
    heating = np.concatenate([np.linspace(20, 30, 5), np.linspace(30, 20, 5)])
    out = run(TemperatureHysteresis((0.2, 0.0, 0.0)), heating)
    assert out[1, 0] == pytest.approx(1.2) and out[8, 0] == pytest.approx(0.8)
    with pytest.raises(ValueError, match="positive"):
        Clipping((1.0, -1.0, 1.0))
    # Each is a model effect the audit can re-simulate: the rail holds a static axis on it.
    model = ErrorModel(accel=TriadErrorModel((Clipping((9.0, 9.0, 9.0)),)))
    s = simulate(static_spec(model=model, duration_s=1.0, rate_hz=50.0), 1).session
    assert np.max(np.abs(s.accel_mps2)) <= 9.0


def test_a_deterministic_residual_is_structured_between_positions_and_a_wander_is_not():
    from estimators.audit.audit import fit_baselines, structure_of

    def structure(effect):
        h = hide(9400, effect, Triad.ACCEL, "x", 10.0)
        s, chain = session_of(h.model, 9400)
        (st,) = structure_of(s, chain, fit_baselines(s, chain, colour=False))
        return st

    step, wander = structure("bias_step"), structure("bias_instability")
    i = "xyz".index(step.axis)
    assert step.structured and step.lr_between[i] > step.threshold > step.lr_within[i]
    assert "structured between positions" in step.sentence
    # Wander moves the bias inside positions too: the halves see it, so it is not a structure.
    assert not wander.structured and wander.lr_within[0] > wander.threshold


def test_two_deterministic_effects_at_once_are_both_named():
    # The pair (an x drift with a z scale non-linearity) and a bias step with a temperature scale,
    # 8 seeded trials each (benchmarks/bench_audit.py runs 20). Tested at the F test's estimated scale,
    # each effect's leftover diluted the other: 4 and 2 of 10 named both. ≥ 6 of 8 passes a pair named at
    # 90 % with probability 96 % (binomial) and one named at 40 % with 5 %.
    for k in (0, 3):
        hits = [pair_trial(hide_pair(9500 + t, *PAIRS[k], 10.0), 9500 + t) for t in range(8)]
        assert sum(hits) >= 6, (PAIRS[k], hits)


def test_a_wander_s_position_means_covary_as_consecutive_batch_means_do():
    # Equal windows end to end are consecutive batches; every other one, windows a batch's length apart.
    batch_s, tau_s = 5.0, 2.0
    start = batch_s * np.arange(6)
    batches = batch_mean_covariance(6, batch_s, tau_s)
    np.testing.assert_allclose(window_mean_covariance(start, start + batch_s, tau_s), batches)
    every_other = start[::2]
    np.testing.assert_allclose(
        window_mean_covariance(every_other, every_other + batch_s, tau_s), batches[::2, ::2]
    )


def test_a_cross_axis_term_next_to_a_wander_is_named_at_10_of_its_standard_errors_under_the_wander():
    # Seed 1 of the benchmark's cross-axis x + wander y pair. Sized on the effect-free session, the term was
    # 10 / 3.7 of its standard errors under the wander and only the wander was named (3 of the 20 seeds named
    # both); sized under the wander's covariance (hidden.wander_se_ratio) both are named (19 of 20).
    seed = 402_001
    pair = hide_pair(seed, *PAIRS[2], 10.0)
    assert pair_trial(pair, seed)


def test_an_effect_that_stood_in_for_two_leaves_once_both_are_selected():
    # Seed 9 of the benchmark's drift x + K2 z pair: forward selection took the drift, the K2 and a change of
    # the cosines (LR 94, threshold 26, while it stood in for parts of both); refitted against the two it adds
    # LR 1.7, so the backward step drops it and exactly the two hidden effects are named.
    seed = 400_009
    assert pair_trial(hide_pair(seed, *PAIRS[0], 10.0), seed)


def test_a_step_taken_at_the_wrong_break_moves_once_the_other_effect_is_in():
    # Seed 15 of the benchmark's step z + temperature scale x pair: the step joined first, at the break its
    # leftover with the temperature scale favoured (LR 49 there); it stayed there once the scale was in, and the
    # misfit was named as an x wander besides. The swap moves it to the break the joint fit prefers (LR 95).
    seed = 403_015
    assert pair_trial(hide_pair(seed, *PAIRS[3], 10.0), seed)


def test_an_extended_model_outside_its_band_is_said_with_the_statistics_that_are_out():
    def cmp(stat, measured, axis=None):
        return Comparison(stat, Triad.ACCEL, axis, measured, 1.0, 0.8, 1.25, measured, 0.5)

    inside = [cmp("chi2_per_dof", 1.1), cmp("allan", 1.0, "x")]
    assert unexplained_excess(inside) is None
    said = unexplained_excess(
        [cmp("chi2_per_dof", 3.0), cmp("allan", 1.7, "z"), cmp("f0_q999", 1.0)]
    )
    assert said is not None and said.startswith("unexplained excess")
    assert "chi2_per_dof (accel: ratio 3)" in said and "allan (accel z: ratio 1.7)" in said
    assert "f0_q999" not in said


def test_a_50_hz_line_is_found_with_its_axis_frequency_and_amplitude(tmp_path):
    # The case: 1.5 noise sd at 50 Hz on a 200 Hz session, 8 seeded trials (20 in the benchmark).
    # ≥ 7 of 8 passes a detector at the 95 % asked with probability 94 % (binomial).
    hits = [trial(draw(9600 + t, 1.5, LINE_KIND), 9600 + t) for t in range(8)]
    assert sum(hits) >= 7, hits
    h = hide(9610, *LINE_KIND, "z", 1.5)
    s, _ = session_of(h.model, 9610, rate_hz=h.rate_hz)
    res = run_audit(s, AuditConfig(ChainConfig(gravity_mps2=G), replicas=3))
    (line,) = [c for c in res.named if c.effect == "spectral_line"]
    p = line.params
    assert line.axis == "z" and abs(p["freq_hz"] - 50.0) <= p["freq_resolution_hz"], p
    # The amplitude from the excess over the floor: within 10 % (the floor's own scatter over 3 bins of 81 segments).
    assert abs(p["amplitude_si"] / h.value - 1.0) < 0.1, (p["amplitude_si"], h.value)
    # The line's variance A²/2 leaves the white noise of the extended model and goes to the line.
    base, ext = res.baseline[Triad.ACCEL], res.extended_model[Triad.ACCEL]
    np.testing.assert_allclose(
        base.white_sd_si[2] ** 2 - ext.white_sd_si[2] ** 2, 0.5 * p["amplitude_si"] ** 2
    )
    assert "spectral_line" in [e["effect"] for e in res.extension]
    md = write_report(res, tmp_path, title="line").read_text()
    assert (tmp_path / "mechanism_spectral_line_accel_z.png").stat().st_size > 0
    assert "spectrum_psd" not in md


def test_effect_free_200_hz_sessions_name_no_line():
    # 10 seeded sessions (40 in the benchmark): a false line anywhere would be at the audit's 1 % family-wise rate.
    named = [
        c.effect
        for k in range(10)
        for c in _named_at(9700 + k, rate_hz=200.0)
        if c.effect == "spectral_line"
    ]
    assert named == []


def _named_at(seed, rate_hz):
    from estimators.audit.audit import find_candidates, fit_baselines
    from estimators.audit.hidden import baseline_model

    s, chain = session_of(baseline_model(np.random.default_rng(seed)), seed, rate_hz=rate_hz)
    return [
        c for c in find_candidates(s, chain, fit_baselines(s, chain, colour=False)) if c.selected
    ]


def test_the_extended_replicas_move_only_the_positions_named_as_disturbed():
    # One knock: position 12 of a MEMS trial session spliced from the same unit wobbling 3 mrad rms. It is
    # named disturbed and left out of the statistics inside positions on both sides; its motion read as
    # noise moved every replica position instead (extended gyro Allan x 0.46, y 0.59, means y 0.62 of
    # the replicas', outside their band), so the gyro comparison blamed positions that never moved.
    seed = 8470
    model = baseline_model(np.random.default_rng(seed))
    s, chain = session_of(model, seed)
    moved, _ = session_of(
        model.with_effect(NonstaticPositions(angle_rms_rad=3e-3, band_hz=(0.05, 0.5))), seed
    )
    a, b = chain.positions[12].index_start, chain.positions[12].index_stop
    accel, gyro = s.accel_mps2.copy(), s.gyro_rps.copy()
    accel[a:b], gyro[a:b] = moved.accel_mps2[a:b], moved.gyro_rps[a:b]
    knocked = ImuSession(s.t_s, accel, gyro, s.temp_c)
    res = run_audit(knocked, AuditConfig(trial_chain_config(Grade.MEMS, knocked), replicas=20))
    assert res.left_out == (12,)
    gyro_inside = [
        c
        for c in res.extended_cmp
        if c.triad is Triad.GYRO and c.statistic in ("allan", "means_rms")
    ]
    assert len(gyro_inside) == 6 and all(c.inside for c in gyro_inside), gyro_inside


def test_a_quadratic_temperature_bias_is_named_as_temperature_bias_on_its_axis():
    # 1e-4 m/s2 per °C² about 30 °C on accel y over the 20–40 °C cycle (0.01 m/s² at the ends, ~16 sd of a
    # position mean). At first order the audit left the curvature to the wander: bias_instability y in 3 of
    # 3; the order chosen on held-out temperatures (M3) takes it.
    assert all(quadratic_temperature_named(seed, "y", 1e-4) for seed in (8480, 8481, 8482))


def test_a_drifts_stated_power_says_the_step_competes_with_it():
    # A drift and a step at a middle turn both move the later positions' means one way; the step, profiled
    # over the turns, can be named in the drift's place (bench_audit: a drift at 6 standard errors named in
    # 7 of 10, where its stated 95 % power puts it at 5.35). The drift's stated size is against no effect.
    cands = [
        Candidate(
            "bias_drift", Triad.ACCEL, "x", True, params={"rate_norm_per_s_min_detectable": 1e-6}
        ),
        Candidate("bias_step", Triad.ACCEL, "x", True, params={"step_norm_min_detectable": 1e-3}),
        Candidate(
            "bias_drift", Triad.GYRO, "x", True, params={"rate_rps_per_s_min_detectable": 1e-6}
        ),
    ]
    accel, gyro = detectable_statements(cands)
    assert "not against a bias_step" in accel, accel
    # Without a step among the candidates there is nothing to say.
    assert "bias_step" not in gyro, gyro
