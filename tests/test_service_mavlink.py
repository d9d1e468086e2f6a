"""The service on a real MAVLink link on 127.0.0.1: IMU messages in, HEARTBEAT and STATUSTEXT out (pymavlink peer)."""

from __future__ import annotations

import functools
import json
import socket
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from real_data import REAL_TLOG, needs
from service_support import (
    RMEM_MAX,
    ServiceThread,
    free_tcp_port,
    free_udp_port,
    mavlink_packets,
    needs_rmem_max,
    of_type,
    receive_until,
    service_config,
    wait_subscribed,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)
from test_service_faults import ServiceProcess, Statuses, put_store, write_config

from estimators.conventions import Triad
from estimators.session import ImuSession
from protocols.events import Predicate, Severity, decode_event
from protocols.frames import SampleBatch
from protocols.log_rate import LOG_PERIOD_S
from protocols.mavlink_adapter import (
    ImuMessage,
    alert_text,
    decode_imu_message,
    use_mavlink2,
)
from protocols.zenoh_adapter import EventReceiver, FramePublisher, frame_key
from service.demo import demo_passport, demo_scenario
from service.passport_store import PassportStore

pytestmark = pytest.mark.network
QUIET = {"timeout_s": 60.0}


@functools.cache
def unit():
    passport, g = demo_passport()
    sc = demo_scenario()
    # From shortly before landing: the fault, F0 on the landed unit, then the post-flight handling.
    return passport, g, sc, sc.landing_s - 0.5


def store(tmp_path, keys):
    st = PassportStore(tmp_path / "passports")
    for v, i in keys:
        st.put(v, i, unit()[0])
    return st.root


def decoded(packets: list[bytes]) -> list:
    """What the service decodes from these packets (the SI values of the 'equivalent frames')."""
    parser = mavlink2.MAVLink(None)
    return [decode_imu_message(m) for p in packets for m in parser.parse_buffer(p)]


def test_statustext_alerts_reach_a_udp_peer_with_their_severity(tmp_path):
    """An autopilot-side peer streams SCALED_IMU over UDP; it gets HEARTBEATs and the F0 (warning) and F6 (error) alerts."""
    _passport, g, sc, start = unit()
    port = free_udp_port()
    cfg = service_config(
        tmp_path, port=None, passport_dir=store(tmp_path, [("mav1", 0)]), site={"gravity_mps2": g}, validity=QUIET,
        mavlink={"enabled": True, "device": f"udpin:127.0.0.1:{port}", "vehicle": "mav1"},
    )  # fmt: skip
    packets = mavlink_packets(sc.session, ImuMessage.SCALED_IMU, start_s=start)
    with ServiceThread(cfg) as svc:
        peer = use_mavlink2(
            mavutil.mavlink_connection(
                f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
            )
        )
        try:
            received = lambda: svc.call(lambda: svc.service.mavlink_sink.link.counters.messages)  # noqa: E731
            # 20 messages per datagram; at most 50 datagrams in flight, so the socket buffer never overflows.
            for k in range(0, len(packets), 20):
                if k % 1000 == 0:
                    wait_until(
                        lambda: k - received() <= 1000,
                        timeout_s=30,
                        what="the service reading the stream",
                    )
                peer.write(b"".join(packets[k : k + 20]))
            wait_until(
                lambda: received() == len(packets), timeout_s=30, what="every IMU message read"
            )
            got = receive_until(
                peer,
                ["STATUSTEXT", "HEARTBEAT"],
                lambda msgs: len(of_type(msgs, "STATUSTEXT")) >= 2 and of_type(msgs, "HEARTBEAT"),
                timeout_s=30,
                what="two STATUSTEXT and a HEARTBEAT",
            )
            texts = [(m.severity, m.text) for m in of_type(got, "STATUSTEXT")]
            heartbeat = of_type(got, "HEARTBEAT")[0]
        finally:
            peer.close()
        stored = stored_events(svc)
    assert [e.predicate for e in stored] == [Predicate.F0, Predicate.F6]
    assert texts == [
        (int(Severity.WARNING), alert_text(stored[0])),
        (int(Severity.ERROR), alert_text(stored[1])),
    ]
    assert texts[1][1].startswith("IMU0 ACC Z scale") and len(texts[1][1]) <= 50
    assert heartbeat.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert heartbeat.get_srcComponent() == mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER


def stored_events(svc) -> list:
    return svc.call(lambda: [decode_event(p.payload) for p in svc.service.outbox.stored()])


def test_alerts_are_rate_limited_while_every_event_is_kept(tmp_path):
    """The y gyro sticks and frees itself five times in 5 s: ten events are stored, two STATUSTEXT go out
    (the first 'stuck' and the first 'recovered'); the eight repeats are suppressed on MAVLink only."""
    _passport, g, sc, _start = unit()
    port = free_udp_port()
    cfg = service_config(
        tmp_path, port=None, passport_dir=store(tmp_path, [("mav1", 0)]), site={"gravity_mps2": g}, validity=QUIET,
        mavlink={"enabled": True, "device": f"udpin:127.0.0.1:{port}", "vehicle": "mav1", "alert_max_per_s": 50.0},
    )  # fmt: skip
    s = sc.session
    k0 = int(np.searchsorted(s.t_s, 10.0))
    gyro = s.gyro_rps[k0 : k0 + 1000].copy()
    for cycle in range(5):
        gyro[cycle * 200 : cycle * 200 + 150, 1] = 0.01  # stuck for 150 samples, free for 50
    flapping = type(s)(s.t_s[k0 : k0 + 1000], s.accel_mps2[k0 : k0 + 1000], gyro, None)
    packets = mavlink_packets(flapping, ImuMessage.HIGHRES_IMU)
    with ServiceThread(cfg) as svc:
        peer = use_mavlink2(
            mavutil.mavlink_connection(
                f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
            )
        )
        try:
            for k in range(0, len(packets), 20):
                peer.write(b"".join(packets[k : k + 20]))
            wait_until(
                lambda: svc.call(lambda: svc.service.events_stored) >= 9,
                timeout_s=30,
                what="the stale events",
            )
            wait_until(lambda: svc.call(lambda: svc.service.outbox.counts().pending_by_sink["mavlink"]) == 0,
                       timeout_s=30, what="the alert sink to go through the events")  # fmt: skip
            # Every alert was sent before this point: read until the link is quiet, within a deadline.
            deadline = time.monotonic() + 30
            texts = []
            while (
                msg := peer.recv_match(type="STATUSTEXT", blocking=True, timeout=0.5)
            ) is not None:
                texts.append(msg.text)
                assert time.monotonic() < deadline, f"STATUSTEXT still coming after 30 s: {texts}"
        finally:
            peer.close()
        policy = svc.call(lambda: svc.service.mavlink_sink.policy)
        stored = stored_events(svc)
    assert [e.predicate for e in stored] == [Predicate.STALE] * len(stored) and len(stored) in (
        9,
        10,
    )
    assert (
        texts == [alert_text(stored[0]), alert_text(stored[1])]
        and "stuck" in texts[0]
        and "recovered" in texts[1]
    )
    assert policy.suppressed == len(stored) - 2


def test_raw_scaled_and_highres_input_give_the_diagnosis_of_equivalent_zenoh_frames(tmp_path):
    """The same samples as RAW_IMU, SCALED_IMU2 and HIGHRES_IMU over TCP (vehicle mav1, IMUs 0, 1, 2) and as
    Zenoh frames of the values the service decodes from them (vehicle zen1): the same events, number for number."""
    _passport, g, sc, start = unit()
    kinds = {0: ImuMessage.RAW_IMU, 1: ImuMessage.SCALED_IMU2, 2: ImuMessage.HIGHRES_IMU}
    packets = {i: mavlink_packets(sc.session, kind, start_s=start) for i, kind in kinds.items()}
    mav_port = free_tcp_port()
    with zenoh_router() as zport:
        cfg = service_config(
            tmp_path, port=zport, site={"gravity_mps2": g}, validity=QUIET, pipeline={"queue_capacity": 4096},
            passport_dir=store(tmp_path, [(v, i) for v in ("mav1", "zen1") for i in kinds]),
            mavlink={
                "enabled": True, "device": f"tcpin:127.0.0.1:{mav_port}", "vehicle": "mav1",
                "messages": [k.value for k in kinds.values()], "imu_index": {k.value: i for i, k in kinds.items()},
            },
        )  # fmt: skip
        with (
            ServiceThread(cfg) as svc,
            zenoh.open(zenoh_client_config(zport)) as vehicle,
            zenoh.open(zenoh_client_config(zport)) as ground,
        ):
            got = []
            with EventReceiver(ground, lambda e: got.append(e)):
                with socket.create_connection(("127.0.0.1", mav_port), timeout=10) as tcp:
                    # Interleave the three IMUs sample by sample, as an autopilot does.
                    tcp.sendall(
                        b"".join(p for row in zip(*packets.values(), strict=True) for p in row)
                    )
                    for imu in kinds:
                        samples = decoded(packets[imu])
                        wait_subscribed(vehicle, frame_key("zen1", imu))
                        with FramePublisher(
                            vehicle, "zen1", imu, congestion_control=zenoh.CongestionControl.BLOCK
                        ) as pub:
                            for k in range(0, len(samples), 100):
                                part = samples[k : k + 100]
                                pub.publish(
                                    SampleBatch("zen1", imu, k // 100, np.array([s.t_s for s in part]),
                                                np.array([s.accel_mps2 for s in part]), np.array([s.gyro_rps for s in part]))
                                )  # fmt: skip
                    wait_until(lambda: len(got) >= 12, timeout_s=60,
                               what=lambda: f"F0 and F6 of six IMUs: {sorted((e.vehicle, e.imu, e.predicate.value) for e in got)}, "
                               f"{svc.call(lambda: svc.service.fleet.status('zen1', service='t', now_unix_s=0).counters)}")  # fmt: skip
    key = lambda e: (e.imu, e.predicate, e.triad, e.axis, e.cause, e.t_s, e.estimate)  # noqa: E731
    mav = sorted(key(e) for e in got if e.vehicle == "mav1")
    zen = sorted(key(e) for e in got if e.vehicle == "zen1")
    assert mav == zen and len(mav) == 6
    assert {(i, p) for i, p, *_ in mav} == {
        (i, p) for i in kinds for p in (Predicate.F0, Predicate.F6)
    }
    assert all(t is Triad.ACCEL for _, _, t, *_ in mav)


def daemon_config(tmp_path, zport: int, mav_port: int, **link) -> Path:
    """The daemon's configuration: Zenoh to the router, MAVLink on a UDP port for vehicle mav1."""
    path = write_config(tmp_path, zport, put_store(tmp_path, [("mav1", 0)]))
    table = {"enabled": True, "device": f"udpin:127.0.0.1:{mav_port}", "vehicle": "mav1", **link}
    path.write_text(
        path.read_text()
        + "[mavlink]\n"
        + "".join(f"{k} = {json.dumps(v)}\n" for k, v in table.items())
    )
    return path


def stream(peer, packets: list[bytes], status: Statuses, between=()) -> None:
    """The packets 20 to a datagram, each of ``between`` as its own datagram after every 50th; paced by the
    daemon's count of messages read (status topic) so that the socket's buffer never overflows."""
    for j, k in enumerate(range(0, len(packets), 20)):
        if k % 1000 == 0:
            wait_until(lambda: k - status.counter("mav1", "service.mavlink.messages") <= 1000,
                       timeout_s=60, what="the daemon reading the stream")  # fmt: skip
        peer.write(b"".join(packets[k : k + 20]))
        if j % 50 == 49:
            for datagram in between:
                peer.write(datagram)


def run_daemon(
    tmp_path, packets, between, counted: str, n_counted: int, *, taken: int | None = None, **link
):
    """A real daemon reading vehicle mav1 over UDP (``link``: more [mavlink] keys), sent ``packets`` with
    ``between`` (:func:`stream`), until mav1's F0 and F6 events arrived and the status topic shows
    ``taken`` SCALED_IMU samples read (default: every packet) and ``n_counted`` of ``counted``; returns
    (events, counters, log lines, seconds it ran)."""
    mav_port = free_udp_port()
    with zenoh_router() as zport, zenoh.open(zenoh_client_config(zport)) as ground:
        status, got = Statuses(ground), []
        with EventReceiver(
            ground, lambda e: got.append(e.predicate) if e.vehicle == "mav1" else None
        ):
            daemon = ServiceProcess(daemon_config(tmp_path, zport, mav_port, **link))
            t0 = time.monotonic()
            try:
                peer = use_mavlink2(mavutil.mavlink_connection(f"udpout:127.0.0.1:{mav_port}"))
                stream(peer, packets, status, between=between)
                peer.close()
                wait_until(
                    lambda: len(got) >= 2,
                    timeout_s=60,
                    what=lambda: f"F0 and F6 of mav1, got {got}",
                )
                wait_until(
                    lambda: (
                        status.counter("mav1", counted) == n_counted
                        and status.counter("mav1", "service.mavlink.samples.SCALED_IMU")
                        == (len(packets) if taken is None else taken)
                    ),
                    timeout_s=30,
                    what=lambda: f"every packet counted: {status.get('mav1').counters}",
                )
                counters = status.get("mav1").counters
            finally:
                assert daemon.terminate() == 0
            return got, counters, daemon.lines, time.monotonic() - t0


def test_garbage_and_bad_crc_are_counted_and_logged_while_the_fault_is_found(tmp_path):
    """A real daemon reads a vehicle's SCALED_IMU stream with a fault, between which come datagrams of
    garbage, of a packet with a broken CRC, and of a packet cut short: each is counted on the status
    topic (garbage in bytes) and logged, a new kind at once and more of it at most once per LOG_PERIOD_S;
    the F0 and F6 events arrive."""
    _passport, _g, sc, start = unit()
    packets = mavlink_packets(sc.session, ImuMessage.SCALED_IMU, start_s=start)
    broken = bytearray(packets[0])
    broken[-2] ^= 0x5A
    garbage, cut = b"\x00\x11garbage\x7f" * 4, packets[1][:20]
    hostile = (garbage, bytes(broken), cut)
    n_hostile = len(range(0, len(packets), 20)) // 50
    got, counters, lines, elapsed_s = run_daemon(
        tmp_path, packets, hostile, "service.mavlink.rejected.bad_crc", n_hostile
    )
    assert got == [Predicate.F0, Predicate.F6]
    assert counters["service.mavlink.rejected.garbage_bytes"] == n_hostile * (
        len(garbage) + len(cut)
    )
    assert counters["service.mavlink.dropped_kernel"] == 0  # the stream is paced to the reading
    logged = [line for line in lines if "rejected" in line and "bad_crc" in line]
    # bad_crc's first line, then one a period at most; a line said at once for the other kind
    # (garbage_bytes) may hold bad_crc counted since the last line.
    assert 1 <= len(logged) <= 2 + elapsed_s / LOG_PERIOD_S, lines


def test_a_second_system_on_the_link_does_not_hide_the_autopilots_fault(tmp_path):
    """autopilot_system unset: the vehicle's autopilot (system 1, its IMU with the demo's fault) and a
    second system (42: another vehicle on a shared bus, a simulator; a healthy unit on a clock 2.5 ms
    apart) stream SCALED_IMU interleaved message by message. The link reads the first system heard:
    the fault's F0 and F6 events arrive (merged, the static detector saw no rest and they never
    came), system 42's messages are counted as rejected.other_system and it is logged once."""
    _passport, _g, sc, start = unit()
    healthy = demo_scenario(fault_magnitude=0.0).session
    healthy = ImuSession(healthy.t_s + 0.0025, healthy.accel_mps2, healthy.gyro_rps, None)
    mine = mavlink_packets(sc.session, ImuMessage.SCALED_IMU, start_s=start)
    other = mavlink_packets(
        healthy, ImuMessage.SCALED_IMU, start_s=start, mav=mavlink2.MAVLink(None, srcSystem=42)
    )
    packets = [p for pair in zip(mine, other, strict=True) for p in pair]
    got, counters, lines, _ = run_daemon(
        tmp_path, packets, (), "service.mavlink.rejected.other_system", len(other), taken=len(mine)
    )
    assert got == [Predicate.F0, Predicate.F6]
    assert counters["service.mavlink.messages"] == len(packets)
    said = [line for line in lines if "IMU messages of system" in line]
    assert len(said) == 1 and "system 42 ignored" in said[0], said
    assert "come from system 1, the first heard" in said[0]


KEY = bytes(range(32))


def signer(key: bytes, link_id: int):
    """A pymavlink sender (system 1, the autopilot) that signs with ``key``."""
    conn = use_mavlink2(mavutil.mavlink_connection("udpout:127.0.0.1:9", source_system=1))
    conn.setup_signing(key, sign_outgoing=True, link_id=link_id)
    return conn


def test_with_a_signing_key_only_signed_imu_messages_are_read(tmp_path):
    """A real daemon with a signing key file: the vehicle's stream signed with the key gives its F0 and F6
    events, while IMU messages signed with another key and unsigned ones, sent between, are refused and
    counted on the status topic (bad_signature, unsigned); a replayed packet of the vehicle's, signed
    with the key, is refused and counted apart (signing_stale, logged)."""
    _passport, _g, sc, start = unit()
    (tmp_path / "mav.key").write_text(KEY.hex() + "\n")
    right, wrong = signer(KEY, 1), signer(bytes(reversed(KEY)), 2)
    packets = mavlink_packets(sc.session, ImuMessage.SCALED_IMU, start_s=start, mav=right.mav)
    forged = mavlink_packets(sc.session, ImuMessage.SCALED_IMU, start_s=start, mav=wrong.mav)[:1]
    unsigned = mavlink_packets(sc.session, ImuMessage.SCALED_IMU, start_s=start)[:1]
    right.close()
    wrong.close()
    n_hostile = len(range(0, len(packets), 20)) // 50
    # A replay of the vehicle's first packet: signed with the key, refused as old, counted apart.
    got, counters, lines, _ = run_daemon(
        tmp_path, packets, (forged[0], unsigned[0], packets[0]), "service.mavlink.rejected.unsigned",
        n_hostile, signing_key_file="mav.key",
    )  # fmt: skip
    assert got == [Predicate.F0, Predicate.F6]
    rejected = {
        k: n for k, n in counters.items() if k.startswith("service.mavlink.rejected.") and n
    }
    assert rejected == {
        "service.mavlink.rejected.bad_signature": 2 * n_hostile,
        "service.mavlink.rejected.unsigned": n_hostile,
    }
    assert counters["service.mavlink.signing_stale"] == n_hostile
    assert any(
        "signed with the key were refused as older than their stream" in line for line in lines
    )


IMU_TYPES = frozenset(m.value for m in ImuMessage)


@needs_rmem_max
@pytest.mark.parametrize("reader", ["process", "thread"])
def test_a_receive_buffer_the_kernel_caps_is_said_at_start(tmp_path, caplog, reader):
    """More receive buffer asked than net.core.rmem_max grants: one warning names both and the sysctl."""
    rmem_max = int(RMEM_MAX.read_text())
    asked = rmem_max + 4096
    mavlink = {"enabled": True, "device": f"udpin:127.0.0.1:{free_udp_port()}", "vehicle": "mav1",
               "reader": reader, "udp_rcvbuf_bytes": asked}  # fmt: skip
    cfg = service_config(tmp_path, port=None, passport_dir=put_store(tmp_path, []), mavlink=mavlink)
    with caplog.at_level("WARNING", logger="ins_health"), ServiceThread(cfg) as svc:
        assert svc.service.mavlink_sink.link.udp_rcvbuf_granted_bytes == rmem_max
    said = [r.getMessage() for r in caplog.records if "receive buffer" in r.getMessage()]
    assert len(said) == 1, said
    assert f"granted {rmem_max} bytes of receive buffer of the {asked} asked" in said[0]
    assert f"net.core.rmem_max={asked}" in said[0]


@needs(REAL_TLOG)
def test_a_real_telemetry_log_streamed_live_is_accepted_as_its_replay_accepts_it(tmp_path):
    """The ArduPlane SITL VTOL tlog (SOURCE.md), every recorded packet (23,894, of about a hundred message
    types) sent as the datagram of its own that a MAVProxy --out forwards, 200 at a time, each lot waited
    for on the status topic: the daemon, with no passport, reads RAW_IMU 795 and SCALED_IMU2 796, accepts
    794 and 795 (each IMU's one repeated time stamp is refused and counted, as `ins-health replay` leaves
    out the same two), refuses no byte, drops nothing and raises no event. Its 799 GPS_RAW_INT are read
    for the thrust-axis check, one left out as replay leaves it out (a repeated time: no vertical). The two IMUs come in two message
    types of different units: RAW_IMU's accelerations read 1.2 times too large raise cross-IMU events here."""
    log = mavutil.mavlink_connection(str(REAL_TLOG))
    packets = []
    while (msg := log.recv_msg()) is not None:
        if msg.get_type() != "BAD_DATA":
            packets.append((msg.get_type() in IMU_TYPES, bytes(msg.get_msgbuf())))
    port = free_udp_port()
    with zenoh_router() as zport, zenoh.open(zenoh_client_config(zport)) as ground:
        status, got = Statuses(ground), []
        with EventReceiver(ground, got.append):
            config = write_config(tmp_path, zport, put_store(tmp_path, []), mavlink_port=port)
            config.write_text(
                config.read_text().replace("status_period_s = 0.2", "status_period_s = 0.05")
            )
            daemon = ServiceProcess(config)
            try:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
                    imu_sent = 0
                    for k in range(0, len(packets), 200):
                        for is_imu, packet in packets[k : k + 200]:
                            sock.sendto(packet, ("127.0.0.1", port))
                            imu_sent += is_imu
                        wait_until(
                            lambda: status.counter("mav1", "service.mavlink.messages") >= imu_sent,
                            timeout_s=30,
                            what=lambda: f"{imu_sent} IMU messages read: {status.get('mav1')}",
                        )
                wait_until(
                    lambda: (
                        status.counter("mav1", "imu1.samples.accepted") >= 795
                        and status.counter("mav1", "service.mavlink.gnss_messages") >= 799
                    ),
                    timeout_s=30,
                    what=lambda: f"the last samples accepted: {status.get('mav1')}",
                )
                counters = status.get("mav1").counters
            finally:
                assert daemon.terminate() == 0
    assert len(packets) == 23_894 and got == []
    assert counters["service.mavlink.samples.RAW_IMU"] == 795
    assert counters["service.mavlink.samples.SCALED_IMU2"] == 796
    assert (counters["imu0.samples.accepted"], counters["imu1.samples.accepted"]) == (794, 795)
    for imu in (0, 1):
        assert any(
            n
            for k, n in counters.items()
            if k.startswith((f"imu{imu}.samples.rejected.", f"imu{imu}.frames.rejected."))
        ), counters
    refused = {k: n for k, n in counters.items() if k.startswith("service.mavlink.rejected.") and n}
    assert refused == {"service.mavlink.rejected.gnss_not_finite": 1}
    assert counters["service.mavlink.gnss_messages"] == 799
    assert (
        counters["service.mavlink.dropped_kernel"]
        == counters["service.mavlink.dropped_overload"]
        == 0
    )
