"""Units at the edge (refused with the unit named) and "not diagnosed" is not "no fault" (exit 3)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from estimators.conventions import STANDARD_GRAVITY_MPS2
from estimators.sim import Grade, grade_error_model, multi_position_spec, simulate
from protocols.session_file import (
    SessionFileError,
    SessionUnits,
    UnitsError,
    check_units,
    read_csv_session,
    write_csv_session,
)
from service.cli import main


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("units")
    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(5))
    session = simulate(multi_position_spec(model=model, static_s=8.0), seed=50).session
    write_csv_session(d / "si.csv", session)
    assert main(["calibrate", str(d / "si.csv"), "--out", str(d / "pp.json"), "--no-audit"]) == 0
    short = simulate(multi_position_spec(model=model, n_positions=3, static_s=8.0), seed=51)
    write_csv_session(d / "three.csv", short.session)
    foreign = grade_error_model(Grade.MEMS, rng=np.random.default_rng(6))
    other = simulate(multi_position_spec(model=foreign, static_s=8.0), seed=52).session
    write_csv_session(d / "other.csv", other)
    return d, session


def _variants(session):
    """(name, session in other units, metadata comment or None, CLI option, what the refusal names)."""
    return [
        ("accel_g", replace(session, accel_mps2=session.accel_mps2 / STANDARD_GRAVITY_MPS2),
         {"accel_unit": "g"}, ["--accel-unit", "g"], "look like g, not m/s2"),
        ("accel_mg", replace(session, accel_mps2=session.accel_mps2 / STANDARD_GRAVITY_MPS2 * 1e3),
         {"accel_unit": "mg"}, ["--accel-unit", "mg"], "look like mg, not m/s2"),
        ("gyro_dps", replace(session, gyro_rps=np.degrees(session.gyro_rps)),
         {"gyro_unit": "deg/s"}, ["--gyro-unit", "deg/s"], "look like deg/s, not rad/s"),
        ("time_ms", replace(session, t_s=session.t_s * 1e3),
         {"time_unit": "ms"}, ["--time-unit", "ms"], "look like ms, not s"),
        ("time_us", replace(session, t_s=session.t_s * 1e6),
         {"time_unit": "us"}, ["--time-unit", "us"], "look like us, not s"),
    ]  # fmt: skip


@pytest.mark.parametrize("case", range(5))
@pytest.mark.parametrize("command", ["calibrate", "diagnose", "audit"])
def test_a_session_in_other_units_is_refused_with_the_unit_named(
    files, tmp_path, capsys, case, command
):
    d, session = files
    name, other, _, _, named = _variants(session)[case]
    path = tmp_path / f"{name}.csv"
    write_csv_session(path, other)
    extra = {
        "calibrate": ["--out", str(tmp_path / "x.json")],
        "diagnose": ["--passport", str(d / "pp.json")],
        "audit": [],
    }
    capsys.readouterr()
    assert main([command, str(path), *extra[command]]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and named in err, err


@pytest.mark.parametrize("case", range(5))
def test_declared_units_option_or_comment_read_the_same_samples(files, tmp_path, case):
    _, session = files
    name, other, meta, _, _ = _variants(session)[case]
    commented = tmp_path / f"{name}_comment.csv"
    write_csv_session(commented, other, metadata=meta)
    plain = tmp_path / f"{name}.csv"
    write_csv_session(plain, other)
    by_comment = read_csv_session(commented)
    key, unit = next(iter(meta.items()))
    by_option = read_csv_session(plain, units=SessionUnits(**{key.removesuffix("_unit"): unit}))
    for loaded in (by_comment, by_option):
        check_units(loaded.session, loaded.units)
        np.testing.assert_allclose(loaded.session.t_s, session.t_s, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(loaded.session.accel_mps2, session.accel_mps2, rtol=1e-12)
        np.testing.assert_allclose(loaded.session.gyro_rps, session.gyro_rps, rtol=1e-12)


def test_declared_units_on_the_command_line_are_used(files, tmp_path):
    _, session = files
    path = tmp_path / "g.csv"
    write_csv_session(path, replace(session, accel_mps2=session.accel_mps2 / STANDARD_GRAVITY_MPS2))
    out = tmp_path / "g.json"
    assert main(["calibrate", str(path), "--out", str(out), "--no-audit", "--accel-unit", "g"]) == 0


def test_si_declared_for_si_data_is_accepted_and_a_wrong_declaration_refused(files):
    _, session = files
    check_units(session, SessionUnits())
    read_as_g = SessionUnits(accel="g").to_si(session)  # an SI file declared to be in g
    with pytest.raises(UnitsError, match="accelerometer values look like m/s2, not g"):
        check_units(read_as_g, SessionUnits(accel="g"))
    with pytest.raises(SessionFileError, match="unknown gyro unit 'rpm'"):
        SessionUnits(gyro="rpm")


def test_a_fault_free_session_whose_mems_gyro_cannot_be_fitted_is_no_fault_with_what_was_tested(
    files, capsys
):
    """The accelerometers are diagnosed and pass; the MEMS gyro (no passport) cannot see the Earth
    rate, as the session's own position means show: its F0 and F1…F9 do not apply (no session of it
    could run them), the gross test ran on it. 'No fault', exit 0, with the coverage saying so; a
    gyro that could be fitted and was not would be 'not tested' (exit 3: test_diagnose_findings)."""
    d, _ = files
    capsys.readouterr()
    assert main(["diagnose", str(d / "si.csv"), "--passport", str(d / "pp.json")]) == 0
    out = capsys.readouterr().out
    assert "  no fault" in out.splitlines() and "FAULT" not in out
    assert (
        "coverage: IMU0 gyro F1-F9: does not apply (gyro cannot see the Earth rate: this session's "
        "position means are too noisy against it)" in out
    )
    assert "coverage: IMU0 gyro gross: ran on" in out
    assert not any(line.startswith("NOT DIAGNOSED") for line in out.splitlines())


def test_too_few_positions_is_not_diagnosed_exit_3_with_the_reason(files, capsys):
    d, _ = files
    capsys.readouterr()
    assert main(["diagnose", str(d / "three.csv"), "--passport", str(d / "pp.json")]) == 3
    out = capsys.readouterr().out
    assert "no fault" not in out
    assert "NOT DIAGNOSED: accel: 3 positions; the nine parameters need at least 9" in out
    assert main(["diagnose", str(d / "three.csv"), "--passport", str(d / "pp.json"), "--json"]) == 3
    doc = json.loads(capsys.readouterr().out)
    assert doc["diagnosed"] is False and "3 positions" in doc["reason"]
    assert doc["triads"]["accel"]["diagnosed"] is False
    assert doc["triads"]["gyro"]["reason"] == "no passport for this triad"


def test_diagnose_runs_f0_against_the_passport(files, capsys):
    d, _ = files
    capsys.readouterr()
    assert main(["diagnose", str(d / "si.csv"), "--passport", str(d / "pp.json"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["diagnosed"] is True and doc["reason"] == ""
    f0 = doc["f0"]["accel"]
    assert f0["run"] and f0["tested"] > 10_000 and f0["failed"] == 0
    # Another unit's samples leave this unit's shell.
    assert main(["diagnose", str(d / "other.csv"), "--passport", str(d / "pp.json"), "--json"]) == 1
    other = json.loads(capsys.readouterr().out)["f0"]["accel"]
    assert (
        other["failed"] > 0
        and other["first_fail_t_s"] is not None
        and other["worst"] > other["lambda0"]
    )


def test_a_passport_of_another_unit_is_named(files, capsys):
    d, _ = files
    capsys.readouterr()
    assert main(["diagnose", str(d / "other.csv"), "--passport", str(d / "pp.json")]) == 1
    out = capsys.readouterr().out
    assert "the passport is probably not this unit's" in out
    assert main(["diagnose", str(d / "si.csv"), "--passport", str(d / "pp.json")]) == 0
    assert "probably not this unit's" not in capsys.readouterr().out


TIME_SCALE = {"s": 1.0, "ms": 1e3, "us": 1e6}


@pytest.mark.parametrize("rate_hz", [50.0, 100.0])
@pytest.mark.parametrize(
    ("written", "declared"),
    [(w, d) for w in TIME_SCALE for d in TIME_SCALE if w != d],
)
def test_time_in_one_unit_declared_another_is_refused_with_the_unit_it_is_in(
    files, tmp_path, capsys, written, declared, rate_hz
):
    # 50 Hz in s declared ms reads as 50 kHz: above the 10 kHz the service accepts (and so on).
    d, session = files
    assert np.isclose(session.rate_hz, 100.0)
    path = tmp_path / f"t_{written}.csv"
    t_s = session.t_s * (100.0 / rate_hz)
    write_csv_session(path, replace(session, t_s=t_s * TIME_SCALE[written]))
    capsys.readouterr()
    status = main(
        ["diagnose", str(path), "--passport", str(d / "pp.json"), "--time-unit", declared]
    )
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert "\n" not in err and f"time values look like {written}, not {declared}" in err, err
    assert f"--time-unit {written}" in err


def test_rates_the_service_accepts_are_accepted_in_their_unit(files):
    # The range is 0.5 Hz … 10 kHz (estimators.stream_validity.ValidityLimits): 1 % inside each end
    # is accepted, 1 % outside refused.
    _, session = files
    steps = np.arange(session.n_samples, dtype=float)
    for inside_hz, outside_hz in ((0.505, 0.495), (9_900.0, 10_100.0)):
        check_units(replace(session, t_s=steps / inside_hz), SessionUnits())
        with pytest.raises(UnitsError, match="time values"):
            check_units(replace(session, t_s=steps / outside_hz), SessionUnits())


def test_an_interval_plausible_in_two_units_is_named_by_the_nearer_typical_rate(files):
    # A 1.25 kHz log in ms declared us: 0.8 ms steps read as 0.8 µs. In s the same numbers would
    # be 1.25 Hz, also inside the range; ms puts the rate nearer the range's middle (≈ 70 Hz, log scale).
    _, session = files
    steps = np.arange(session.n_samples, dtype=float)  # 1 per sample, as written
    with pytest.raises(UnitsError, match="time values look like ms, not us"):
        check_units(replace(session, t_s=steps * 0.8e-6), SessionUnits(time="us"))
    # 0.1 per sample declared us: 10 Hz in s or 10 kHz in ms; s is nearer.
    with pytest.raises(UnitsError, match="time values look like s, not us"):
        check_units(replace(session, t_s=steps * 0.1e-6), SessionUnits(time="us"))
