"""diagnose's findings beyond one fit of the whole session (issue 28): F0 failing persistently is a
fault even without the nine parameters, six-position sessions are diagnosed by the M4 fits that
made their passport, a fault that began mid-session is found in the positions after it, and the
exit status says which (0 tested, no fault; 1 a fault; 2 unusable input; 3 not enough to test)."""

import dataclasses
import json

import numpy as np
import pytest
from real_data import XSENS, needs
from service_support import batches_of, run_fleet

from estimators.conventions import Triad
from estimators.ninepar import SOURCE_VECTOR
from estimators.sim import Fault, FaultKind, Grade, grade_error_model, multi_position_spec, simulate
from estimators.sixpos import ferraris_spec
from protocols.passport_codec import read_passport_json
from protocols.session_file import read_csv_session, write_csv_session
from service.cli import main
from service.pipeline import FleetProcessor, PipelineOptions

MODEL = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
SCALE_Z = 5  # parameter index of e_z
SCALE_Y = 4
F0_FAULT = 0.04
"""A z scale error this large moves ½(|ã|²−1) by about e·u_z² = 0.04 with z vertical: beyond the
MEMS passport's shell (λ0 ≈ 0.016, mostly its tolerances), so F0 sees it; 20× the tolerance of e_z."""


def _diagnose(capsys, path, passport, *extra):
    """(exit status, text) and (exit status, JSON) of diagnose."""
    argv = ["diagnose", str(path), "--passport", str(passport), "--latitude", "45", *extra]
    capsys.readouterr()
    status = main(argv)
    text = capsys.readouterr().out
    json_status = main([*argv, "--json"])
    return status, text, json_status, json.loads(capsys.readouterr().out)


@pytest.fixture(scope="module")
def unit(tmp_path_factory):
    """An 18-position MEMS session, its passport, and the multi-position sessions under test."""
    d = tmp_path_factory.mktemp("diag")
    clean = simulate(multi_position_spec(model=MODEL), seed=30)
    write_csv_session(d / "clean.csv", clean.session)
    argv = ["calibrate", str(d / "clean.csv"), "--out", str(d / "pp.json"), "--latitude", "45"]
    assert main([*argv, "--no-audit"]) == 0
    return d, clean


# --- F0 is a finding -----------------------------------------------------------------------------


def test_f0_failing_on_five_positions_is_a_fault_exit_1(unit, capsys):
    """Five positions cannot fit nine parameters; F0 failed on a third of the rest samples and the
    answer was NOT DIAGNOSED, exit 3, no fault. F0 alone is the finding."""
    d, _ = unit
    fault = Fault(FaultKind.STEP, Triad.ACCEL, SCALE_Z, 0.0, F0_FAULT)
    res = simulate(multi_position_spec(model=MODEL, n_positions=5, faults=(fault,)), seed=34)
    write_csv_session(d / "five.csv", res.session)
    status, text, json_status, doc = _diagnose(capsys, d / "five.csv", d / "pp.json")
    assert status == json_status == 1
    assert "NOT DIAGNOSED: accel: 5 positions" in text  # the nine parameters: still not fitted
    (line,) = [x for x in text.splitlines() if x.startswith("  FAULT F0: accel")]
    f0 = doc["f0"]["accel"]
    assert f0["persistent"] and f0["failed"] > 1000
    assert f"on {f0['failed']} of {f0['tested']} static samples" in line
    # The gross test finds the unit off g at rest too (tests/test_gross.py): here F0's finding.
    named = [f for f in doc["faults"] if f["predicate"] != "gross"]
    assert [(f["predicate"], f["triad"]) for f in named] == [("F0", "accel")]
    found = named[0]
    # The z faces fail first: |s| ≈ 0.04 there, beyond λ0.
    assert found["failed"] == f0["failed"] and found["first_t_s"] == f0["onset_t_s"]
    assert f0["lambda0"] < found["worst"] < 1.5 * F0_FAULT


def test_a_knock_is_counted_and_said_not_a_fault(unit, capsys):
    """One sample far off the shell at rest (a knock: shorter than the 20 ms the service's
    persistence asks) is counted and named, and stays what it is: not a fault."""
    d, _ = unit
    res = simulate(multi_position_spec(model=MODEL, n_positions=5), seed=35)
    session = res.session
    k = int(np.searchsorted(session.t_s, np.mean(res.truth.static_intervals_s[2])))
    session.accel_mps2[k] *= 1.03  # |s| ≈ 0.03: out of the shell, too small to end the rest
    write_csv_session(d / "knock.csv", session)
    status, text, json_status, doc = _diagnose(capsys, d / "knock.csv", d / "pp.json")
    assert status == json_status == 3
    f0 = doc["f0"]["accel"]
    assert f0["failed"] == f0["knocks"] == 1 and not f0["persistent"]
    assert doc["faults"] == [] and "FAULT" not in text
    assert "in 1 knock shorter than 0.02 s" in text and "not a fault" in text


# --- six-position sessions -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    """Ferraris-type sessions (six faces, with and without full turns) and their passports."""
    d = tmp_path_factory.mktemp("six")
    for turns in (True, False):
        res = simulate(ferraris_spec(MODEL, static_s=8.0, turns=turns), seed=8)
        path = d / f"cal-{turns}.csv"
        write_csv_session(path, res.session, metadata={"gravity_mps2": res.truth.gravity_mps2})
        out = d / f"pp-{turns}.json"
        assert main(["calibrate", str(path), "--out", str(out), "--no-audit"]) == 0
    return d


def _six_session(d, turns, faults, seed):
    spec = dataclasses.replace(ferraris_spec(MODEL, static_s=8.0, turns=turns), faults=faults)
    res = simulate(spec, seed=seed)
    path = d / f"s-{turns}-{seed}-{len(faults)}.csv"
    write_csv_session(path, res.session, metadata={"gravity_mps2": res.truth.gravity_mps2})
    return path


@pytest.mark.parametrize("turns", [True, False])
def test_a_six_position_session_of_the_unit_diagnoses_as_no_fault_against_its_passport(
    six, capsys, turns
):
    """Another session of the unit that made the passport: the vector fit (and the turns) diagnose
    it, nothing fails. Without turns the gyro has no passport: not tested, said, exit 3."""
    path = _six_session(six, turns, (), seed=9)
    status, text, _, doc = _diagnose(capsys, path, six / f"pp-{turns}.json")
    accel = doc["triads"]["accel"]
    assert accel["diagnosed"] and accel["estimate"]["sources"] == [SOURCE_VECTOR] * 9
    assert doc["faults"] == [] and "FAULT" not in text
    if turns:
        assert doc["triads"]["gyro"]["diagnosed"]
        assert status == 0 and "  no fault" in text.splitlines()
    else:
        assert status == 3
        assert "  no finding within coverage; not tested: gyro: no passport for this triad" in text


@pytest.mark.parametrize("turns", [True, False])
def test_a_2_percent_scale_fault_of_one_axis_is_named_by_the_six_position_fit(six, capsys, turns):
    passport = read_passport_json(six / f"pp-{turns}.json").triads[Triad.ACCEL]
    fault = Fault(FaultKind.STEP, Triad.ACCEL, SCALE_Y, 0.0, 0.02)
    path = _six_session(six, turns, (fault,), seed=9)
    status, text, json_status, doc = _diagnose(capsys, path, six / f"pp-{turns}.json")
    assert status == json_status == 1
    named = [f for f in doc["faults"] if f["predicate"] not in ("F0", "gross")]
    assert [(f["predicate"], f["triad"], f["axis"], f["cause"]) for f in named] == [
        ("F5", "accel", "y", "scale_factor")
    ]
    # The fault is the change from the passport: 0.02 within the noise of both.
    f5 = named[0]
    s = np.hypot(f5["sigma"], passport.sigma[SCALE_Y])
    assert abs(f5["estimate"] - f5["nominal"] - 0.02) < 4.0 * s
    assert f"(σ {f5['sigma']:.2g}, {SOURCE_VECTOR})" in text
    # F0 fails only where y points along gravity; one set of parameters explains every position,
    # so the fault was there from the start: no onset, no split of the six faces.
    assert doc["onset"] is None and "mid-session" not in text


# --- where the fault began -----------------------------------------------------------------------


def test_a_fault_from_the_10th_of_18_positions_is_dated_and_named_in_the_later_positions(
    unit, capsys
):
    """Position 10 holds −z up: a z scale fault from its start fails F0 at once. One fit of all
    18 positions mixes the unit before and after; the positions after the onset name it."""
    d, clean = unit
    t10 = clean.truth.static_intervals_s[9][0]
    fault = Fault(FaultKind.STEP, Triad.ACCEL, SCALE_Z, t10, F0_FAULT)
    res = simulate(multi_position_spec(model=MODEL, faults=(fault,)), seed=36)
    write_csv_session(d / "late.csv", res.session)
    status, text, json_status, doc = _diagnose(capsys, d / "late.csv", d / "pp.json")
    assert status == json_status == 1
    onset = doc["onset"]
    # Dated at the first static sample that fails: within the detector's window (1 s) of the
    # position's start.
    assert t10 <= onset["t_s"] < t10 + 1.0
    assert onset["n_before"] == 9 and onset["n_after"] == 9
    assert onset["faults_before"] == []
    after = [f for f in doc["faults"] if f["predicate"] not in ("F0", "gross")]
    assert [(f["predicate"], f["axis"], f["cause"], f["positions"]) for f in after] == [
        ("F6", "z", "scale_factor", "after onset")
    ]
    assert f"F0's persistent failure began at {onset['t_s']:.3f} s, mid-session" in text
    assert "probably not this unit's" not in text and not doc["passport_of_another_unit"]

    twin = simulate(multi_position_spec(model=MODEL), seed=36)
    write_csv_session(d / "late_twin.csv", twin.session)
    status, text, _, doc = _diagnose(capsys, d / "late_twin.csv", d / "pp.json")
    assert doc["faults"] == [] and doc["onset"] is None and "FAULT" not in text
    assert status == 0  # the MEMS gyro's F0 and F1…F9 cannot apply; the gross test ran


@needs(XSENS)
def test_the_measured_xsens_session_keeps_its_diagnosis(tmp_path, capsys):
    """The real unit against its own passport: the accelerometers diagnosed, nothing fails; F0
    tests the 34,882 samples the service tests (tests/test_pipeline_xsens.py: the static runs less
    25 samples at each end) and none leaves this shell (the six single-sample failures diagnose
    counted as knocks before were those run ends); the gyro has no passport and cannot see the
    Earth rate (its F0 and F1…F9 do not apply); the gross test tests both triads at rest, the
    accelerometer's too although this gyro rests 0.05 rad/s off 0 (inside its class's 20 °/s: a
    healthy gyro must not switch the accelerometer's test off). Everything that applies ran: no
    fault, exit 0."""
    pp = tmp_path / "xs.json"
    assert main(["calibrate", str(XSENS), "--out", str(pp), "--no-audit"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(XSENS), "--passport", str(pp), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc["positions"]) == 38 and doc["triads"]["accel"]["diagnosed"]
    assert doc["faults"] == [] and doc["onset"] is None
    f0 = doc["f0"]["accel"]
    assert (f0["tested"], f0["failed"], f0["knocks"]) == (34882, 0, 0)
    assert doc["triads"]["gyro"]["reason"] == "no passport for this triad"
    checks = {(c["triad"], c["check"]): c for c in doc["coverage"]["checks"]}
    assert not checks["gyro", "F1-F9"]["applies"] and not checks["gyro", "F0"]["applies"]
    assert checks["accel", "gross"]["samples"] == checks["gyro", "gross"]["samples"] == 695
    assert doc["not_tested"] == []


# --- what diagnose must not do (review of the above) ---------------------------------------------


def test_a_channel_clipped_flat_is_an_f0_fault_not_unusable_input(unit, capsys):
    """z clipped at ±5 m/s² from the start: where z is near vertical its output is flat (no
    spread: no position covariance) and |a| ≈ 0.7 g. The fit cannot use those positions, F0 fails
    on them: a fault (exit 1) with the accelerometers not diagnosed and why, not 'unusable input'."""
    d, _ = unit
    fault = Fault(FaultKind.SATURATION, Triad.ACCEL, 2, 0.0, 5.0)
    res = simulate(multi_position_spec(model=MODEL, n_positions=5, faults=(fault,)), seed=37)
    write_csv_session(d / "clipped.csv", res.session)
    status, text, json_status, doc = _diagnose(capsys, d / "clipped.csv", d / "pp.json")
    assert status == json_status == doc["exit_status"] == 1
    assert [(f["predicate"], f["triad"]) for f in doc["faults"] if f["predicate"] != "gross"] == [
        ("F0", "accel")
    ]
    accel = doc["triads"]["accel"]
    assert not accel["diagnosed"] and "axis z has no spread at all" in accel["reason"]
    assert "FAULT F0: accel" in text and "axis z has no spread at all" in text


def test_a_dead_gyro_channel_does_not_stop_the_accelerometers_being_diagnosed(unit, capsys):
    """The passport has no gyro (a MEMS gyro cannot see the Earth rate); the session's gyro x reads
    exactly 0. That triad cannot be fitted, the accelerometers still can: diagnosed, nothing
    found, the gyro not tested and why (exit 3), not 'unusable input' (exit 2)."""
    d, _ = unit
    res = simulate(multi_position_spec(model=MODEL, n_positions=12, static_s=5.0), seed=38)
    gyro = res.session.gyro_rps.copy()
    gyro[:, 0] = 0.0
    write_csv_session(d / "deadgyro.csv", dataclasses.replace(res.session, gyro_rps=gyro))
    status, text, json_status, doc = _diagnose(capsys, d / "deadgyro.csv", d / "pp.json")
    assert status == json_status == doc["exit_status"] == 3
    assert doc["triads"]["accel"]["diagnosed"] and doc["faults"] == []
    assert "not tested: gyro: no passport for this triad" in text


def _accel_only(d, name, seed, noise_factor=1.0):
    """A 12-position accelerometer-only session of the unit, its white noise ``noise_factor`` × the
    passport's."""
    res = simulate(multi_position_spec(model=MODEL, n_positions=12, static_s=5.0), seed=seed)
    accel = res.session.accel_mps2
    if noise_factor != 1.0:
        tp = read_passport_json(d / "pp.json").triads[Triad.ACCEL]
        extra = np.sqrt(noise_factor**2 - 1.0) * tp.noise_std * tp.reference
        accel = accel + extra * np.random.default_rng(seed).standard_normal(accel.shape)
    write_csv_session(
        d / name, dataclasses.replace(res.session, accel_mps2=accel, gyro_rps=None, temp_c=None)
    )
    return d / name


def test_f0_that_tested_no_sample_is_not_tested_not_inside_the_shell(unit, capsys):
    """A unit 6× noisier than its passport: the chain's detector (thresholds from the session's
    own noise) finds its positions and F1…F9 pass, but the service's detector (thresholds from
    the passport's noise) sees no rest, so F0 tested nothing. That is not 'no fault' (exit 0)
    and not '0 static samples inside the shell': F0 was not tested, and why (exit 3)."""
    d, _ = unit
    path = _accel_only(d, "noisy.csv", seed=39, noise_factor=6.0)
    status, text, json_status, doc = _diagnose(capsys, path, d / "pp.json")
    assert doc["triads"]["accel"]["diagnosed"] and doc["f0"]["accel"]["tested"] == 0
    assert status == json_status == doc["exit_status"] == 3
    assert "  no fault" not in text.splitlines() and "inside the shell" not in text
    assert "not tested: F0 accel: no static sample" in text


def test_a_passport_triad_the_session_does_not_carry_is_not_tested(unit, capsys):
    """The passport diagnoses a gyro (a navigation-grade one); the session has no gyro columns.
    The accelerometers pass, the gyro was not tested: exit 3 and said, not 'no fault'."""
    from estimators.nominal_passport import SensorClass, nominal_passport
    from protocols.passport_codec import write_passport_json

    d, _ = unit
    own = read_passport_json(d / "pp.json")
    gyro = nominal_passport(SensorClass.NAVIGATION).triads[Triad.GYRO]
    write_passport_json(
        dataclasses.replace(own, triads={**own.triads, Triad.GYRO: gyro}), d / "pp_gyro.json"
    )
    path = _accel_only(d, "accel_only.csv", seed=40)
    status, text, json_status, doc = _diagnose(capsys, path, d / "pp_gyro.json")
    assert doc["triads"]["accel"]["diagnosed"] and doc["faults"] == []
    assert status == json_status == doc["exit_status"] == 3
    assert "not tested: gyro: the session has no gyro samples" in text


def test_a_second_fault_after_the_onset_is_said_and_not_taken_for_another_units_passport(
    unit, capsys
):
    """z zero signal +0.05 g from the 6th position, x scale +0.04 from the 13th: F0 dates the first
    change and the positions after it are fitted apart, but they hold a second change too, so no
    one set of parameters explains them and most predicates fail. That is the unit changing twice,
    said so, and not a passport of another unit (issue 28, item 6); exit 1."""
    d, clean = unit
    starts = [a for a, _ in clean.truth.static_intervals_s]
    faults = (
        Fault(FaultKind.STEP, Triad.ACCEL, 2, starts[5], 0.05),
        Fault(FaultKind.STEP, Triad.ACCEL, 3, starts[12], 0.04),
    )
    res = simulate(multi_position_spec(model=MODEL, faults=faults), seed=41)
    write_csv_session(d / "twice.csv", res.session)
    status, text, json_status, doc = _diagnose(capsys, d / "twice.csv", d / "pp.json")
    assert status == json_status == doc["exit_status"] == 1
    assert doc["onset"] is not None and doc["onset"]["changed_after"]
    assert not doc["passport_of_another_unit"] and "probably not this unit's" not in text
    assert "not explained by one set of parameters either" in text


def test_the_f0_finding_counts_and_measures_its_persistent_failure_not_the_knocks(unit, capsys):
    """Five positions, a z scale fault of 0.02 (|s| ≈ 0.023 where z is vertical, beyond λ0 ≈ 0.016)
    and one knock of 3.5 % (|s| ≈ 0.035) on a rest sample elsewhere: the FAULT F0 finding's count
    and worst value are the persistent failure's; the knock is counted apart, as knocks are."""
    d, _ = unit
    fault = Fault(FaultKind.STEP, Triad.ACCEL, SCALE_Z, 0.0, 0.02)
    res = simulate(multi_position_spec(model=MODEL, n_positions=5, faults=(fault,)), seed=42)
    k = int(np.searchsorted(res.session.t_s, np.mean(res.truth.static_intervals_s[1])))
    res.session.accel_mps2[k] *= 1.035
    write_csv_session(d / "fault_knock.csv", res.session)
    status, text, _, doc = _diagnose(capsys, d / "fault_knock.csv", d / "pp.json")
    f0 = doc["f0"]["accel"]
    assert status == 1 and f0["persistent"] and f0["knocks"] == 1
    (found,) = [f for f in doc["faults"] if f["predicate"] != "gross"]
    assert found["failed"] == f0["failed"] - 1 and found["worst"] < 0.03 < f0["worst"]
    assert f"on {found['failed']} of {f0['tested']} static samples" in text
    assert f"worst |½(|ã|²−1)| {found['worst']:.3g}, and 1 knock" in text


def test_a_healthy_flights_manoeuvre_is_not_taken_for_a_full_turn_of_a_calibration(
    tmp_path, capsys
):
    """A navigation-grade unit's 60 s flight against its own passport: one position, nothing to
    fit. Between its rests the gyro integrates to within 10 % of 2π about x, which a calibration's
    turn detector accepts; taken as a turn of exactly 2π it 'measured' e_x = -0.025 (tolerance
    0.0045): FAULT F4 on a healthy unit. Full turns diagnose only a session holding the six faces
    (the Ferraris calibration they belong to); the flight is not diagnosed (exit 3), as before."""
    cal, flight, pp = tmp_path / "cal.csv", tmp_path / "flight.csv", tmp_path / "pp.json"
    nav = ["--grade", "navigation"]
    assert (
        main(["simulate", "--out", str(cal), "--static-s", "6", "--transition-s", "2", *nav]) == 0
    )
    assert main(["calibrate", str(cal), "--out", str(pp), "--latitude", "45", "--no-audit"]) == 0
    argv = ["--profile", "flight", "--duration-s", "60", "--seed", "4032", *nav]
    assert main(["simulate", "--out", str(flight), *argv]) == 0
    status, text, json_status, doc = _diagnose(capsys, flight, pp)
    assert len(doc["positions"]) == 1
    assert doc["faults"] == [] and "FAULT" not in text
    assert status == json_status == doc["exit_status"] == 3


def test_f0_tests_the_samples_the_services_f0_tests(unit, capsys):
    """diagnose's F0 is the service's (f0_report): the same detector and the same erosion of every
    static run by the positions' trim (service.pipeline.static_gate), where the slow start and end
    of a motion still sit in a quiet window. A healthy 60 s flight: the service tests 1,902
    samples and none fails; diagnose tested the 100 edge samples too and called one a knock."""
    d, _ = unit
    path = d / "flight.csv"
    argv = ["--profile", "flight", "--duration-s", "60", "--seed", "1000"]
    assert main(["simulate", "--out", str(path), *argv]) == 0
    _, text, _, doc = _diagnose(capsys, path, d / "pp.json")
    passport = read_passport_json(d / "pp.json")
    fleet = FleetProcessor(
        passports=lambda v, i: passport, options=PipelineOptions(gravity_mps2=doc["gravity_mps2"])
    )
    session = read_csv_session(path).session
    assert run_fleet(fleet, batches_of(session, vehicle="v", imu=0, batch_samples=100)) == []
    counters = fleet.pipelines[("v", 0)].counters
    f0 = doc["f0"]["accel"]
    service = (counters["f0.accel.tests"], counters.get("f0.accel.fail", 0))
    assert (f0["tested"], f0["failed"]) == service == (1902, 0)
    assert f0["knocks"] == 0 and "knock" not in text


def test_not_diagnosed_after_a_late_onset_says_after_the_onset(unit, capsys):
    """z scale +0.04 from the 17th of 18 positions: the positions before F0 sees it are diagnosed
    (nothing found), the ones after are too few. The summary line is about the later set and says so,
    instead of a bare NOT DIAGNOSED of a session whose first positions were diagnosed."""
    d, _ = unit
    spec = multi_position_spec(model=MODEL, static_s=6.0, transition_s=2.0)
    t16 = simulate(spec, seed=43).truth.static_intervals_s[16][0]
    fault = Fault(FaultKind.STEP, Triad.ACCEL, SCALE_Z, t16, F0_FAULT)
    res = simulate(dataclasses.replace(spec, faults=(fault,)), seed=43)
    write_csv_session(d / "late16.csv", res.session)
    status, text, _, doc = _diagnose(capsys, d / "late16.csv", d / "pp.json")
    assert status == 1 and doc["onset"]["n_before"] >= 16
    assert not doc["triads"]["accel"]["diagnosed"]
    assert doc["onset"]["before"]["accel"]["diagnosed"] and doc["onset"]["faults_before"] == []
    (line,) = [x for x in text.splitlines() if x.startswith("NOT DIAGNOSED")]
    assert line.startswith("NOT DIAGNOSED after the onset: accel: ")
