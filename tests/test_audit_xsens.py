"""The conclusion of the audit on the real Xsens session (docs/audit-xsens.md).

Each number checked here is compared with a computation the audit does not make,
or with a fact about the session, named next to it.
"""

from dataclasses import replace

import numpy as np
import pytest
from real_data import XSENS, needs

from estimators.audit import AuditConfig, run_audit
from estimators.audit.audit import colour_threshold
from estimators.audit.statistics import position_table
from estimators.chain import ChainConfig, run_chain
from estimators.conventions import Triad
from estimators.noise import batch_means_sd
from estimators.positions import PositionConfig
from estimators.session import validate_session
from estimators.static_detector import StaticDetectorConfig, detect_static
from protocols.session_file import load_session

pytestmark = needs(XSENS)
G_XSENS = 9.81744  # SOURCE.md: the local gravity the original authors used


@pytest.fixture(scope="module")
def session():
    return load_session(str(XSENS)).session


@pytest.fixture(scope="module")
def detector(session):
    # What `ins-health audit` uses (the document's command): thresholds from the session's own noise.
    return StaticDetectorConfig.from_session(session)


@pytest.fixture(scope="module")
def audit(session, detector):
    # 20 replicas, the command's default: with 10 the 5–95 % band is about the replicas' range and the
    # headline (measured 8.73, extended median 6.8) sits near its edge.
    chain = ChainConfig(gravity_mps2=G_XSENS, detector=detector)
    return run_audit(session, AuditConfig(chain, replicas=20, seed=0))


def static_records(session, detector) -> list[np.ndarray]:
    """The accelerometer samples of each static interval, trimmed as the positions are (no model)."""
    trim_s = PositionConfig().trim_s
    return [
        session.accel_mps2[
            (session.t_s >= iv.t_start_s + trim_s) & (session.t_s <= iv.t_end_s - trim_s)
        ]
        for iv in detect_static(session, config=detector).intervals
    ]


def largest_excursions(session, detector, count: int) -> list[int]:
    """The ``count`` static positions whose specific-force magnitude strays farthest from its own
    median, from the raw samples (no model, no simulation): a position disturbed by a hand shows it."""
    norm = [np.linalg.norm(r, axis=1) for r in static_records(session, detector)]
    excursion = [np.abs(v - np.median(v)).max() for v in norm]
    return sorted(int(k) for k in np.argsort(excursion)[-count:])


def test_xsens_causes_are_accelerometer_wander_gyro_g_sensitivity_and_three_disturbed_positions(
    audit, session, detector
):
    named = {(c.effect, c.triad, c.axis) for c in audit.named}
    assert {("bias_instability", Triad.ACCEL, "y"), ("bias_instability", Triad.ACCEL, "z")} <= named
    assert {("g_sensitivity", Triad.GYRO, ax) for ax in "xyz"} <= named
    nonstatic = next(c for c in audit.named if c.effect == "nonstatic_positions")
    # Hand-held turns: the positions starting at 164.7, 208.4 (0.3 s after the knock at 208.1 s) and
    # 351.4 s. The raw data agree: #10 and #26 have the two largest excursions of |a| from the
    # position's median (2.5 and 2.2 times the median position's; the third, #19, 1.7 times); #13's
    # motion turns the sensed direction (its half-to-half differences) more than it changes |a|.
    assert nonstatic.params["disturbed_positions"] == [10, 13, 26]
    assert largest_excursions(session, detector, 2) == [10, 26]
    assert 208.1 < nonstatic.params["disturbed_t_start_s"][1] < 208.6
    # Screened before any wobble common to every position is fitted: none is named (with the wobble
    # fitted first it took #26's motion for a wobble of all, and the extended model overshot).
    assert nonstatic.lr < nonstatic.threshold
    # What the data rules out: no deterministic drift, no non-linearity; temperature and gravity cannot be told.
    assert not any(c.effect in ("bias_drift", "scale_nonlinearity") for c in audit.named)
    assert all(
        not c.identifiable
        for c in audit.candidates
        if c.effect in ("temperature_bias", "temperature_scale", "gravity_mismatch")
    )


def test_xsens_headline_moves_inside_the_extended_models_own_spread(audit):
    base, ext = audit.headline(audit.baseline_cmp), audit.headline(audit.extended_cmp)
    # The calibration's χ²/dof on these positions: 8.73; under white noise alone its expectation is 1,
    # and the simulated replicas of the baseline (white noise and its colour) stay below 1.8.
    assert base.measured > base.simulated_p95
    assert ext.simulated_p05 <= ext.measured <= ext.simulated_p95


def test_xsens_extended_model_states_the_calibration_uncertainty_and_cuts_f0_false_alarms(audit):
    gain = audit.gain
    # Held-out χ² per position has expectation 1 when the noise model states the real
    # uncertainty; the baseline gives 5.6, the extended model 1.3.
    assert gain["heldout_chi2_baseline"] > 3.0 and gain["heldout_chi2_extended"] < 2.0
    # F0 at the stated false-alarm probability (1e-3 per window): the baseline's λ0 is crossed
    # in 4.3 % of the measured 1 s windows, the extended model's in none of the 327.
    assert gain["f0_false_alarm_rate_extended"] < gain["f0_false_alarm_rate_baseline"]
    assert gain["f0_false_alarm_rate_extended"] <= 0.01


def test_xsens_allan_deviations_of_all_three_axes_are_inside_the_extended_band(
    audit, session, detector
):
    # The z-up first position (52 s) wanders most on z: one Gauss–Markov bias per axis brings its Allan
    # ratio inside. On x nothing wanders (no bias_instability named); its measured Allan deviation at
    # τ = L/8 (6.5 s) is 1.45 × what white noise of its per-sample sd gives, and it is inside only because
    # the simulation has the noise's short-lag colour (without it the extended ratio was 1.66–1.86).
    allan = {(c.triad, c.axis): c for c in audit.extended_cmp if c.statistic == "allan"}
    for ax in "xyz":
        c = allan[(Triad.ACCEL, ax)]
        assert c.simulated_p05 <= c.measured <= c.simulated_p95, c
    # Why the colour is right: fitted on frequencies of 1 Hz and up, it predicts the level at which
    # 0.5 s means shrink; measured directly (batch means of the static intervals, the three disturbed
    # ones left out: ~640 batches, a 2.8 % sd) x agrees within 3 sd, and white noise of the same
    # per-sample sd falls 17 % short.
    base = audit.baseline[Triad.ACCEL]
    assert np.all(base.colour_lr[:, 0] > colour_threshold()) and np.all(
        base.colour_sigma_si[:, 0] > 0
    )
    disturbed = set(largest_excursions(session, detector, 3))
    records = [r for k, r in enumerate(static_records(session, detector)) if k not in disturbed]
    measured_x = batch_means_sd(records, 50)[0]
    assert abs(base.colour_level_sd_si[0] / measured_x - 1.0) < 3 * 0.028
    assert base.white_sd_si[0] / measured_x < 1.0 - 3 * 0.028


def test_xsens_f0_per_sample_spread_is_the_noise_the_x_and_y_axes_share(audit, session, detector):
    # F0 projects each sample's noise on the gravity direction, uᵀ Σ u: the noise x and y share at the same
    # sample adds 2 u_x u_y Σ_xy, up to ±9 % of the variance in the positions tilted between x and y. The
    # baseline reads the correlation with the per-sample noise (0.5 s moving mean, pooled over positions);
    # here it is read apart, from 0.5 s batches detrended by their own mean, the disturbed positions left
    # out (a correlation's sd (1 − ρ²)/√n is about 0.005 at these 40 000 samples, and the two readings
    # differ in their windows and in the disturbed positions: 0.02).
    disturbed = set(largest_excursions(session, detector, 3))
    noise = []
    for k, r in enumerate(static_records(session, detector)):
        nb = r.shape[0] // 50
        if k not in disturbed and nb:
            batches = r[: nb * 50].reshape(nb, 50, 3)
            noise.append((batches - batches.mean(axis=1, keepdims=True)).reshape(-1, 3))
    rho_xy = np.corrcoef(np.concatenate(noise).T)[0, 1]
    base = audit.baseline[Triad.ACCEL]
    assert -0.45 < rho_xy < -0.25
    assert abs(base.noise_correlation[0, 1] - rho_xy) < 0.02
    assert np.all(np.abs(base.noise_correlation[2, :2]) < 0.05)
    f0 = {c.statistic: c for c in audit.extended_cmp if c.statistic.startswith("f0")}
    base_f0 = next(c for c in audit.baseline_cmp if c.statistic == "f0_sd")
    # The baseline, without the wander between positions, is short (1.6 %; 3.1 % with independent axes).
    assert base_f0.measured > base_f0.simulated_p95 and base_f0.ratio > 1.01
    # The extended model, the disturbed positions left out on both sides: without the correlation its
    # replicas were 0.7 % short (tail 0.05); with it, and the extension's noise read without the disturbed
    # positions too, the ratio is 1.00 (tail 0.60), inside (docs/audit-xsens.md). One correlation for every
    # position still over-reads the positions tilted between x and y a little (in the replicas the cross
    # term adds 1.6 % to the sd there, measured 1.0 %), hence the 1 % bound and no tighter.
    # The per-sample tail (99.9 % quantile) is inside: the "heavy tail" it showed was the shared noise and
    # the disturbed positions (1.07, no replica reaching it, over every position with independent axes).
    assert abs(f0["f0_sd"].ratio - 1.0) < 0.01, f0["f0_sd"]
    assert f0["f0_q999"].inside, f0["f0_q999"]


def test_xsens_half_to_half_and_allan_ratios_of_both_triads_are_inside_the_extended_band(audit):
    # Issue 13 item 4. Before: accelerometer half-to-half x 1.39 and y 1.21 outside (tail 0.00 and 0.05).
    # 1. The z wander's τ is told by the scatter of the 0.5 s means inside the positions beyond the
    #    noise's own (candidates.BatchContrasts): 4.6 s, not 1.7 s; a 1.7 s wander put more of itself
    #    into the batches the chain's σ of a mean is pooled from, inflating the replicas' x and y σ.
    # 2. The x half-to-half differences correlate with z's (−0.5 over the 35 undisturbed positions): the
    #    z wander moves x by about −0.2 of itself (candidates.fit_loading, LR 10.1 against 9.1).
    # 3. Gyro y's was above the band (1.26) through disturbed position #10, which no replica moves: the
    #    extended comparison computes the statistics inside a position over the positions the model
    #    describes, on the measured session and on every replica alike (next test).
    z = next(
        c
        for c in audit.named
        if (c.effect, c.triad, c.axis) == ("bias_instability", Triad.ACCEL, "z")
    )
    assert 3.0 < z.params["gm_tau_s"] < 8.0
    assert z.params["gm_loading_lr"]["x"] > z.params["gm_loading_threshold"]
    assert -0.4 < z.params["gm_loading"]["x"] < -0.1 and "y" not in z.params["gm_loading"]
    inside = {
        (c.triad, c.statistic, c.axis): c
        for c in audit.extended_cmp
        if c.statistic in ("halves_rms", "allan")
    }
    for key, c in inside.items():
        assert c.simulated_p05 <= c.measured <= c.simulated_p95, (key, c)
    assert len(inside) == 12


def test_xsens_extended_comparison_leaves_out_the_disturbed_positions_and_says_so(
    audit, session, detector
):
    # #10's hand-held turn, computed here from the chain's positions (no simulation): 3.9 sd on gyro y alone.
    validated, _ = validate_session(session)
    chain = run_chain(
        validated,
        replace(ChainConfig(gravity_mps2=G_XSENS, detector=detector), bias_instability_std=None),
    )
    tab = position_table(chain, validated.gyro_rps, validated.t_s, Triad.GYRO)
    z = tab.halves / (2.0 * np.sqrt(np.einsum("kii->ki", tab.cov)))
    assert abs(z[10, 1]) > 3.5
    assert audit.left_out == (10, 13, 26)
    left = audit.to_dict()["extended"]["positions_left_out"]
    assert left["positions"] == [10, 13, 26] and "halves_rms" in left["statistics"]
    assert "nonstatic_positions" in left["reason"] and "chi2_per_dof" not in left["statistics"]
    key = ("halves_rms", Triad.GYRO, "y")
    ext = next(c for c in audit.extended_cmp if (c.statistic, c.triad, c.axis) == key)
    base = next(c for c in audit.baseline_cmp if (c.statistic, c.triad, c.axis) == key)
    # The baseline keeps every position (its job is to show what it misses); over them gyro y is 1.25,
    # above the extended band; without #10, #13 and #26 it is 1.05, inside.
    assert ext.positions_left_out == (10, 13, 26) and base.positions_left_out == ()
    assert base.measured > ext.simulated_p95 and ext.inside
    # The headline is the calibration's fit over every position, on both sides.
    head = audit.headline(audit.extended_cmp)
    assert (
        head.positions_left_out == ()
        and head.measured == audit.headline(audit.baseline_cmp).measured
    )


def test_xsens_states_its_grade_paths_and_its_grid(audit):
    paths = audit.to_dict()["grade_paths"]
    assert paths["accel"]["path"] == "gravity_scalar"
    # A MEMS gyro: the position means' noise is above the Earth rate itself.
    assert paths["gyro"]["path"] == "earth_rate_as_noise"
    assert paths["gyro"]["mean_noise_over_reference"] > 1.0
    grid = next(
        c for c in audit.candidates if c.effect == "quantization" and c.triad is Triad.ACCEL
    )
    # Output on a grid of 2.418e-3 m/s² with about 3 steps of noise: M2's half-pulse correction holds.
    assert grid.params["half_pulse_correction_holds"]
    assert grid.params["step_si"][0] == pytest.approx(2.418e-3, rel=1e-3)


def test_the_report_is_sentences_and_tables_without_python_reprs(audit, tmp_path):
    """Issue 34: audit.md showed the fitted parameters as Python dict reprs (``gm_loading_lr {'x':
    2.79…}``) and the gain as raw keys. Each figure is a number with its name, a standard error
    beside its value, and the gain a table of the baseline against the extended model."""
    import re

    from service.audit_report import write_report

    md = write_report(audit, tmp_path, title="xsens").read_text()
    assert not re.search(r"[{}]|'[a-z_]+':", md)
    assert "gm_loading x -0.2" in md and "gm_loading {}" not in md
    assert re.search(r"gx_rps_per_mps2 [-\d.e]+ ± [\d.e-]+", md) and "_se " not in md
    # The extended λ0 reads the noise without the three disturbed positions, its wander fitted with each
    # leveraged residual counted as its share of a datum (0.000845 when each counted as one).
    assert "| F0 threshold λ0 | 0.000322 | 0.000849 |" in md
