"""Event and status schemas: stable ids, lossless round trips, validated decoding."""

import json
from dataclasses import replace

import msgpack
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from estimators.conventions import Cause, Triad
from estimators.diagnosis import Finding
from protocols._schema import Reason
from protocols.events import (
    Event,
    EventError,
    ImuState,
    ImuStatus,
    Predicate,
    ServiceStatus,
    Severity,
    Status,
    StreamCause,
    decode_event,
    decode_service_status,
    decode_status,
    encode_event,
    encode_service_status,
    encode_status,
    event_from_finding,
    event_from_json,
    event_to_dict,
    event_to_json,
    make_event,
    status_to_dict,
)

FINDING = Finding("F5", Triad.ACCEL, "y", Cause.SCALE_FACTOR, 2.1e-3, 0.0, 1.0e-3, 1.0e-4)


def _event(**kw):
    base = dict(vehicle="v1", imu=1, t_s=125.25)
    base.update(kw)
    return event_from_finding(FINDING, **base)


def test_severity_values_are_mavlinks():
    for s in Severity:
        assert s.value == getattr(mavlink2, f"MAV_SEVERITY_{s.name}")


def test_id_is_stable_and_depends_on_every_identifying_field():
    e = _event()
    assert e.event_id == _event().event_id  # same detection, same id (retry, replay)
    assert len(e.event_id) == 32
    others = {
        _event(vehicle="v2").event_id,
        _event(imu=0).event_id,
        _event(t_s=125.25 + 1e-9).event_id,
        event_from_finding(replace(FINDING, axis="x"), vehicle="v1", imu=1, t_s=125.25).event_id,
        event_from_finding(
            replace(FINDING, predicate="F2", cause=Cause.ZERO_SIGNAL),
            vehicle="v1",
            imu=1,
            t_s=125.25,
        ).event_id,
        event_from_finding(
            replace(FINDING, triad=Triad.GYRO), vehicle="v1", imu=1, t_s=125.25
        ).event_id,
    }
    assert e.event_id not in others and len(others) == 6
    # Numbers and severity describe the detection; they do not make a new one.
    assert _event(severity=Severity.CRITICAL).event_id == e.event_id


def test_the_same_fault_at_the_same_uptime_after_a_reboot_is_a_new_event():
    """The id held the time since boot only: the first fault after a reboot at the uptime of one before
    it had the old id, and the outbox dropped it as delivered. The source's epoch (its runs) now enters
    the id; epoch 0 keeps the ids events had, and is written at the schema versions it was."""
    first, rebooted = _event(), _event(epoch=1)
    assert rebooted.event_id != first.event_id
    assert rebooted.event_id == _event(epoch=1).event_id  # a retry keeps its id
    assert event_to_dict(first)["v"] == 1 and "epoch" not in event_to_dict(first)
    assert event_to_dict(rebooted)["v"] == 3 and event_to_dict(rebooted)["epoch"] == 1
    assert decode_event(encode_event(rebooted)) == rebooted
    # A map of an older version naming no epoch is epoch 0, whatever else it holds.
    assert decode_event(encode_event(first)).epoch == 0


def test_finding_maps_onto_event_fields():
    e = _event()
    assert (e.predicate, e.triad, e.axis, e.cause) == (
        Predicate.F5,
        Triad.ACCEL,
        "y",
        Cause.SCALE_FACTOR,
    )
    assert (e.estimate, e.nominal, e.tolerance, e.sigma, e.unit) == (
        2.1e-3,
        0.0,
        1.0e-3,
        1.0e-4,
        "1",
    )
    assert e.severity is Severity.ERROR
    # The text names the instance, the sensor, the cause and the number.
    assert (
        e.text
        == "v1 IMU1 accelerometer y: scale factor error 0.0021 (nominal 0, tolerance 0.001, sigma 0.0001) [F5]"
    )


@pytest.mark.parametrize("predicate", [5, "F5", Predicate.F5])
def test_predicate_given_as_int_string_or_enum(predicate):
    assert (
        event_from_finding(replace(FINDING, predicate=predicate), vehicle="v1", imu=1, t_s=125.25)
        == _event()
    )


def test_generic_constructor_for_stream_validity():
    e = make_event(
        vehicle="v1",
        imu=2,
        t_s=40.0,
        predicate="timeout",
        cause=StreamCause.NO_DATA,
        severity=Severity.CRITICAL,
        estimate=0.75,
        tolerance=0.2,
        unit="s",
    )
    assert e.triad is None and e.axis is None
    assert e.text == "v1 IMU2: no samples 0.75 s (tolerance 0.2) [timeout]"
    stale = make_event(
        vehicle="v1",
        imu=0,
        t_s=3.0,
        predicate=Predicate.STALE,
        cause="stuck_value",
        severity=Severity.WARNING,
        triad="gyro",
        axis="z",
        estimate=400,
        unit="count",
        text="custom",
    )
    assert stale.text == "custom" and stale.estimate == 400.0 and isinstance(stale.estimate, float)


@pytest.mark.parametrize(
    "e",
    [
        _event(),
        make_event(
            vehicle="v9",
            imu=0,
            t_s=1.0,
            predicate="F0",
            cause="out_of_shell",
            severity=4,
            triad="accel",
            estimate=0.05,
            tolerance=0.01,
        ),
        make_event(
            vehicle="v9",
            imu=0,
            t_s=2.0,
            predicate="cross_imu",
            cause="disagreement",
            severity=Severity.WARNING,
        ),
    ],
)
def test_msgpack_and_json_round_trips(e):
    assert decode_event(encode_event(e)) == e
    line = event_to_json(e)
    assert "\n" not in line and json.loads(line)["id"] == e.event_id
    assert event_from_json(line) == e


def _mutate(**kw):
    d = event_to_dict(_event())
    d.update(kw)
    return {k: v for k, v in d.items() if v is not _DROP}


_DROP = object()

BAD_MAPS = {
    "unknown version": (_mutate(v=7), Reason.UNKNOWN_VERSION),
    "unknown type": (_mutate(type="ins.imu.frame"), Reason.UNKNOWN_TYPE),
    "missing text": (_mutate(text=_DROP), Reason.MISSING_FIELD),
    "imu as str": (_mutate(imu="1"), Reason.WRONG_TYPE),
    "unknown predicate": (_mutate(predicate="F10"), Reason.BAD_VALUE),
    "unknown cause": (_mutate(cause="gremlins"), Reason.BAD_VALUE),
    "unknown triad": (_mutate(triad="magnetometer"), Reason.BAD_VALUE),
    "bad axis": (_mutate(axis="w"), Reason.BAD_VALUE),
    "bad severity": (_mutate(severity="panic"), Reason.BAD_VALUE),
    "estimate as str": (_mutate(estimate="2e-3"), Reason.WRONG_TYPE),
    "NaN sigma": (_mutate(sigma=float("nan")), Reason.NON_FINITE),
    "forged id": (_mutate(id="0" * 32), Reason.BAD_VALUE),
    "id changed field": (_mutate(axis="z"), Reason.BAD_VALUE),
    "short id": (_mutate(id="abc"), Reason.BAD_VALUE),
    "version 3 without epoch": (_mutate(v=3), Reason.MISSING_FIELD),
    "version 3 of epoch 0": (_mutate(v=3, epoch=0), Reason.BAD_VALUE),
    "epoch as str": (_mutate(v=3, epoch="1"), Reason.WRONG_TYPE),
    "negative epoch": (_mutate(v=3, epoch=-1), Reason.BAD_VALUE),
    "epoch the id lacks": (_mutate(v=3, epoch=2), Reason.BAD_VALUE),
}


@pytest.mark.parametrize("case", sorted(BAD_MAPS))
def test_bad_events_rejected_with_reason(case):
    obj, reason = BAD_MAPS[case]
    with pytest.raises(EventError) as info:
        decode_event(msgpack.packb(obj, use_bin_type=True))
    assert info.value.reason is reason, str(info.value)


@pytest.mark.parametrize(
    "data,reason",
    [
        (b"\x93\x01", Reason.MALFORMED),
        (msgpack.packb("just a string"), Reason.NOT_A_MAP),
        (b"\x80" + b"\x00" * 70_000, Reason.TOO_LARGE),
    ],
)
def test_bad_event_bytes(data, reason):
    with pytest.raises(EventError) as info:
        decode_event(data)
    assert info.value.reason is reason


@pytest.mark.parametrize(
    "text,reason",
    [
        ("{not json", Reason.MALFORMED),
        ('{"t_s": NaN}', Reason.NON_FINITE),
        ("[1, 2]", Reason.NOT_A_MAP),
    ],
)
def test_bad_json_lines(text, reason):
    with pytest.raises(EventError) as info:
        event_from_json(text)
    assert info.value.reason is reason


def test_status_round_trip_and_validation():
    st = Status(
        vehicle="v1",
        service="svc-a",
        t_s=1.7e9,
        counters={"frames": 10, "rejected.non_finite": 2, "dropped": 0},
        imus=(
            ImuStatus(0, ImuState.OK, samples=2000, last_t_s=10.0, positions=4),
            ImuStatus(1, "no_data"),
        ),
    )
    out = decode_status(encode_status(st))
    assert out == st and out.imus[1].state is ImuState.NO_DATA and out.imus[1].last_t_s is None
    with pytest.raises(TypeError):
        out.counters["frames"] = 11  # read-only view
    with pytest.raises(EventError, match="counter 'x' must be"):
        Status(vehicle="v1", service="s", t_s=0.0, counters={"x": -1})
    bad = msgpack.unpackb(encode_status(st), raw=False)
    bad["imus"][0]["state"] = "exploded"
    with pytest.raises(EventError) as info:
        decode_status(msgpack.packb(bad))
    assert info.value.reason is Reason.BAD_VALUE


def test_status_carries_each_imus_coverage_and_older_statuses_still_decode():
    from estimators.coverage import Check, CheckCoverage

    coverage = (
        CheckCoverage(Check.F0, Triad.ACCEL, ran=True, samples=900, mdf_bias_si=(0.3, float("inf"), 0.2),
                      mdf_scale=(0.03, float("inf"), 0.02), false_alarm_prob=1e-9),
        CheckCoverage(Check.F1_F9, Triad.ACCEL, ran=False, positions=3, reason="3 positions at rest, 9 needed"),
    )  # fmt: skip
    st = Status("v1", "svc", 1.7e9, imus=(ImuStatus(0, ImuState.STARTING, coverage=coverage),))
    wire = msgpack.unpackb(encode_status(st), raw=False)
    assert wire["v"] == 2 and wire["imus"][0]["coverage"][1]["reason"].startswith("3 positions")
    assert decode_status(encode_status(st)) == st
    # A version-1 status (before coverage) decodes, with no coverage.
    old = {**wire, "v": 1, "imus": [{k: v for k, v in wire["imus"][0].items() if k != "coverage"}]}
    assert decode_status(msgpack.packb(old)).imus[0].coverage == ()
    wire["imus"][0]["coverage"][0]["triad"] = "magnetometer"
    with pytest.raises(EventError, match="unusable coverage entry") as info:
        decode_status(msgpack.packb(wire))
    assert info.value.reason is Reason.BAD_VALUE


def test_a_status_with_a_check_this_reader_does_not_know_is_read_and_keeps_it():
    """A newer daemon adds checks within status version 2 (the thrust axis, the cross-IMU norm):
    an older reader reads the rest of its status, keeps the entry as it came and writes it back
    (``watch --json``), and a person is told a newer daemon's check is not understood here."""
    from estimators.coverage import Check, CheckCoverage
    from service.commands.watch import status_line

    f0 = CheckCoverage(Check.F0, Triad.ACCEL, ran=True, samples=900)
    st = Status("v1", "svc", 1.7e9, imus=(ImuStatus(0, ImuState.OK, samples=900, coverage=(f0,)),))
    wire = msgpack.unpackb(encode_status(st), raw=False)
    newer = {"check": "cross_imu_heading", "triad": None, "ran": True, "samples": 12, "extra": [1]}
    wire["imus"][0]["coverage"].append(newer)
    read = decode_status(msgpack.packb(wire))
    assert read.imus[0].coverage == (f0,) and read.imus[0].samples == 900
    assert read.imus[0].unknown_coverage == (newer,)
    assert status_to_dict(read)["imus"][0]["coverage"] == wire["imus"][0]["coverage"]
    said = status_line(read, 1.7e9)
    assert "checks unknown to this watch (a newer daemon's): cross_imu_heading" in said


def test_event_construction_rejects_non_finite_numbers():
    with pytest.raises(EventError, match="estimate must be a finite number"):
        make_event(
            vehicle="v1",
            imu=0,
            t_s=0.0,
            predicate="F0",
            cause="out_of_shell",
            severity=4,
            estimate=float("inf"),
        )
    with pytest.raises(EventError, match="t_s must be a finite number"):
        make_event(
            vehicle="v1", imu=0, t_s=float("nan"), predicate="F0", cause="out_of_shell", severity=4
        )
    assert isinstance(_event(), Event)


def test_a_service_status_says_an_instance_runs_before_any_vehicle():
    """An instance's own status: no vehicle needed; its vehicles and counters checked as a vehicle's."""
    none_yet = ServiceStatus(service="onboard", t_s=1.7e9)
    assert decode_service_status(encode_service_status(none_yet)) == none_yet
    serving = ServiceStatus("onboard", 1.7e9, ("uav-1",), {"service.frames.dropped_overload": 3})
    assert decode_service_status(encode_service_status(serving)) == serving
    with pytest.raises(EventError, match="counter 'x' must be"):
        ServiceStatus("onboard", 0.0, counters={"x": -1})
    with pytest.raises(EventError):
        ServiceStatus("onboard", 0.0, vehicles=("bad/id",))
    # A vehicle's status is not taken for an instance's, nor the other way round.
    with pytest.raises(EventError):
        decode_service_status(encode_status(Status(vehicle="v1", service="onboard", t_s=0.0)))
    with pytest.raises(EventError):
        decode_status(encode_service_status(none_yet))
