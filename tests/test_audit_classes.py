"""The audit's classes of issue 13: temperature records, coarse quantization (and, per triad, the grade path).

Hidden-effect trials of :mod:`estimators.audit.hidden` at 8–10 detection standard errors:
40 seeded trials per class, the right effect and only it in at least 39.
"""

import numpy as np
import pytest

from estimators.audit import AuditConfig, run_audit
from estimators.audit.audit import fit_baselines, same_session_spec, triad_model
from estimators.audit.hidden import (
    ACCEL_SD_MPS2,
    TEMPERATURE_KINDS,
    baseline_model,
    clean_trial,
    draw,
    hide,
    named_effects,
    session_of,
    trial,
)
from estimators.chain import ChainConfig, run_chain
from estimators.conventions import Triad
from estimators.noise import dequantized_white_sd, rounding_mean_var
from estimators.session import ImuSession
from estimators.sim import ErrorModel, RecordedTemperature, simulate

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
    hits = []
    for t in range(TRIALS):
        seed = 8000 + t
        kind = TEMPERATURE_KINDS[t % len(TEMPERATURE_KINDS)]
        hits.append(trial(draw(seed, _size(seed, DETECTION), kind), seed))
    assert sum(hits) >= REQUIRED, [t for t, h in enumerate(hits) if not h]


def test_a_session_with_temperature_and_no_effect_names_nothing():
    clean = [clean_trial(8100 + k) for k in range(TRIALS)]
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
        seed = 8200 + t
        h = hide(seed, "quantization", Triad.ACCEL, None, _size(seed, COARSE))
        assert h.value > 2.4 * ACCEL_SD_MPS2
        hits.append(trial(h, seed, temperature=t % 2 == 0))
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
