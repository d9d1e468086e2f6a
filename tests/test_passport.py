"""Passports (methods.md M1, M2): the default tolerance rule, round trips, strict rejection of bad input."""

from __future__ import annotations

import copy
import dataclasses
import json
import os

import msgpack
import numpy as np
import pytest
from ninepar_support import PASSPORT_G_MPS2, synthetic_passport
from scipy.stats import norm

from estimators.conventions import EARTH_RATE_RPS, STANDARD_GRAVITY_MPS2, Triad
from estimators.ninepar import Estimate, Method, Verdict
from estimators.passport import (
    GRADE_FLOORS,
    PASSPORT_SCHEMA_VERSION,
    Grade,
    Passport,
    PassportError,
    PassportVersionError,
    TemperatureModel,
    TriadPassport,
    default_tolerance_rule,
    passport_from_estimates,
    per_sample_noise_std,
)
from estimators.positions import Position
from protocols.passport_codec import (
    PassportCodecError,
    decode_passport,
    encode_passport,
    read_passport_json,
    write_passport_json,
)

G_MPS2 = PASSPORT_G_MPS2


@pytest.fixture(scope="module")
def passport() -> Passport:
    return synthetic_passport(7)


def test_default_tolerance_is_three_sigma_or_the_grade_floor():
    rule = default_tolerance_rule(Triad.ACCEL, Grade.MEMS, STANDARD_GRAVITY_MPS2)
    sigma = np.array([1e-5, 1e-3, 2e-3, 1e-5, 1e-3, 2e-3, 1e-5, 1e-3, 2e-3])
    # MEMS accelerometer floors: 2 mg, 2e-3, 1e-3 rad (GRADE_FLOORS); 3σ wins where larger.
    np.testing.assert_allclose(
        rule.tolerance(sigma), [2e-3, 3e-3, 6e-3, 2e-3, 3e-3, 6e-3, 1e-3, 3e-3, 6e-3]
    )
    gyro = default_tolerance_rule(Triad.GYRO, Grade.NAVIGATION, EARTH_RATE_RPS)
    np.testing.assert_allclose(gyro.floor[0], np.radians(0.01) / 3600.0 / EARTH_RATE_RPS)
    assert set(GRADE_FLOORS) == {(t, g) for t in Triad for g in Grade}


def test_passport_from_estimates_carries_values_sigmas_and_intervals(passport):
    tp = passport.triads[Triad.ACCEL]
    assert tp.reference == G_MPS2 and tp.reference_kind.value == "gravity_mps2"
    np.testing.assert_allclose(
        tp.tolerance,
        np.maximum(3.0 * tp.sigma, default_tolerance_rule(Triad.ACCEL, Grade.MEMS, G_MPS2).floor),
    )
    z = norm.ppf(0.975)
    np.testing.assert_allclose(tp.provenance.ci_high - tp.nominal, z * tp.sigma)
    np.testing.assert_allclose(tp.nominal - tp.provenance.ci_low, z * tp.sigma)
    assert tp.provenance.method is Method.REFINED and tp.provenance.n_positions == 18
    assert passport.triads[Triad.GYRO].reference_kind.value == "earth_rate_rps"
    assert passport.triads[Triad.GYRO].quantization_step is None


def test_not_observable_estimates_make_no_passport():
    est = Estimate(
        Triad.ACCEL,
        Method.REFINED,
        Verdict.NOT_OBSERVABLE_YET,
        "3 positions",
        3,
        None,
        None,
        np.zeros(9, bool),
        0,
        np.inf,
        None,
        0,
        9.81,
    )
    with pytest.raises(PassportError, match="cannot build the accel passport: 3 positions"):
        passport_from_estimates(
            {Triad.ACCEL: est}, unit_id="u", sensor_model="m", sensor_ids={}, created="2024-05-01",
            noise_std={Triad.ACCEL: np.ones(3)}, sample_rate_hz=100.0, grade=Grade.MEMS,
        )  # fmt: skip


def test_per_sample_noise_is_recovered_from_the_covariance_of_the_means():
    per_sample = np.array([0.01, 0.02, 0.03])
    positions = [
        Position(0.0, 10.0, n, np.zeros(3), np.diag(per_sample**2 / n), None, None)
        for n in (500, 1000, 2000)
    ]
    np.testing.assert_allclose(per_sample_noise_std(positions, Triad.ACCEL, 2.0), per_sample / 2.0)
    # Correlated noise (τ = n / n_eff = 4) widens the covariance of the mean, not the per-sample noise.
    correlated = [
        dataclasses.replace(p, accel_cov_mps2=4.0 * p.accel_cov_mps2, accel_n_eff=p.n_samples / 4.0)
        for p in positions
    ]
    np.testing.assert_allclose(per_sample_noise_std(correlated, Triad.ACCEL, 2.0), per_sample / 2.0)
    with pytest.raises(PassportError, match="position 0 has no gyro covariance"):
        per_sample_noise_std(positions, Triad.GYRO, EARTH_RATE_RPS)


def test_dict_round_trip_is_exact(passport):
    d = passport.to_dict()
    assert d["type"] == "ins.health.passport" and d["schema_version"] == PASSPORT_SCHEMA_VERSION
    back = Passport.from_dict(copy.deepcopy(d))
    assert back.to_dict() == d
    assert back.triads[Triad.ACCEL].temperature.order == 2


def test_the_temperature_range_round_trips(passport):
    d = passport.to_dict()
    assert {k: d["triads"]["accel"]["temperature"][k] for k in ("valid_min_c", "valid_max_c")} == {
        "valid_min_c": -20.0,
        "valid_max_c": 60.0,
    }
    model = decode_passport(encode_passport(passport)).triads[Triad.ACCEL].temperature
    assert (model.valid_min_c, model.valid_max_c, model.bounded) == (-20.0, 60.0, True)


def _schema_1(passport: Passport) -> dict:
    """The passport as a schema-1 file holds it: the same map without the temperature range."""
    d = copy.deepcopy(passport.to_dict())
    d["schema_version"] = 1
    for key in ("valid_min_c", "valid_max_c"):
        del d["triads"]["accel"]["temperature"][key]
    return d


def test_a_schema_1_passport_reads_with_an_unbounded_temperature_model_and_writes_back_unchanged(
    passport, tmp_path
):
    old = _schema_1(passport)
    back = Passport.from_dict(copy.deepcopy(old))
    model = back.triads[Triad.ACCEL].temperature
    assert (
        back.schema_version == 1
        and not model.bounded
        and model.valid_min_c is None
        and model.valid_max_c is None
    )
    assert model.in_range([-1e3, 1e3]).all()
    assert back.to_dict() == old
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    assert read_passport_json(path).to_dict() == old
    # A schema-1 file has no range keys, and a schema-2 file must have them.
    with pytest.raises(
        PassportError, match=r"temperature has unknown field\(s\) \['valid_max_c', 'valid_min_c'\]"
    ):
        Passport.from_dict({**passport.to_dict(), "schema_version": 1})
    with pytest.raises(
        PassportError, match=r"temperature lacks field\(s\) \['valid_min_c', 'valid_max_c'\]"
    ):
        Passport.from_dict({**old, "schema_version": 2})
    # Built in memory, the same rule: the schema decides whether a temperature model carries a range.
    with pytest.raises(
        PassportError,
        match=f"a schema-{PASSPORT_SCHEMA_VERSION} passport needs a temperature model with its valid range",
    ):
        Passport(back.unit_id, back.sensor_model, back.sensor_ids, back.created, back.triads)
    with pytest.raises(
        PassportError, match="a schema-1 passport needs a temperature model without a valid range"
    ):
        dataclasses.replace(passport, schema_version=1)


@pytest.mark.parametrize(
    ("bounds", "match"),
    [
        (
            {"valid_min_c": 30.0, "valid_max_c": 30.0},
            r"valid_min_c must be below valid_max_c, got 30\.0 ≥ 30\.0",
        ),
        (
            {"valid_min_c": 40.0, "valid_max_c": -10.0},
            r"valid_min_c must be below valid_max_c, got 40\.0 ≥ -10\.0",
        ),
        (
            {"valid_min_c": 30.0, "valid_max_c": 60.0},
            r"reference_temp_c 25\.0 °C is outside the valid range 30\.0…60\.0 °C",
        ),
        (
            {"valid_min_c": float("-inf"), "valid_max_c": 60.0},
            r"valid_min_c must be finite, got -inf",
        ),
        (
            {"valid_min_c": -10.0, "valid_max_c": float("nan")},
            r"valid_max_c must be finite, got nan",
        ),
        (
            {"valid_min_c": -10.0, "valid_max_c": None},
            r"valid_min_c and valid_max_c go together, got -10\.0 and None",
        ),
    ],
)
def test_an_invalid_temperature_range_is_rejected(bounds, match):
    with pytest.raises(PassportError, match=match):
        TemperatureModel(25.0, np.zeros((3, 2)), np.zeros((3, 2)), **bounds)


def test_json_file_round_trip_is_exact_and_atomic(passport, tmp_path):
    path = tmp_path / "unit.json"
    write_passport_json(passport, path)
    write_passport_json(passport, path)  # overwrite in place
    assert os.listdir(tmp_path) == ["unit.json"]
    assert read_passport_json(path).to_dict() == passport.to_dict()
    json.loads(path.read_text())  # plain strict JSON


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(passport, tmp_path, monkeypatch):
    path = tmp_path / "unit.json"
    write_passport_json(passport, path)
    before = path.read_bytes()

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        write_passport_json(passport, path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["unit.json"]


def test_msgpack_round_trip_is_exact(passport):
    data = encode_passport(passport)
    assert decode_passport(data).to_dict() == passport.to_dict()
    with pytest.raises(PassportCodecError, match="not_a_map"):
        decode_passport(msgpack.packb([1, 2]))
    with pytest.raises(PassportCodecError, match="too_large"):
        decode_passport(data, max_bytes=100)


def _mutated(passport: Passport, path: tuple, value) -> dict:
    d = copy.deepcopy(passport.to_dict())
    target = d
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return d


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        (
            ("triads", "accel", "nominal"),
            [0.0] * 8,
            r"triads\.accel\.nominal must have shape \(9,\), got shape \(8,\): \[0\.0",
        ),
        (
            ("triads", "accel", "tolerance"),
            [0.1] * 8 + [float("nan")],
            r"triads\.accel\.tolerance must be finite, got \[0\.1.*nan",
        ),
        (
            ("triads", "gyro", "sigma"),
            "large",
            r"triads\.gyro\.sigma must be numbers of shape \(9,\), got 'large'",
        ),
        (("triads", "accel", "tolerance"), [0.0] * 9, r"tolerance must be positive, got \[0\.0"),
        (
            ("triads", "accel", "observable"),
            [1] * 9,
            r"observable must be a list of booleans, got \[1, 1",
        ),
        (
            ("triads", "accel", "reference_kind"),
            "earth_rate_rps",
            "must be 'gravity_mps2' for the accel triad",
        ),
        (("triads", "accel", "reference"), -9.8, r"reference must be positive, got -9\.8"),
        (("triads", "accel", "noise_std"), [True, 1.0, 1.0], "must be numbers, got booleans"),
        (
            ("triads", "accel", "temperature", "bias_coeffs"),
            [[1.0, 2.0]] * 2,
            r"bias_coeffs must have shape \(3, order\+1\), got \(2, 2\)",
        ),
        (
            ("triads", "accel", "temperature", "valid_max_c"),
            None,
            r"temperature\.valid_max_c must be a number, got None",
        ),
        (
            ("triads", "accel", "temperature", "valid_min_c"),
            26.0,
            r"reference_temp_c 25\.0 °C is outside the valid range 26\.0…60\.0 °C",
        ),
        (
            ("triads", "accel", "provenance", "confidence"),
            1.5,
            r"confidence must be in \(0, 1\), got 1\.5",
        ),
        (
            ("triads", "accel", "bias_instability_std"),
            [0.0, -1e-5, 0.0],
            r"bias_instability_std must not be negative",
        ),
        (("triads", "accel", "provenance", "n_runs"), 0, r"n_runs must be a positive int, got 0"),
        (
            ("triads", "accel", "provenance", "reproducible"),
            [1] * 9,
            r"reproducible must be a list of booleans or null",
        ),
        (
            ("triads", "accel", "provenance", "reproducible"),
            [True] * 8,
            r"reproducible must be 9 booleans or null",
        ),
        (
            ("triads", "accel", "provenance", "procedure"),
            "",
            r"procedure must be a non-empty string",
        ),
        # Read before, then the pipeline and diagnose failed in their linear algebra.
        (
            ("triads", "accel", "nominal"),
            [3.0] * 9,
            r"triads\.accel\.nominal .* is no working triad",
        ),
        (
            ("triads", "accel", "nominal"),
            [0, 0, 0, -0.95, 0, 0, 0, 0, 0],
            r"is no working triad: a gain 1 \+ e outside \(0\.1, 10\)",
        ),
        (("triads", "accel", "param_names"), ["b"] * 9, "param_names must be"),
        (("triads", "accel", "extra"), 1, r"triads\.accel has unknown field\(s\) \['extra'\]"),
        (("triads", "accel", "sigma"), KeyError, r"triads\.accel lacks field\(s\) \['sigma'\]"),
        (("triads", "imu3"), {}, "triads key is 'imu3'"),
        (
            ("created",),
            "yesterday",
            "created must be an ISO 8601 date or date-time, got 'yesterday'",
        ),
        (("unit_id",), " ", "unit_id must not be empty"),
        (("sensor_ids",), {"accel": 17}, "sensor_ids must map strings to strings"),
        (
            ("type",),
            "ins.health.event",
            r"type tag 'ins\.health\.event' is not 'ins\.health\.passport'",
        ),
    ],
)
def test_invalid_passports_are_rejected_with_the_field_and_value(passport, path, value, match):
    with pytest.raises(PassportError, match=match):
        Passport.from_dict(_mutated(passport, path, value))


@pytest.mark.parametrize(
    ("version", "match"),
    [
        (PASSPORT_SCHEMA_VERSION + 1, "newer than this build reads .*upgrade ins-health"),
        ("1", "not supported"),
        (0, "not supported"),
        (None, "not supported"),
    ],
)
def test_unsupported_schema_versions_raise_a_typed_error_with_a_hint(passport, version, match):
    with pytest.raises(PassportVersionError, match=match):
        Passport.from_dict(_mutated(passport, ("schema_version",), version))


def test_unusable_json_files_name_the_file(passport, tmp_path):
    path = tmp_path / "bad.json"
    path.write_text('{"type": "ins.health.passport", "schema_version": 1,')
    with pytest.raises(PassportError, match=r"bad\.json: not valid JSON \(line 1"):
        read_passport_json(path)
    text = json.dumps(passport.to_dict()).replace("[0.001, 0.001, 0.001]", "[NaN, 0.001, 0.001]", 1)
    path.write_text(text)
    with pytest.raises(PassportError, match="non-finite number NaN"):
        read_passport_json(path)
    path.write_text(json.dumps(_mutated(passport, ("schema_version",), 99)))
    with pytest.raises(
        PassportVersionError, match=r"bad\.json: passport schema version 99 is newer"
    ):
        read_passport_json(path)


def test_passport_arrays_are_read_only(passport):
    tp = passport.triads[Triad.ACCEL]
    with pytest.raises(ValueError, match="read-only"):
        tp.nominal[0] = 1.0
    with pytest.raises(TypeError):
        passport.triads[Triad.GYRO] = tp


def test_bias_instability_survives_window_averaging_and_floors_position_covariances(passport):
    tp = passport.triads[Triad.ACCEL]
    wander = np.array([1e-4, 2e-4, 0.0])
    audited = TriadPassport.from_dict(
        Triad.ACCEL, {**tp.to_dict(), "bias_instability_std": wander.tolist()}
    )
    # White noise averages down as 1/n, the wander not at all: σ_eff²/n = σ_w²/n + σ_bi².
    n = 100
    np.testing.assert_allclose(
        audited.effective_noise_std(n) ** 2 / n, tp.noise_std**2 / n + wander**2, rtol=1e-12
    )
    np.testing.assert_allclose(tp.effective_noise_std(n), tp.noise_std)
    np.testing.assert_allclose(np.diag(audited.position_cov_floor()), (wander * tp.reference) ** 2)
