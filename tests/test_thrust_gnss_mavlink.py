"""The thrust-axis check on a live MAVLink link (issue 32): the autopilot's GPS_RAW_INT beside its IMU
messages, read by the link's reader process, into the fleet's check of the link's vehicle; a
thrust-axis fault in flight reaches the ground station as an event.

The flight: 5 s rest, 90 s of ``Fly``, 5 s rest, consumer MEMS at 25 Hz (the lowest rate of the
ones tried, 25/50/100 Hz, at which the fault is found as at 100 Hz: 6 s after its onset), a
receiver at 10 Hz (0.05 m/s, 0.15 s latency); z + 0.1 m/s² from 80 s, after the check's 60 s of
learning in flight.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import zenoh
from pymavlink import mavutil
from service_support import (
    ServiceThread,
    free_udp_port,
    mavlink_packets,
    receive_until,
    service_config,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)
from test_service_faults import Statuses
from test_service_mavlink import stored_events

from estimators.session import ImuSession
from estimators.sim import Fly, flight_spec, simulate
from estimators.sim.gnss import gnss_velocity
from protocols.events import Predicate
from protocols.gnss_logs import gps_raw_int_messages, gps_raw_int_si, gps_raw_int_track
from protocols.mavlink_adapter import ImuMessage, LinkCounters, alert_text, use_mavlink2
from protocols.mavlink_gnss import GpsRawIntStream
from protocols.zenoh_adapter import EventReceiver

ONSET_S = 80.0


@functools.cache
def flight():
    res = simulate(flight_spec(fly=Fly(90.0), rest_s=5.0, rate_hz=25.0), 4)
    gt, gv = gnss_velocity(
        res.truth, rate_hz=10.0, vel_sd_mps=0.05, latency_s=0.15, rng=np.random.default_rng(4)
    )
    alt = 100.0 + np.r_[0.0, np.cumsum(0.5 * (gv[1:, 2] + gv[:-1, 2]) * np.diff(gt))]
    return res.session, gt, gv, alt


def test_gps_raw_int_in_pieces_gives_the_epochs_of_the_whole_track():
    """GPS_RAW_INT fields cut into pieces of 1 to 7 messages, with epochs without a fix, of unknown
    course, of a repeated time and of a clock gone back among them: the frames hold the whole track's epochs (the log's
    reading) but the last (its vertical waits for the next epoch), left-out epochs counted by the
    same reasons, and the receiver's rate."""
    rng = np.random.default_rng(1)
    _s, gt, gv, alt = flight()
    speed = np.hypot(gv[:, 0], gv[:, 1])
    cog = np.round(np.degrees(np.arctan2(gv[:, 0], gv[:, 1])) * 100) % 36000
    fix = np.where(rng.random(gt.size) < 0.05, 2, 3)
    fix[:4] = 1  # no fix at first
    raw = np.column_stack(
        [np.round(gt * 1e6), fix, np.round(speed * 100), cog, np.round(alt * 1e3)]
    )
    raw[rng.choice(gt.size, 10, replace=False), 3] = 65535
    raw = np.insert(raw, 300, raw[299], axis=0)
    # The clock back by 0.3 s and forward again, short of where it was.
    raw = np.insert(raw, 500, raw[[497, 498]] + [[0, 0, 0, 0, 0], [50_000, 0, 0, 0, 0]], axis=0)
    whole = gps_raw_int_track(gps_raw_int_si(raw))
    counters = LinkCounters()
    stream = GpsRawIntStream("mav1", counters)
    frames, k = [], 0
    while k < len(raw):
        n = int(rng.integers(1, 8))
        frames += stream.frames(raw[k : k + n])
        k += n
    np.testing.assert_array_equal(np.concatenate([f.t_s for f in frames]), whole.t_s[:-1])
    np.testing.assert_allclose(
        np.concatenate([f.vel_enu_mps for f in frames]), whole.vel_enu_mps[:-1], rtol=0, atol=1e-12
    )
    assert [f.seq for f in frames] == list(range(len(frames)))
    assert counters.rejected == {f"gnss_{k}": n for k, n in whole.rejected.items()}
    assert set(whole.rejected) == {"no_3d_fix", "not_finite"}  # the repeat has no vertical
    np.testing.assert_allclose([f.rate_hz for f in frames[5:]], 10.0, rtol=1e-6)


def autopilot_packets(*, fault: bool) -> tuple[list[bytes], int, int]:
    """The flight as its autopilot sends it, HIGHRES_IMU and GPS_RAW_INT in time order; with the
    counts of each."""
    session, gt, gv, alt = flight()
    accel = session.accel_mps2.copy()
    if fault:
        accel[session.t_s >= ONSET_S, 2] += 0.1
    imu = mavlink_packets(ImuSession(session.t_s, accel, session.gyro_rps), ImuMessage.HIGHRES_IMU)
    gnss = gps_raw_int_messages(gt, gv, alt)
    order = np.argsort(np.r_[session.t_s, gt], kind="stable")
    both = imu + gnss
    return [both[k] for k in order], len(imu), len(gnss)


@pytest.mark.network
@pytest.mark.parametrize("fault", [True, False], ids=["fault", "fault-free"])
def test_a_thrust_axis_fault_over_the_mavlink_link_reaches_the_ground_station(
    tmp_path, caplog, fault
):
    """A daemon reading vehicle mav1 over UDP (its reader process), sent the flight 20 messages to a
    datagram: every GPS_RAW_INT is read and becomes GNSS frames of mav1 (status topic); with the
    fault, one thrust_axis event on the accelerometer's z within 10 s of the onset reaches the
    ground station (Zenoh) and its alert the MAVLink peer; the fault-free twin raises none, and its
    status says the check ran. The twin's stream begins with GPS_RAW_INT of another system (another
    clock than the IMUs'): they are counted and logged, not used."""
    packets, n_imu, n_gnss = autopilot_packets(fault=fault)
    other = [] if fault else gps_raw_int_messages(*flight()[1:], source_system=2)[:5]
    packets, n_gnss = other + packets, n_gnss + len(other)
    mav_port = free_udp_port()
    link = {"enabled": True, "device": f"udpin:127.0.0.1:{mav_port}", "vehicle": "mav1"}
    with zenoh_router() as zport, zenoh.open(zenoh_client_config(zport)) as ground:
        cfg = service_config(
            tmp_path, port=zport, passport_dir=tmp_path / "passports",
            validity={"timeout_s": 60.0}, mavlink=link,
        )  # fmt: skip
        status, got = Statuses(ground), []
        with (
            caplog.at_level("WARNING", logger="ins_health"),
            ServiceThread(cfg) as svc,
            EventReceiver(ground, got.append),
        ):
            peer = use_mavlink2(mavutil.mavlink_connection(f"udpout:127.0.0.1:{mav_port}"))
            try:
                for k in range(0, len(packets), 20):
                    # Paced by the daemon's reading: the socket's buffer never overflows.
                    wait_until(lambda: k - read(status) <= 1000, timeout_s=60, what="the reading")
                    peer.write(b"".join(packets[k : k + 20]))
                wait_until(
                    lambda: (
                        status.counter("mav1", "imu0.samples.accepted") == n_imu
                        and status.counter("mav1", "service.mavlink.gnss_messages") == n_gnss
                    ),
                    timeout_s=60,
                    what=lambda: f"every message counted: {status.get('mav1')}",
                )
                counters = status.get("mav1").counters
                assert counters["service.gnss.frames"] > 0
                rejected = {k: n for k, n in counters.items() if "gnss" in k and "rejected" in k}
                assert rejected == (
                    {} if fault else {"service.mavlink.rejected.gnss_other_system": 5}
                )
                if fault:
                    wait_until(
                        lambda: any(e.predicate is Predicate.THRUST_AXIS for e in got),
                        timeout_s=30,
                        what="the thrust_axis event",
                    )
                    (e,) = [e for e in got if e.predicate is Predicate.THRUST_AXIS]
                    assert e.vehicle == "mav1" and e.axis == "z"
                    assert ONSET_S <= e.t_s <= ONSET_S + 10.0
                    texts = receive_until(
                        peer, ["STATUSTEXT"],
                        lambda m: any(x.text == alert_text(e) for x in m),
                        timeout_s=30, what="the thrust_axis alert",
                    )  # fmt: skip
                    assert texts
                else:
                    stored = stored_events(svc)
                    assert not [e for e in stored if e.predicate is Predicate.THRUST_AXIS]
                    assert not [e for e in got if e.predicate is Predicate.THRUST_AXIS]
                    lines = [
                        c for c in status.get("mav1").imus[0].coverage
                        if c.check.value == "thrust_axis"
                    ]  # fmt: skip
                    assert len(lines) == 1 and lines[0].ran
                    said = [r.getMessage() for r in caplog.records]
                    assert [m for m in said if "5 gnss_other_system" in m], said
            finally:
                peer.close()


def read(status: Statuses) -> int:
    """Messages of mav1 the daemon read (IMU and GNSS), from its status."""
    return status.counter("mav1", "service.mavlink.messages") + status.counter(
        "mav1", "service.mavlink.gnss_messages"
    )
