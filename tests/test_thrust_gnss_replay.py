"""The thrust-axis check in ``replay`` (issue 32): GNSS velocity read from the log, an in-flight
fault as a ``thrust_axis`` event, the coverage line and the report's plot; the shared real logs
with GNSS read, and replayed without an in-flight alarm.

The simulated log: the project's flight profile (10 s rest, 170 s of ``Fly``, 10 s rest) of a
consumer-MEMS unit as HIGHRES_IMU at 100 Hz and a receiver's GPS_RAW_INT at 10 Hz (0.05 m/s of
velocity noise, 0.15 s latency; the vertical from the altitude) in one tlog; the same flight as a
PX4 ULog, ``sensor_combined`` and the receiver's own ``sensor_gps`` (newer PX4).
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from real_data import LOGS, SHARED, needs
from replay_support import replay_with_coverage

from estimators.session import ImuSession
from estimators.sim import Fly, flight_spec, simulate
from estimators.sim.gnss import gnss_velocity
from estimators.thrust_gnss import up_velocity_from_altitude
from protocols import gnss_logs
from protocols.events import Predicate, event_from_json, event_to_dict
from protocols.gnss_logs import (
    ULOG_GNSS_TOPICS,
    append_gps_raw_int,
    gps_raw_int_track,
    read_gnss_track,
)
from protocols.logs import write_dataflash_text, write_tlog
from protocols.mavlink_adapter import ImuMessage
from protocols.ulog import UlogGnss, write_ulog
from service.cli import EXIT_FAULT, EXIT_UNTESTED

ONSET_S = 140.0
T0_S = 1000.0


def _flight(*, fault: bool):
    """The IMU session (on the log's clock) and the receiver's epochs, ENU."""
    res = simulate(flight_spec(fly=Fly(170.0), rest_s=10.0), 4)
    s = res.session
    gt, gv = gnss_velocity(
        res.truth, rate_hz=10.0, vel_sd_mps=0.05, latency_s=0.15, rng=np.random.default_rng(4)
    )
    accel = s.accel_mps2.copy()
    if fault:
        accel[s.t_s >= ONSET_S, 2] += 0.1
    return ImuSession(s.t_s + T0_S, accel, s.gyro_rps), gt + T0_S, gv


def _tlog(path, *, fault: bool):
    imu, gt, gv = _flight(fault=fault)
    alt = 100.0 + np.r_[0.0, np.cumsum(0.5 * (gv[1:, 2] + gv[:-1, 2]) * np.diff(gt))]
    write_tlog(path, {0: imu}, messages={0: ImuMessage.HIGHRES_IMU})
    append_gps_raw_int(path, gt, gv, alt)
    return path


def _ned(vel_enu_mps):
    return np.column_stack([vel_enu_mps[:, 1], vel_enu_mps[:, 0], -vel_enu_mps[:, 2]])


def _thrust_check(coverage):
    (imu,) = coverage["imus"]
    (check,) = [c for c in imu["checks"] if c["check"] == "thrust_axis"]
    return check


def test_a_thrust_axis_fault_in_a_logged_flight_is_an_event(capsys, tmp_path):
    """z + 0.1 m/s² from 140 s: one thrust_axis event on the accelerometer's z within 10 s (schema
    version 2), verdict fault; the coverage says z was tested in flight and x, y not."""
    log = _tlog(tmp_path / "flight.tlog", fault=True)
    status, lines, err, coverage = replay_with_coverage(capsys, log, "--json")
    events = [event_from_json(line) for line in lines]
    thrust = [e for e in events if e.predicate is Predicate.THRUST_AXIS]
    assert status == EXIT_FAULT and len(thrust) == 1
    (e,) = thrust
    assert (e.triad.value, e.axis) == ("accel", "z") and event_to_dict(e)["v"] == 2
    assert T0_S + ONSET_S <= e.t_s <= T0_S + ONSET_S + 10.0
    check = _thrust_check(coverage)
    assert check["ran"] and check["mdf_bias_si"][:2] == [None, None]
    assert 0.0 < check["mdf_bias_si"][2] < 0.1
    assert "GNSS: 1899 epochs of GPS_RAW_INT at 10 Hz; left out none" in err
    assert "in flight: z accelerometer tested against GNSS on" in err
    assert "x, y not observable" in err


def test_a_px4_log_with_only_sensor_gps_is_checked_against_it(capsys, tmp_path):
    """Newer PX4 logs the receiver as ``sensor_gps``, maybe without ``vehicle_gps_position``: the
    check runs on it (NED to ENU) and finds the z + 0.1 m/s² from 140 s as on the tlog."""
    imu, gt, gv = _flight(fault=True)
    log = tmp_path / "flight.ulg"
    write_ulog(
        log, {0: imu}, topics=["sensor_combined"], gnss=[UlogGnss("sensor_gps", gt, _ned(gv))]
    )
    status, lines, err, coverage = replay_with_coverage(capsys, log, "--json")
    thrust = [e for e in map(event_from_json, lines) if e.predicate is Predicate.THRUST_AXIS]
    assert status == EXIT_FAULT and len(thrust) == 1
    assert T0_S + ONSET_S <= thrust[0].t_s <= T0_S + ONSET_S + 10.0
    assert thrust[0].axis == "z" and _thrust_check(coverage)["ran"]
    assert f"GNSS: {gt.size} epochs of sensor_gps at 10 Hz; left out none" in err


def _still_ulog(path, *receivers):
    n = 500
    still = ImuSession(
        np.arange(n) / 100.0, np.tile([0.0, 0.0, 9.8], (n, 1)), np.zeros((n, 3)), None
    )
    write_ulog(path, {0: still}, topics=["sensor_combined"], gnss=receivers)
    return path


def _epochs(topic, *, multi_id=0, fix_type=3, vel_ned_valid=True, n=20):
    t = 0.1 + np.arange(n) * 0.2
    vel = np.column_stack([np.full(n, 1.0), np.full(n, -2.0), np.full(n, 0.5)])
    return UlogGnss(topic, t, vel, multi_id, fix_type, vel_ned_valid)


def test_of_several_px4_gnss_sources_the_one_with_most_epochs_is_taken_the_others_said(tmp_path):
    """Receiver 0 without a fix, receiver 1 with one: receiver 1 (North 1, East -2, Down 0.5 m/s
    is ENU (-2, 1, -0.5)); the same epochs in vehicle_gps_position and sensor_gps: the first."""
    fixes = np.r_[np.zeros(5, int), np.full(15, 3)]
    valid = np.r_[np.ones(17, bool), np.zeros(3, bool)]
    two = _still_ulog(
        tmp_path / "two.ulg",
        _epochs("sensor_gps", fix_type=0),
        _epochs("sensor_gps", multi_id=1, fix_type=fixes, vel_ned_valid=valid),
    )
    track = read_gnss_track(two)
    assert (track.source, track.unused) == ("sensor_gps.1", {"sensor_gps.0": 0})
    assert track.rejected == {"no_3d_fix": 5, "velocity_not_valid": 3}
    np.testing.assert_allclose(track.vel_enu_mps, np.tile([-2.0, 1.0, -0.5], (12, 1)))
    np.testing.assert_allclose(track.t_s, 0.1 + np.arange(5, 17) * 0.2)
    both = _still_ulog(
        tmp_path / "both.ulg", _epochs("sensor_gps"), _epochs("vehicle_gps_position")
    )
    track = read_gnss_track(both)
    assert (track.source, track.unused) == ("vehicle_gps_position", {"sensor_gps": 20})


def _renamed(path, topic, field, new):
    """The log with ``field`` of ``topic``'s format definition renamed (same length): a message
    version without that field."""
    raw = path.read_bytes()
    at = raw.index(field, raw.index(f"{topic}:".encode()))
    path.write_bytes(raw[:at] + new + raw[at + len(field) :])
    return path


def test_a_px4_gnss_instance_of_another_message_version_leaves_the_others_read(capsys, tmp_path):
    """A ``sensor_gps`` without ``vel_n_m_s`` beside a readable ``vehicle_gps_position``: the
    latter is taken and the former said unreadable (not the whole log's GNSS lost); without any
    readable instance, the error names the topic and field. A ``vel_ned_valid`` the message lacks
    is no flag (as DataFlash and MAVLink have none), not an unreadable topic."""
    log = _still_ulog(
        tmp_path / "old.ulg", _epochs("vehicle_gps_position", n=15), _epochs("sensor_gps")
    )
    track = read_gnss_track(_renamed(log, "sensor_gps", b"vel_n_m_s", b"vel_n_m_x"))
    assert (track.source, track.t_s.size) == ("vehicle_gps_position", 15)
    assert track.unreadable == {"sensor_gps": "no field vel_n_m_s"}
    _, _, err, _ = replay_with_coverage(capsys, log)
    assert (
        "GNSS: 15 epochs of vehicle_gps_position at 5 Hz; left out none; "
        "unreadable: sensor_gps (no field vel_n_m_s)"
    ) in err
    alone = _renamed(_still_ulog(tmp_path / "alone.ulg", _epochs("sensor_gps")), "sensor_gps", b"vel_n_m_s", b"vel_n_m_x")  # fmt: skip
    with pytest.raises(gnss_logs.GnssLogError, match="sensor_gps: no field vel_n_m_s"):
        read_gnss_track(alone)
    fixes = np.r_[np.zeros(4, int), np.full(16, 3)]
    unflagged = _still_ulog(
        tmp_path / "unflagged.ulg", _epochs("vehicle_gps_position", fix_type=fixes)
    )
    track = read_gnss_track(_renamed(unflagged, "vehicle_gps_position", b"vel_ned_valid", b"vel_ned_vali_"))  # fmt: skip
    assert (track.t_s.size, track.rejected) == (16, {"no_3d_fix": 4})


def test_a_px4_gnss_topic_lost_to_a_damaged_definition_is_not_called_absent(capsys, tmp_path):
    """A type misspelt in sensor_gps's format definition: pyulog drops its 20 records as damage;
    the coverage says the GNSS could not be read, not "no GNSS velocity in the log"."""
    log = _still_ulog(tmp_path / "damaged.ulg", _epochs("sensor_gps"))
    _renamed(log, "sensor_gps", b"float vel_n_m_s", b"flozt vel_n_m_s")
    _, _, err, coverage = replay_with_coverage(capsys, log, "--json")
    assert _thrust_check(coverage)["reason"] == (
        f"{log}: GNSS records unreadable: the file is damaged and no record of "
        "vehicle_gps_position or sensor_gps was read"
    )
    assert "no GNSS velocity" not in err


def _resubscribed(path, topic, multi_id):
    """The log with ``topic`` instance ``multi_id``'s subscription renamed instance 0: the same
    receiver under two subscriptions (two message ids)."""
    raw = path.read_bytes()
    at = re.search(b"A" + bytes([multi_id]) + b".." + topic.encode(), raw, re.DOTALL).start()
    path.write_bytes(raw[: at + 1] + b"\x00" + raw[at + 2 :])
    return path


def test_a_px4_gnss_instance_under_two_subscriptions_is_one_receiver(tmp_path):
    """ULog lets a topic instance be subscribed twice (two message ids): its epochs, every other
    one in each, are one receiver's 20 in time order, which outnumber vehicle_gps_position's 15."""
    t = 0.1 + np.arange(20) * 0.2
    vel = np.tile([1.0, -2.0, 0.5], (10, 1))
    log = _still_ulog(
        tmp_path / "twice.ulg",
        _epochs("vehicle_gps_position", n=15),
        UlogGnss("sensor_gps", t[::2], vel),
        UlogGnss("sensor_gps", t[1::2], vel, multi_id=9),
    )
    track = read_gnss_track(_resubscribed(log, "sensor_gps", 9))
    assert (track.source, track.rejected, track.unused) == (
        "sensor_gps",
        {},
        {"vehicle_gps_position": 15},
    )
    np.testing.assert_allclose(track.t_s, t)


def test_a_damaged_gnss_velocity_beyond_any_receiver_is_left_out_not_a_fault(capsys, tmp_path):
    """One epoch of 1e20 m/s (a damaged float) in the fault-free flight's sensor_gps: it would bury
    the check's velocity integral in rounding (on main: an alarm, exit 1); it is above the 515 m/s
    a civil receiver reports, left out and counted. DataFlash's float GPS likewise."""
    imu, gt, gv = _flight(fault=False)
    vel = _ned(gv)
    vel[1500, 2] = 1e20
    log = tmp_path / "glitch.ulg"
    write_ulog(log, {0: imu}, topics=["sensor_combined"], gnss=[UlogGnss("sensor_gps", gt, vel)])
    status, lines, err, _ = replay_with_coverage(capsys, log, "--json")
    assert status != EXIT_FAULT and not [e for e in lines if "thrust_axis" in e]
    assert (
        f"GNSS: {gt.size - 1} epochs of sensor_gps at 10 Hz; left out speed_over_515_mps 1" in err
    )
    text = tmp_path / "glitch.log"
    write_dataflash_text(text, {0: imu})
    with open(text, "a", encoding="ascii") as fh:
        fh.write("FMT, 130, 23, GPS, QBIHfff, TimeUS,Status,GMS,GWk,Spd,GCrs,VZ\n")
        for k, speed in enumerate([2.0, 1e20, 2.0]):
            fh.write(f"GPS, {1_000_000 + k * 200_000}, 3, 0, 2200, {speed}, 90.0, -0.5\n")
    assert read_gnss_track(text).rejected == {"speed_over_515_mps": 1}
    # A tlog's GPS_RAW_INT as the live intake: 600 m/s fits its uint16 cm/s, and is left out.
    rows = np.array(
        [[1.0 + 0.2 * k, 3, speed, 0.5, 100.0] for k, speed in enumerate([2, 600, 2, 2])]
    )
    assert gps_raw_int_track(rows).rejected == {"speed_over_515_mps": 1}


@pytest.mark.parametrize("topic", ULOG_GNSS_TOPICS)
def test_a_px4_gnss_topic_without_a_valid_velocity_is_said_not_called_absent(
    capsys, tmp_path, topic
):
    """A receiver that never flags its velocity valid: the coverage names the topic and why no
    epoch was kept, not "no GNSS velocity in the log"."""
    log = _still_ulog(tmp_path / "invalid.ulg", _epochs(topic, vel_ned_valid=False))
    _, _, err, coverage = replay_with_coverage(capsys, log, "--json")
    reason = _thrust_check(coverage)["reason"]
    assert reason == (
        f"0 GNSS epoch(s) with a 3D fix and a valid velocity of {topic}, 2 needed; "
        "left out velocity_not_valid 20"
    )
    assert f"accel thrust_axis: does not apply ({reason})" in err


def test_the_fault_free_flight_raises_nothing_and_its_report_plots_the_statistic(capsys, tmp_path):
    log = _tlog(tmp_path / "flight.tlog", fault=False)
    status, lines, _, coverage = replay_with_coverage(
        capsys, log, "--json", "--report", tmp_path / "report"
    )
    assert status == EXIT_UNTESTED and lines == []
    assert _thrust_check(coverage)["ran"]
    assert (tmp_path / "report" / "thrust_axis.png").stat().st_size > 0
    assert (
        "![Thrust axis against GNSS in flight](thrust_axis.png)"
        in (tmp_path / "report" / "report.md").read_text()
    )


def test_the_vertical_from_the_altitude_is_the_centred_difference():
    """A climb at constant acceleration: the centred difference is the velocity at the middle
    epoch exactly; the ends are one-sided."""
    t = np.arange(0.0, 2.0, 0.2)
    v = up_velocity_from_altitude(t, 0.5 * 1.5 * t**2)
    np.testing.assert_allclose(v[1:-1], 1.5 * t[1:-1], atol=1e-12)
    assert v[0] == pytest.approx(1.5 * 0.1) and v[-1] == pytest.approx(1.5 * (t[-1] - 0.1))


@needs(LOGS)
@needs(SHARED / "data" / "field")
def test_the_shared_logs_gnss_is_read_on_their_imu_clock():
    """ULog's vehicle_gps_position (no-fix epochs left out), DataFlash GPS (ArduCopter 3.1's boot
    clock T), the tlog's GPS_RAW_INT: ENU, m/s, seconds of the autopilot's boot clock."""
    px4 = read_gnss_track(LOGS / "px4-events.ulg")
    assert (px4.source, px4.t_s.size, px4.rejected, px4.unused) == (
        "vehicle_gps_position",
        423,
        {"no_3d_fix": 160},
        {"sensor_gps": 22},  # the same receiver logged every second
    )
    tlog = read_gnss_track(LOGS / "ardupilot-sitl-vtol.tlog")
    assert (tlog.source, tlog.t_s.size) == ("GPS_RAW_INT", 798)
    assert 608.0 < tlog.t_s[0] < 609.0 and 4.9 < tlog.rate_hz < 5.1
    old = read_gnss_track(LOGS / "ardupilot-copter31-no-imu.log")
    assert old.t_s[0] == pytest.approx(66.937) and old.t_s.size == 551
    assert read_gnss_track(LOGS / "ardupilot-test.BIN").t_s.size == 5
    fmu = read_gnss_track(SHARED / "data" / "field" / "px4-fmuv3-10hz.ulg")
    assert fmu.rate_hz == pytest.approx(5.0, rel=1e-3)
    assert np.all(np.linalg.norm(fmu.vel_enu_mps, axis=1) < 30.0)


def _damaged(src, tmp_path):
    """The log, the log with bytes overwritten by a false header and garbage a third in, and the
    log cut two thirds in, mid-message."""
    data = src.read_bytes()
    third = len(data) // 3
    garbage = b"\xa3\x95\x00garbage\xa3"
    variants = {
        "whole": data,
        "garbage": data[:third] + garbage + data[third + len(garbage) :],
        "cut": data[: 2 * third + 5],
    }
    for name, content in variants.items():
        path = tmp_path / f"{src.stem}-{name}{src.suffix}"
        path.write_bytes(content)
        yield path


@needs(LOGS)
@needs(SHARED / "data" / "field")
@pytest.mark.parametrize(
    "src",
    [LOGS / "ardupilot-test.BIN", SHARED / "data" / "field" / "ardupilot-copter462-cut.bin"],
    ids=lambda p: p.name,
)
def test_a_binary_logs_gps_messages_are_pymavlinks(tmp_path, src):
    """The numpy scan hands out the GPS messages pymavlink's reader finds, field for field, whole,
    with garbage in the middle and cut short."""
    for path in _damaged(src, tmp_path):
        oracle = gnss_logs._messages(path, "GPS")
        found = gnss_logs._bin_gps_messages(path)
        assert oracle, path.name
        assert [m.to_dict() for m in found] == [m.to_dict() for m in oracle], path.name


def _pymavlink_track(path):
    msgs = gnss_logs._messages(path, "GPS_RAW_INT")
    return gnss_logs.gps_raw_int_track(gnss_logs.gps_raw_int_rows(msgs))


def _same_track(a, b):
    assert (a.source, a.rejected) == (b.source, b.rejected)
    np.testing.assert_array_equal(a.t_s, b.t_s)
    np.testing.assert_array_equal(a.vel_enu_mps, b.vel_enu_mps)


def test_a_tlogs_gps_raw_int_records_are_pymavlinks(tmp_path):
    """The numpy scan reads the simulated flight's GPS_RAW_INT as pymavlink does, to the bit; with
    garbage in the middle the scan stops and pymavlink reads the file."""
    path = _tlog(tmp_path / "flight.tlog", fault=False)
    rows = gnss_logs._scanned_gps_raw_int_rows(path)
    np.testing.assert_array_equal(
        rows, gnss_logs.gps_raw_int_rows(gnss_logs._messages(path, "GPS_RAW_INT"))
    )
    _same_track(read_gnss_track(path), _pymavlink_track(path))
    (damaged,) = [p for p in _damaged(path, tmp_path) if p.stem.endswith("garbage")]
    assert gnss_logs._scanned_gps_raw_int_rows(damaged) is None
    _same_track(read_gnss_track(damaged), _pymavlink_track(damaged))


@needs(LOGS)
def test_the_shared_tlogs_gps_raw_int_records_are_pymavlinks():
    path = LOGS / "ardupilot-sitl-vtol.tlog"
    assert gnss_logs._scanned_gps_raw_int_rows(path) is not None
    _same_track(read_gnss_track(path), _pymavlink_track(path))


REAL_LOGS_WITH_GNSS = [
    LOGS / "px4-events.ulg",
    LOGS / "ardupilot-sitl-vtol.tlog",
    SHARED / "data" / "field" / "px4-fmuv3-10hz.ulg",
    SHARED / "data" / "field" / "px4-fmuv5-knock.ulg",
]


@needs(LOGS)
@needs(SHARED / "data" / "field")
@pytest.mark.parametrize("path", REAL_LOGS_WITH_GNSS, ids=lambda p: p.name)
def test_real_logs_with_gnss_raise_no_in_flight_alarm_and_say_why(capsys, path):
    """None of the shared logs holds the minute of flight with a rest before it that the check
    needs (the longest flies 43 s with no rest): no thrust_axis event, and the coverage says it
    was not tested (they flew: not "does not apply") and why."""
    _, lines, err, coverage = replay_with_coverage(capsys, path, "--json")
    assert all(event_from_json(line).predicate is not Predicate.THRUST_AXIS for line in lines)
    check = _thrust_check(coverage) if len(coverage["imus"]) == 1 else None
    if check is not None:
        assert not check["ran"] and check["applies"] and check["reason"]
    assert "accel thrust_axis: NOT TESTED (" in err


def test_a_log_without_gnss_is_not_decoded_a_second_time(tmp_path, monkeypatch):
    """A ULog and a DataFlash text log whose bytes name no GNSS topic or message hold no GNSS
    velocity, as pyulog finds: read_gnss_track says so without pyulog's or pymavlink's pass over
    every record (as long as replay's own read of the IMU)."""
    from pyulog import ULog

    n = 500
    still = ImuSession(
        np.arange(n) / 100.0, np.tile([0.0, 0.0, 9.8], (n, 1)), np.zeros((n, 3)), None
    )
    ulg, text = tmp_path / "imu.ulg", tmp_path / "imu.log"
    write_ulog(ulg, {0: still}, topics=["sensor_combined"])
    write_dataflash_text(text, {0: still})
    assert not [d for d in ULog(str(ulg), list(ULOG_GNSS_TOPICS)).data_list]

    def decoded_again(*_args, **_kwargs):
        raise AssertionError("the whole log decoded again")

    monkeypatch.setattr("pyulog.ULog", decoded_again)
    monkeypatch.setattr(gnss_logs, "_messages", decoded_again)
    assert read_gnss_track(ulg) is None and read_gnss_track(text) is None
    # The search reads the file in blocks: a name across two of them is found.
    monkeypatch.setattr(gnss_logs, "SEARCH_BLOCK_BYTES", 7)
    assert gnss_logs._mentions(ulg, b"sensor_combined")
