"""The audit's classes of issue 13: temperature records, coarse quantization, navigation-grade gyros, grade paths.

Hidden-effect trials of :mod:`estimators.audit.hidden` at 8–10 detection standard errors:
40 seeded trials per class, the right effect and only it in at least 39. Each class's 40 trials
alternate MEMS and navigation grade and (where the class allows) sessions with and without the
temperature column; benchmarks/bench_audit.py gives the hit rate of each grade on its own.
"""

import numpy as np
import pytest

from estimators.audit import AuditConfig, run_audit
from estimators.audit.audit import fit_baselines, same_session_spec, triad_model
from estimators.audit.hidden import (
    TEMPERATURE_KINDS,
    TRIAL_UNITS,
    baseline_model,
    clean_trial,
    draw,
    hide,
    named_effects,
    near_limit_drift_named,
    session_of,
    trial,
    trial_chain_config,
)
from estimators.chain import ChainConfig, run_chain
from estimators.conventions import EARTH_RATE_RPS, Triad
from estimators.noise import dequantized_white_sd, rounding_mean_var
from estimators.session import ImuSession
from estimators.sim import ErrorModel, Grade, RecordedTemperature, simulate

G = 9.80665
DETECTION = (8.0, 10.0)
TRIALS = 40
REQUIRED = 39
COARSE = (25.0, 40.0)
"""Hidden quantization sizes of the coarse class: a step of 2.5–4 white-noise sd (the noise below
half a step, M2's Entier without dithering). Beyond ~5 sd a 5 s position freezes on one count on some
axis and the chain refuses its covariance."""


def _size(seed: int, bounds: tuple[float, float]) -> float:
    return float(np.random.default_rng([seed, 3]).uniform(*bounds))


def _grade(t: int) -> Grade:
    return (Grade.MEMS, Grade.NAVIGATION)[t % 2]


# --- (1) a measured temperature record, replayed ---------------------------------------


def test_recorded_temperature_interpolates_and_holds_its_ends():
    rec = RecordedTemperature(np.array([0.0, 10.0, 20.0]), np.array([20.0, 30.0, 25.0]))
    np.testing.assert_allclose(
        rec.temp_c_at(np.array([-5.0, 0.0, 5.0, 15.0, 20.0, 99.0])),
        [20.0, 20.0, 25.0, 27.5, 25.0, 25.0],
    )
    with pytest.raises(ValueError, match="strictly increasing"):
        RecordedTemperature(np.array([0.0, 0.0]), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="finite"):
        RecordedTemperature(np.array([0.0, 1.0]), np.array([1.0, np.nan]))


def test_the_same_session_replays_each_position_at_its_measured_temperature():
    s, chain = session_of(baseline_model(np.random.default_rng(1)), 5001)
    base = fit_baselines(s, chain)
    model = ErrorModel(accel=triad_model(base[Triad.ACCEL], G))
    sim = simulate(same_session_spec(chain, s, model), 3).session
    sim = ImuSession(sim.t_s, sim.accel_mps2, None, sim.temp_c)
    sim_chain = run_chain(sim, ChainConfig(gravity_mps2=G))
    measured = np.array([p.temp_mean_c for p in chain.positions])
    replayed = np.array([p.temp_mean_c for p in sim_chain.positions])
    assert replayed.size == measured.size
    # The cycle moves 0.6 °C/s at most; a detected span may differ by a few samples.
    assert np.max(np.abs(replayed - measured)) < 0.1, np.abs(replayed - measured)


def test_a_named_temperature_effect_is_re_simulated_on_the_record():
    h = hide(5100, "temperature_bias", Triad.ACCEL, "y", 9.0)
    s, _ = session_of(h.model, 5100)
    res = run_audit(s, AuditConfig(ChainConfig(gravity_mps2=G), replicas=5))
    assert {(c.effect, c.triad, c.axis) for c in res.named} == h.expected
    assert "extended" in res.replica_stats
    head = res.headline(res.extended_cmp)
    assert head is not None and head.inside, head


def test_temperature_effects_are_named_from_the_record():
    # MEMS: accelerometer bias and scale, gyro bias; navigation grade: the gyro scale too (a known rate).
    hits = []
    for t in range(TRIALS):
        seed, grade = 8000 + t, _grade(t)
        kinds = TEMPERATURE_KINDS + ((("temperature_scale", Triad.GYRO),) if t % 2 else ())
        kind = kinds[(t // 2) % len(kinds)]
        hits.append(trial(draw(seed, _size(seed, DETECTION), kind, grade), seed))
    assert sum(hits) >= REQUIRED, [t for t, h in enumerate(hits) if not h]


def test_effect_free_sessions_of_both_grades_name_nothing_with_or_without_temperature():
    clean = [clean_trial(8100 + k, temperature=k % 4 < 2, grade=_grade(k)) for k in range(TRIALS)]
    assert sum(clean) >= REQUIRED, [k for k, c in enumerate(clean) if not c]


# --- (3) coarse quantization -----------------------------------------------------------


def test_rounding_variance_of_a_mean_matches_the_exact_quantizer():
    # Means of round(μ + n) over 20000 samples at 400 values μ spread over one step, σ = 0.25 step.
    rng = np.random.default_rng(4)
    mu = rng.uniform(0.0, 1.0, 400)
    out = np.round(mu[:, None] + 0.25 * rng.standard_normal((400, 20000)))
    kept = out.mean(axis=1) - mu
    expected = float(rounding_mean_var(np.array(0.25), np.array(1.0)))
    # 400 draws of the kept error: its variance within 4 of its sd (and far above the sampling noise 0.25²/20000).
    assert abs(np.var(kept) / expected - 1.0) < 4.0 * np.sqrt(2.0 / 400)
    within = np.mean(np.var(out, axis=1))
    np.testing.assert_allclose(
        dequantized_white_sd(np.array([np.sqrt(within)]), np.array([1.0])), [0.25], rtol=0.02
    )


def test_coarse_quantization_is_named_and_nothing_else():
    hits = []
    for t in range(TRIALS):
        seed, grade = 8200 + t, _grade(t)
        h = hide(seed, "quantization", Triad.ACCEL, None, _size(seed, COARSE), grade=grade)
        assert h.value > 2.4 * TRIAL_UNITS[grade].accel_sd_mps2
        hits.append(trial(h, seed, temperature=t % 4 < 2))
    assert sum(hits) >= REQUIRED, [t for t, h in enumerate(hits) if not h]


def test_the_quantization_candidate_states_the_step_and_the_kept_rounding():
    h = hide(8200, "quantization", Triad.ACCEL, None, 35.0)
    s, chain = session_of(h.model, 8200)
    named = named_effects(s, chain)
    assert named == {("quantization", Triad.ACCEL, None)}
    res = run_audit(s, AuditConfig(ChainConfig(gravity_mps2=G), replicas=3))
    q = next(c for c in res.candidates if c.effect == "quantization" and c.triad is Triad.ACCEL)
    np.testing.assert_allclose(q.params["step_si"], [h.value] * 3, rtol=1e-9)
    assert not q.params["half_pulse_correction_holds"]
    assert min(q.params["rounding_over_mean_noise"]) > 1.0
    assert "noise below ½ step" in q.reason


# --- (2) navigation-grade gyros, and (5) the path each triad took ----------------------

EARTH_RATE_KINDS = (
    ("g_sensitivity", Triad.GYRO),
    ("bias_drift", Triad.GYRO),
    ("temperature_bias", Triad.GYRO),
    ("temperature_scale", Triad.GYRO),
)


def test_navigation_grade_gyro_effects_are_named_against_the_earth_rate():
    # The Earth rate's projection (unknown heading) is ~300× a position mean's noise here: regressing the
    # means on the specific force (the MEMS path) names nothing at these sizes.
    hits = []
    for t in range(TRIALS):
        seed = 8400 + t
        kind = EARTH_RATE_KINDS[t % len(EARTH_RATE_KINDS)]
        h = draw(seed, _size(seed, DETECTION), kind, Grade.NAVIGATION)
        hits.append(trial(h, seed, temperature=kind[0].startswith("temperature") or t % 8 < 4))
    assert sum(hits) >= REQUIRED, [t for t, h in enumerate(hits) if not h]


def test_each_triad_states_its_grade_path_and_why():
    paths, blind = {}, {}
    for grade in (Grade.MEMS, Grade.NAVIGATION):
        s, _ = session_of(baseline_model(np.random.default_rng(2), grade), 8500, grade=grade)
        res = run_audit(s, AuditConfig(trial_chain_config(grade, s), replicas=5))
        data = res.to_dict()
        paths[grade] = {t: p["path"] for t, p in data["grade_paths"].items()}
        assert all(p["reason"] for p in data["grade_paths"].values())
        assert res.named == []
        # The path that cannot resolve the Earth rate says what it cannot see.
        blind[grade] = [st for st in res.statements if st.startswith("gyro blind spot")]
    assert len(blind[Grade.MEMS]) == 1 and blind[Grade.NAVIGATION] == []
    assert paths[Grade.MEMS] == {"accel": "gravity_scalar", "gyro": "earth_rate_as_noise"}
    assert paths[Grade.NAVIGATION] == {"accel": "gravity_scalar", "gyro": "earth_rate_scalar"}


def test_navigation_grade_replicas_see_the_earth_rate_as_the_unit_did():
    # Headings gyrocompassed from the measured means: each replica position's gyro mean matches the measured
    # one to a few of its noise sd (~0.4 % of Ω), where an arbitrary heading would miss by up to Ω cos φ.
    grade = Grade.NAVIGATION
    s, chain = session_of(baseline_model(np.random.default_rng(3), grade), 8600, grade=grade)
    base = fit_baselines(s, chain)
    model = ErrorModel(
        accel=triad_model(base[Triad.ACCEL], G), gyro=triad_model(base[Triad.GYRO], EARTH_RATE_RPS)
    )
    sim = simulate(same_session_spec(chain, s, model), 4).session
    sim_chain = run_chain(sim, trial_chain_config(grade, s))
    measured = np.array([p.gyro_mean_rps for p in chain.positions])
    replayed = np.array([p.gyro_mean_rps for p in sim_chain.positions])
    assert replayed.shape == measured.shape
    assert np.max(np.abs(replayed - measured)) < 0.02 * EARTH_RATE_RPS


# --- a hand's wobble at navigation grade -------------------------------------------------


def test_a_navigation_grade_wobble_is_named_as_nonstatic_positions_and_nothing_else():
    # The gyros see the wobble's rate far above their noise: a chain that took it for turns cut the positions
    # into pieces and left the audit too few to name anything.
    hits = []
    for t in range(TRIALS):
        seed = 8800 + t
        kind = ("nonstatic_positions", Triad.ACCEL)
        h = draw(seed, _size(seed, DETECTION), kind, Grade.NAVIGATION)
        hits.append(trial(h, seed, temperature=t % 2 == 0))
    assert sum(hits) >= REQUIRED, [t for t, h in enumerate(hits) if not h]


# --- bias instability, sized by the evidence the test sees --------------------------------


def test_bias_instability_is_named_on_its_axis_and_nothing_else():
    # Both triads at both grades (10 trials each); the size counts the shares the test sees after the noise
    # reference and the baseline's fit took theirs (estimators.audit.hidden.gm_shares).
    hits = []
    for t in range(TRIALS):
        seed, grade = 8700 + t, _grade(t)
        kind = ("bias_instability", (Triad.ACCEL, Triad.GYRO)[(t // 2) % 2])
        hits.append(
            trial(draw(seed, _size(seed, DETECTION), kind, grade), seed, temperature=t % 8 < 4)
        )
    assert sum(hits) >= REQUIRED, [t for t, h in enumerate(hits) if not h]


# --- the gyro's path is continuous in its parameters' σ -----------------------------------


def test_a_gyro_drift_is_named_on_both_sides_of_the_nine_parameter_sigma_limit():
    # A navigation-grade unit with a noisier gyro: at 1.0e-5 rad/s per sample every gyro parameter's σ is
    # below the chain's 0.01 (observable), at 1.3e-5 the largest is 0.0115 (partially observable). Its
    # position means resolve Ω to ~1 % either way; the Earth rate taken as noise (Ω²/3) would hide this
    # drift (10 SE of the scalar path's, 0.4 of the means').
    assert near_limit_drift_named(8450, 10.0) == (True, True)
