"""Passport inputs found wrong in the field: files that are not text, numbers written as strings,
impossible sample rates, a reference in other units, and a calibration with no redundancy."""

from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest
from ninepar_support import PASSPORT_G_MPS2, synthetic_passport

from estimators.conventions import (
    EARTH_RATE_RPS,
    RPS_PER_DPH,
    Grade,
    Triad,
    normal_gravity_mps2,
)
from estimators.passport import (
    Passport,
    PassportError,
    TemperatureModel,
    check_references,
)
from estimators.sim import grade_error_model, multi_position_spec, simulate
from protocols.passport_codec import read_passport_json, write_passport_json
from protocols.session_file import write_csv_session
from service.cli import main


@pytest.fixture(scope="module")
def passport() -> Passport:
    return synthetic_passport(11)


def _with(passport: Passport, path: tuple[str, ...], value) -> dict:
    d = copy.deepcopy(passport.to_dict())
    target = d
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return d


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """One MEMS unit: 9 positions at 45°, 12 at 60° (calibrated into pp.json), 12 at the equator."""
    d = tmp_path_factory.mktemp("field")
    model = grade_error_model(Grade.MEMS, rng=np.random.default_rng(3))
    for name, n, lat in (("nine", 9, 45.0), ("north", 12, 60.0), ("equator", 12, 0.0)):
        spec = multi_position_spec(
            model=model, n_positions=n, static_s=10.0, transition_s=2.0, latitude_deg=lat
        )
        write_csv_session(d / f"{name}.csv", simulate(spec, seed=5).session)
    argv = ["calibrate", str(d / "north.csv"), "--out", str(d / "pp.json"), "--no-audit"]
    assert main([*argv, "--latitude", "60"]) == 0
    return d


# --------------------------------------------------------------------------- the file itself


def test_a_passport_file_that_is_not_utf8_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "garbage.json"
    path.write_bytes(b"\xae\x91{" + bytes(range(128, 256)))
    with pytest.raises(
        PassportError, match=r"garbage\.json: not UTF-8 text \(byte 0xae at offset 0\)"
    ):
        read_passport_json(path)


def test_a_passport_saved_with_a_byte_order_mark_is_read(tmp_path):
    """A passport opened and saved in a Windows editor starts with a UTF-8 byte-order mark: json refused
    it ("Unexpected UTF-8 BOM") at line 1, column 1. The mark is not text, and the passport reads."""
    passport = synthetic_passport(3)
    plain, marked = tmp_path / "plain.json", tmp_path / "marked.json"
    write_passport_json(passport, plain)
    marked.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    assert read_passport_json(marked).to_dict() == read_passport_json(plain).to_dict()


# --------------------------------------------------------------------------- numbers are numbers


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        (("triads", "accel", "nominal"), ["0.001"] * 9, r"triads\.accel\.nominal must be numbers, got str '0\.001'"),
        (("triads", "accel", "tolerance"), [0.01] * 8 + ["0.01"], r"triads\.accel\.tolerance must be numbers, got str"),
        (("triads", "gyro", "sigma"), [None] * 9, r"triads\.gyro\.sigma must be numbers, got NoneType None"),
        (("triads", "accel", "noise_std"), ["1e-3", 1e-3, 1e-3], r"triads\.accel\.noise_std must be numbers, got str"),
        (("triads", "accel", "quantization_step"), ["2e-4"] * 3, r"quantization_step must be numbers, got str"),
        (("triads", "accel", "bias_instability_std"), [0.0, 0.0, {}], r"bias_instability_std must be numbers, got dict"),
        (("triads", "accel", "provenance", "ci_low"), ["-1"] * 9, r"provenance\.ci_low must be numbers, got str"),
        (("triads", "accel", "temperature", "bias_coeffs"), [["0", "0"]] * 3, r"temperature\.bias_coeffs must be numbers, got str"),
        (("triads", "accel", "temperature", "scale_coeffs"), [[0, "0"]] * 3, r"temperature\.scale_coeffs must be numbers, got str"),
    ],
)  # fmt: skip
def test_an_array_field_with_a_number_written_as_a_string_or_a_non_number_is_refused(
    passport, path, value, match
):
    with pytest.raises(PassportError, match=match):
        Passport.from_dict(_with(passport, path, value))


def test_ragged_temperature_coefficients_are_refused_naming_the_field(passport):
    ragged = [[0.0, 0.0], [0.0], [0.0, 0.0]]
    with pytest.raises(
        PassportError, match=r"temperature\.bias_coeffs must be numbers of shape \(3, order\+1\)"
    ):
        Passport.from_dict(
            _with(passport, ("triads", "accel", "temperature", "bias_coeffs"), ragged)
        )


def _temperature(**fields) -> TemperatureModel:
    args = {"reference_temp_c": 25.0, "valid_min_c": -20.0, "valid_max_c": 60.0} | fields
    return TemperatureModel(bias_coeffs=np.zeros((3, 1)), scale_coeffs=np.zeros((3, 1)), **args)


@pytest.mark.parametrize(
    ("path", "value", "construct", "match"),
    [
        (("triads", "accel", "reference"), "9.8", lambda tp: dataclasses.replace(tp, reference="9.8"), r"triads\.accel\.reference must be a number, got '9\.8'"),
        (("triads", "accel", "sample_rate_hz"), "9.8", lambda tp: dataclasses.replace(tp, sample_rate_hz="9.8"), r"triads\.accel\.sample_rate_hz must be a number, got '9\.8'"),
        (("triads", "accel", "temperature", "reference_temp_c"), "9.8", lambda tp: _temperature(reference_temp_c="9.8"), r"temperature\.reference_temp_c must be a number, got '9\.8'"),
        (("triads", "accel", "temperature", "valid_min_c"), "9.8", lambda tp: _temperature(valid_min_c="9.8"), r"temperature\.valid_min_c must be a number, got '9\.8'"),
        (("triads", "accel", "nominal"), ["9.8"] * 9, lambda tp: dataclasses.replace(tp, nominal=np.array(["9.8"] * 9)), r"triads\.accel\.nominal must be numbers, got str '9\.8'"),
    ],
)  # fmt: skip
def test_a_number_field_refuses_a_string_when_decoded_and_when_constructed_alike(
    passport, path, value, construct, match
):
    with pytest.raises(PassportError, match=match):
        Passport.from_dict(_with(passport, path, value))
    with pytest.raises(PassportError, match=match):
        construct(passport.triads[Triad.ACCEL])


# --------------------------------------------------------------------------- sample rate


@pytest.mark.parametrize("rate_hz", [0.0, -100.0, 0.1, 20_000.0, 1e9])
def test_a_sample_rate_no_session_is_read_at_is_refused(passport, rate_hz):
    d = _with(passport, ("triads", "gyro", "sample_rate_hz"), rate_hz)
    with pytest.raises(
        PassportError,
        match=r"triads\.gyro\.sample_rate_hz must be a sample rate sessions are read at, 0\.5…10000 Hz, got ",
    ):
        Passport.from_dict(d)


@pytest.mark.parametrize("rate_hz", [0.5, 2.0, 10_000.0])
def test_the_sample_rates_sessions_are_read_at_are_accepted(passport, rate_hz):
    d = _with(passport, ("triads", "gyro", "sample_rate_hz"), rate_hz)
    assert Passport.from_dict(d).triads[Triad.GYRO].sample_rate_hz == rate_hz


# --------------------------------------------------------------------------- reference vs session


def _with_reference(passport: Passport, triad: Triad, reference: float) -> Passport:
    tp = dataclasses.replace(passport.triads[triad], reference=reference)
    return dataclasses.replace(passport, triads={**passport.triads, triad: tp})


def test_an_accelerometer_reference_in_g_units_does_not_fit_the_sessions_gravity(passport):
    with pytest.raises(
        PassportError,
        match=r"the passport's accelerometer reference is 1\.0 m/s² but the session's gravity is 9\.8062 m/s²: "
        r"a passport in g units, or of another quantity\?",
    ):
        check_references(_with_reference(passport, Triad.ACCEL, 1.0), gravity_mps2=9.8062)


def test_a_gyro_reference_in_degrees_per_hour_does_not_fit_earths_rate(passport):
    deg_per_h = EARTH_RATE_RPS / RPS_PER_DPH
    with pytest.raises(
        PassportError, match=r"gyro reference is 15\.04.* rad/s but Earth's rotation rate is 7\.29"
    ):
        check_references(
            _with_reference(passport, Triad.GYRO, deg_per_h), gravity_mps2=PASSPORT_G_MPS2
        )


def test_a_passport_from_any_site_on_earth_fits_a_session_from_any_other(passport):
    equator, pole = normal_gravity_mps2(0.0), normal_gravity_mps2(90.0)
    check_references(_with_reference(passport, Triad.ACCEL, equator), gravity_mps2=pole)
    check_references(_with_reference(passport, Triad.ACCEL, pole), gravity_mps2=equator)


def test_diagnose_refuses_a_passport_in_g_units_instead_of_reporting_bias_faults(
    sessions, tmp_path, capsys
):
    calibrated = read_passport_json(sessions / "pp.json")
    write_passport_json(_with_reference(calibrated, Triad.ACCEL, 1.0), tmp_path / "in_g.json")
    capsys.readouterr()
    argv = ["diagnose", str(sessions / "north.csv"), "--passport", str(tmp_path / "in_g.json")]
    assert main([*argv, "--latitude", "60"]) == 2
    out, err = capsys.readouterr()
    assert "FAULT" not in out
    assert len(err.strip().splitlines()) == 1
    assert (
        "in_g.json: the passport's accelerometer reference is 1.0 m/s² but the session's gravity is 9.81918"
        in err
    )


def test_diagnose_with_a_passport_made_at_another_site_finds_no_fault(sessions, capsys):
    capsys.readouterr()
    argv = ["diagnose", str(sessions / "equator.csv"), "--passport", str(sessions / "pp.json")]
    # Exit 0: the MEMS gyro has no passport, but cannot see the Earth rate: its F0 and F1…F9 do
    # not apply, and the gross test ran.
    assert main([*argv, "--latitude", "0", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["faults"] == [] and doc["triads"]["accel"]["diagnosed"]


# --------------------------------------------------------------------------- no redundancy


def test_calibrate_from_exactly_nine_positions_warns_that_the_fit_cannot_be_checked(
    sessions, tmp_path, capsys
):
    capsys.readouterr()
    argv = [
        "calibrate",
        str(sessions / "nine.csv"),
        "--out",
        str(tmp_path / "pp9.json"),
        "--no-audit",
    ]
    assert main([*argv, "--latitude", "45"]) == 0
    err = capsys.readouterr().err
    assert "nan" not in err
    assert "accel: M1 fit observable, residual rms" in err and "no chi2/dof (no redundancy)" in err
    assert (
        "calibrate: warning: the accel fit has 9 positions for its 9 parameters, no redundancy: "
        "the residual check (chi2/dof) is impossible" in err
    )
    assert "record more positions (at least 12)" in err
    assert read_passport_json(tmp_path / "pp9.json").triads[Triad.ACCEL].provenance.n_positions == 9


def test_a_passport_path_that_never_ends_is_read_only_up_to_the_limit():
    # /dev/zero has no size to check first: reading it whole took 3 GB in 4 s and never ended.
    with pytest.raises(PassportError, match=r"/dev/zero: more than the passport limit"):
        read_passport_json("/dev/zero")
