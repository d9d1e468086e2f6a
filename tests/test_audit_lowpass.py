"""The firmware's anti-alias low-pass is a noise colour the audit names (issue 31, item 3).

A Butterworth low-pass keeps the spectrum at 0 (the level position means see) and takes the rest: the
per-sample variance is ``σ²∫|H|²``. The audit fits order and cut-off on the static spectrum, names them with
their uncertainty, simulates the filter in the extended replicas and reads the per-sample noise through it.
Seeded sessions of :mod:`estimators.audit.hidden`; benchmarks/bench_audit.py --shapes runs 40 of each of the
issue's shapes, whose 12-position sessions are tested here too.
"""

import numpy as np

from estimators.audit import AuditConfig, run_audit
from estimators.audit.audit import (
    TriadBaseline,
    effective_noise_std_norm,
    find_candidates,
    fit_baselines,
    triad_model,
)
from estimators.audit.hidden import (
    LOWPASS_CUTOFF_HZ,
    LOWPASS_KIND,
    LOWPASS_ORDER,
    baseline_model,
    hide,
    named_effects,
    session_of,
    trial_chain_config,
)
from estimators.conventions import Triad
from estimators.noise import (
    lowpass_autocovariance,
    lowpass_mean_variance,
    lowpass_spread_share,
    sample_noise_sd,
)
from estimators.sim import ColouredNoise, EffectContext, Grade, LowPass
from service.audit_report import write_report


def _lowpass(cands):
    return {c.triad: c for c in cands if c.effect == "lowpass"}


def test_a_lowpass_session_names_the_filter_with_its_order_and_cutoff_within_its_interval(tmp_path):
    h = hide(9800, *LOWPASS_KIND, None, 0.0)
    s, _ = session_of(h.model, 9800, rate_hz=h.rate_hz)
    res = run_audit(s, AuditConfig(trial_chain_config(Grade.MEMS, s), replicas=3))
    assert {(c.effect, c.triad, c.axis) for c in res.named} == h.expected
    lp = _lowpass(res.named)[Triad.ACCEL]
    p = lp.params
    assert p["order"] == LOWPASS_ORDER and LOWPASS_ORDER in p["orders_consistent"], p["lr_by_order"]
    assert p["cutoff_low_hz"] <= LOWPASS_CUTOFF_HZ <= p["cutoff_high_hz"], p
    # The interval is the data's (jackknifed), not a token: narrower than a tenth of the cut-off.
    assert p["cutoff_high_hz"] - p["cutoff_low_hz"] < 0.1 * LOWPASS_CUTOFF_HZ
    # The extension filters white noise of the level averages keep, in place of the baseline's colour.
    ext = res.extended_model[Triad.ACCEL]
    assert (ext.lowpass_order, ext.colour_sigma_si.shape[1]) == (LOWPASS_ORDER, 0)
    assert res.baseline[Triad.ACCEL].lowpass_order == 0
    md = write_report(res, tmp_path, title="lowpass").read_text()
    assert (tmp_path / "mechanism_lowpass_accel_triad.png").stat().st_size > 0
    assert "fitted_si2" not in md


def test_white_sessions_at_200_and_50_hz_name_no_lowpass():
    # The filter is tested against white noise at the audit's family-wise rate; a white session's
    # spectrum is flat up to Nyquist, where every low-pass of the bilinear design falls to zero.
    for seed, rate in ((9810, 200.0), (9811, 50.0), (9812, 200.0)):
        s, chain = session_of(baseline_model(np.random.default_rng(seed)), seed, rate_hz=rate)
        lp = _lowpass(find_candidates(s, chain, fit_baselines(s, chain, colour=False)))
        assert set(lp) == {Triad.ACCEL, Triad.GYRO}
        assert all(c.identifiable and not c.selected for c in lp.values()), [
            c.reason for c in lp.values()
        ]


def test_twelve_positions_at_200_hz_are_audited_without_a_singular_design():
    # A change at the last break of 12 positions is not told apart from the nine parameters: it cannot be
    # named, and it used to stop the candidates with a singular matrix.
    s, chain = session_of(
        baseline_model(np.random.default_rng(200)), 200, rate_hz=200.0, n_positions=12
    )
    assert len(chain.positions) == 12
    assert named_effects(s, chain) == set()


def test_twelve_positions_leave_three_degrees_of_freedom_not_twelve_to_a_wander():
    # Navigation grade, 12 positions at 200 Hz (a shape of the benchmark): the scalar residuals scatter at
    # χ²₃ = 10.2 (p = 1.7 %); counted as 12 independent data they named an accelerometer y wander at LR 23.4.
    seed = 803017
    s, chain = session_of(
        baseline_model(np.random.default_rng(seed), Grade.NAVIGATION),
        seed,
        temperature=False,
        grade=Grade.NAVIGATION,
        rate_hz=200.0,
        n_positions=12,
    )
    assert named_effects(s, chain) == set()


def test_filtered_noise_is_read_through_the_filter():
    rate, fc, n_avg, n = 200.0, 20.0, 200, 400_000
    rng = np.random.default_rng(9820)
    lp = LowPass(LOWPASS_ORDER, fc)
    ctx = EffectContext(
        np.arange(n) / rate, rate, Triad.ACCEL, 9.8, np.zeros((n, 3)), None, None, rng
    )
    x = lp.apply(rng.normal(size=(n, 1)), ctx)
    r0 = float(lowpass_autocovariance(LOWPASS_ORDER, fc, rate, 1)[0])
    # The per-sample variance is ∫|H|² of the input's; its sampling sd over 400k samples is well under 1 %.
    assert abs(np.var(x) / r0 - 1.0) < 0.02
    # About the baseline's 0.5 s moving mean the spread reads lowpass_spread_share of the input, not r(0).
    read = sample_noise_sd(x, 100)[0] ** 2
    assert abs(read / lowpass_spread_share(LOWPASS_ORDER, fc, rate, 100) - 1.0) < 0.02
    assert read / r0 < 0.97
    # A 1 s window's mean keeps the input's level: its variance over 2000 windows within 3 of its sd (√(2/2000)).
    means = x[: 2000 * n_avg].reshape(2000, n_avg).mean(axis=1)
    v = lowpass_mean_variance(LOWPASS_ORDER, fc, rate, n_avg)
    assert abs(np.var(means) / v - 1.0) < 3.0 * np.sqrt(2.0 / 2000)
    # F0's noise for those windows: the effective per-sample noise times 1/√n_avg is that level.
    base = TriadBaseline(
        np.zeros(9),
        np.full(3, np.sqrt(r0)),
        None,
        rate,
        np.ones(3),
        lowpass_order=LOWPASS_ORDER,
        lowpass_cutoff_hz=fc,
    )
    np.testing.assert_allclose(effective_noise_std_norm(base, 1.0, n_avg) ** 2 / n_avg, v)
    np.testing.assert_allclose(effective_noise_std_norm(base, 1.0, 1) ** 2, r0)
    model = triad_model(base, 1.0)
    assert model.find(LowPass) == lp and model.find(ColouredNoise) is None
