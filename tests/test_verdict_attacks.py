"""Verdicts attacked as a hostile user would: inputs on which a verdict once said less than the truth
(a fault found yet "unusable input", a check that applied but did not run, figures that disagree
between the outputs of the same data)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from replay_support import replay_with_coverage
from service_support import batches_of, run_fleet

from estimators.conventions import STANDARD_GRAVITY_MPS2, Grade, Triad
from estimators.nominal_passport import SensorClass, nominal_passport
from estimators.session import ImuSession
from estimators.sim import Fault, FaultKind, multi_position_spec, simulate
from protocols.events import ImuState, Predicate
from protocols.logs import write_tlog
from protocols.passport_codec import write_passport_json
from protocols.session_file import SessionUnits, UnitsError, check_units, write_csv_session
from service.cli import EXIT_FAULT, EXIT_UNUSABLE, main
from service.pipeline import FleetProcessor, PipelineOptions

G = STANDARD_GRAVITY_MPS2


def level_at_rest(n: int, rate_hz: float, seed: int) -> ImuSession:
    """A level unit at rest: g on z, 0.01 m/s² and 0.002 rad/s of white noise per sample."""
    rng = np.random.default_rng(seed)
    accel = np.array([0.0, 0.0, G]) + rng.normal(0.0, 0.01, (n, 3))
    gyro = rng.normal(0.0, 0.002, (n, 3))
    return ImuSession(np.arange(n) / rate_hz + 50.0, accel, gyro)


def test_an_accelerometer_reading_exactly_zero_is_a_fault_not_unusable_input(capsys, tmp_path):
    """A dead accelerometer whose every axis reads 0 (a tlog's integer milli-g quantize its noise
    away): F0 tests its samples, which show no gravity direction. The gross event is raised and the
    verdict is a fault (exit 1); the coverage once divided 0 by 0 and the replay ended "unusable
    input" (exit 2) after printing the event."""
    session = level_at_rest(2000, 100.0, seed=3)
    session.accel_mps2[:] = 0.0
    log = tmp_path / "dead.tlog"
    write_tlog(log, {0: session})
    status, lines, err, coverage = replay_with_coverage(capsys, log, "--json")
    assert status == EXIT_FAULT, err
    assert Predicate.GROSS.value in {json.loads(line)["predicate"] for line in lines}
    (f0,) = (
        c
        for c in coverage["imus"][0]["checks"]
        if c["check"] == "F0" and c["triad"] == Triad.ACCEL.value
    )
    assert f0["ran"] and f0["samples"] > 0


def navigation_fleet_events(session, gravity_mps2: float):
    """Events and pipeline of a unit on the nominal navigation passport (the daemon's default_grade)."""
    fleet = FleetProcessor(
        passports=lambda vehicle, imu: None,
        options=PipelineOptions(gravity_mps2=gravity_mps2),
        nominal=SensorClass.NAVIGATION,
    )
    events = run_fleet(fleet, batches_of(session, vehicle="v", imu=0, batch_samples=100))
    return events, fleet.pipelines[("v", 0)]


def test_a_healthy_navigation_gyro_passes_f0_through_its_turns_and_a_noisy_one_fails():
    """A navigation-grade unit turned between six positions against its class's nominal passport:
    F0 tests its gyro against the Earth rate (λ0 ≈ 0.4, about 1e-4 rad/s) and a turn's first and
    last 0.2 s reach 0.016 rad/s. The static detector's MEMS spread threshold (0.02 rad/s) counted
    them as rest and F0 failed at every turn edge of a healthy unit. A static window's mean rate is
    now bounded at F0's shell, not its spread: the twin whose gyro x gains 1e-4 rad/s of white
    noise (25× its own) from the third position is still at rest, and F0 finds it there."""
    spec = multi_position_spec(grade=Grade.NAVIGATION, n_positions=6, static_s=5.0)
    res = simulate(spec, seed=11)
    events, pipe = navigation_fleet_events(res.session, res.truth.gravity_mps2)
    assert [e.text for e in events if e.predicate is Predicate.F0] == []
    assert pipe.counters["f0.gyro.tests"] > 0.5 * res.session.n_samples
    onset_s = 2 * (5.0 + 4.0) + 1.0
    noisy = Fault(FaultKind.NOISE_BURST, Triad.GYRO, 0, onset_s, 1e-4, 100.0)
    spec = multi_position_spec(grade=Grade.NAVIGATION, n_positions=6, static_s=5.0, faults=[noisy])
    res = simulate(spec, seed=11)
    events, _ = navigation_fleet_events(res.session, res.truth.gravity_mps2)
    (f0,) = [e for e in events if e.predicate is Predicate.F0]
    assert f0.triad is Triad.GYRO and onset_s <= f0.t_s < onset_s + 1.0


@pytest.mark.parametrize("magnitude_g", [0.35, 0.0])
def test_diagnose_and_publish_test_an_accelerometer_no_unit_fits(tmp_path, capsys, magnitude_g):
    """A unit at rest reading 0.35 g (the dead ArduRover accelerometer) or nothing: its median |a|
    lies outside 5…20 m/s² in m/s², g and mg alike, so the unit check refused the session as
    "implausible in every unit" (exit 2) and diagnose never tested it. No unit mistake explains it:
    diagnose tests it as read and names the gross fault (exit 1); calibrate, a fit, still refuses."""
    session = level_at_rest(2000, 100.0, seed=5)
    session.accel_mps2[:, 2] *= magnitude_g
    csv, passport = tmp_path / "s.csv", tmp_path / "p.json"
    write_csv_session(csv, session)
    write_passport_json(nominal_passport(SensorClass.CONSUMER_MEMS), passport)
    status = main(["diagnose", str(csv), "--passport", str(passport), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert status == EXIT_FAULT == out["exit_status"]
    assert ("gross", "accel") in {(f["predicate"], f["triad"]) for f in out["faults"]}
    with pytest.raises(UnitsError, match="every other unit"):
        check_units(session, SessionUnits())
    note = check_units(session, SessionUnits(), faulty_accel_ok=True)
    assert note is not None and "tested as read" in note
    assert (
        check_units(level_at_rest(200, 100.0, seed=5), SessionUnits(), faulty_accel_ok=True) is None
    )
    assert main(["calibrate", str(csv), "--out", str(tmp_path / "c.json")]) == EXIT_UNUSABLE


def ten_positions_status(grade: Grade, passport_of, seed: int):
    """The status of a healthy unit turned through ten positions, on ``passport_of(gravity)``."""
    res = simulate(multi_position_spec(grade=grade, n_positions=10, static_s=5.0), seed=seed)
    passport = passport_of(res.truth.gravity_mps2)
    fleet = FleetProcessor(
        passports=lambda vehicle, imu: passport,
        options=PipelineOptions(gravity_mps2=res.truth.gravity_mps2),
    )
    events = run_fleet(fleet, batches_of(res.session, vehicle="v", imu=0, batch_samples=100))
    status = fleet.pipelines[("v", 0)].status()
    assert events == [] and status.positions >= 9
    return status.state, {c.name: c for c in status.coverage}


def without_gyro(sensor_class: SensorClass):
    def passport_of(gravity_mps2: float):
        full = nominal_passport(sensor_class, gravity_mps2=gravity_mps2)
        return dataclasses.replace(full, triads={Triad.ACCEL: full.triads[Triad.ACCEL]})

    return passport_of


def test_the_daemon_says_ok_only_when_every_check_that_applies_ran():
    """A passport without its gyro triad, as ``calibrate`` writes for a gyro that cannot see the
    Earth rate. On a navigation unit the gyro's F0 and F1…F9 apply and did not run: replay said "no
    finding within coverage" and the daemon's status "ok"; it is now "warning". On a MEMS unit the
    gyro's own noise (about 12 Ω per sample) shows that they cannot apply: "ok" in the status and
    "no fault" in replay, as with a passport that has its MEMS gyro (replay said "not tested")."""
    state, checks = ten_positions_status(
        Grade.NAVIGATION, without_gyro(SensorClass.NAVIGATION), seed=13
    )
    assert state is ImuState.WARNING
    assert {name for name, c in checks.items() if c.missing} == {"gyro F0", "gyro F1-F9"}
    state, checks = ten_positions_status(Grade.MEMS, without_gyro(SensorClass.CONSUMER_MEMS), 13)
    assert state is ImuState.OK and not any(c.missing for c in checks.values())
    assert not checks["gyro F0"].applies and "own noise" in checks["gyro F0"].reason
    full = lambda g: nominal_passport(SensorClass.CONSUMER_MEMS, gravity_mps2=g)  # noqa: E731
    assert ten_positions_status(Grade.MEMS, full, seed=13)[0] is ImuState.OK
