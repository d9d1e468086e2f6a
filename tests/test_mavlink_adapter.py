"""MAVLink with a real pymavlink peer on 127.0.0.1: IMU messages in SI, HEARTBEAT, STATUSTEXT, signing."""

import asyncio
import os
import re
import select
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from service_support import RMEM_MAX, needs_rmem_max, needs_udp_drops
from test_properties import _MAV, imu_messages

from estimators.conventions import STANDARD_GRAVITY_MPS2, Cause, Triad
from estimators.diagnosis import Finding
from protocols import mavlink_adapter
from protocols.events import Severity, StreamCause, event_from_finding, make_event
from protocols.gnss_logs import gps_raw_int_messages
from protocols.mavlink_adapter import (
    REREADS_MAX,
    STATUSTEXT_MAX_CHARS,
    AlertRateLimiter,
    ImuBatcher,
    ImuMessage,
    ImuScale,
    LinkCounters,
    MavlinkLink,
    MavlinkSettings,
    MavlinkSource,
    alert_text,
    decode_imu_message,
    heartbeat_message,
    highres_triads_updated,
    imu_message,
    statustext_messages,
    use_mavlink2,
)
from protocols.mavlink_settings import UDP_RCVBUF_MIN_BYTES

pytestmark = pytest.mark.network
WAIT_S = 5.0
KEY = bytes(range(32))


@pytest.fixture
def gcs():
    """A pymavlink ground station listening on an ephemeral UDP port."""
    conn = use_mavlink2(
        mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    )
    yield conn, conn.port.getsockname()[1]
    conn.close()


def _recv(conn, kind):
    msg = conn.recv_match(type=kind, blocking=True, timeout=WAIT_S)
    assert msg is not None, f"no {kind} within {WAIT_S} s"
    return msg


def _finding_event(**kw):
    finding = Finding("F5", Triad.ACCEL, "y", Cause.SCALE_FACTOR, 2.1e-3, 0.0, 1.0e-3, 1.0e-4)
    return event_from_finding(finding, vehicle="v1", imu=1, t_s=kw.pop("t_s", 100.0), **kw)


# ------------------------------------------------------------------ alerts out


def test_heartbeat_identifies_an_onboard_computer(gcs):
    conn, port = gcs
    with MavlinkLink(
        MavlinkSettings(
            device=f"udpout:127.0.0.1:{port}", vehicle="v1", source_system=7, source_component=196
        )
    ) as link:
        link.send_heartbeat()
        hb = _recv(conn, "HEARTBEAT")
    assert (
        hb.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
        and hb.autopilot == mavlink2.MAV_AUTOPILOT_INVALID
    )
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (7, 196)
    assert hb.get_header().mlen > 0 and hb.get_msgbuf()[0] == 0xFD  # MAVLink 2 on the wire


@pytest.mark.parametrize(
    "severity", [Severity.CRITICAL, Severity.ERROR, Severity.WARNING, Severity.INFO]
)
def test_statustext_alert_arrives_with_its_severity(gcs, severity):
    conn, port = gcs
    event = _finding_event(severity=severity)
    with MavlinkLink(MavlinkSettings(device=f"udpout:127.0.0.1:{port}", vehicle="v1")) as link:
        sent = link.send_alert(event)
        msg = _recv(conn, "STATUSTEXT")
    assert msg.severity == severity.value
    assert msg.text == sent == "IMU1 ACC Y scale 0.0021 lim 0.001 F5"
    assert msg.id == 0  # a single chunk


class _SlowReadCounters(LinkCounters):
    """Reading ``alerts_sent`` gives the interpreter to another thread: a count not made under a
    lock then loses updates every time."""

    def __getattribute__(self, name):
        value = super().__getattribute__(name)
        if name == "alerts_sent":
            time.sleep(0.001)
        return value


def test_alerts_sent_from_several_lanes_at_once_are_each_counted(gcs):
    _conn, port = gcs
    with MavlinkLink(MavlinkSettings(device=f"udpout:127.0.0.1:{port}", vehicle="v1")) as link:
        link.counters = _SlowReadCounters()
        lanes = [
            threading.Thread(target=lambda: [link.send_alert(_finding_event()) for _ in range(10)])
            for _ in range(4)
        ]
        for lane in lanes:
            lane.start()
        for lane in lanes:
            lane.join()
        assert link.counters.alerts_sent == 40


def test_signed_messages_verify_with_the_key_and_fail_with_another(gcs):
    conn, port = gcs
    conn.setup_signing(KEY, sign_outgoing=False, allow_unsigned_callback=None)
    with MavlinkLink(
        MavlinkSettings(device=f"udpout:127.0.0.1:{port}", vehicle="v1", signing_key=KEY)
    ) as link:
        link.send_alert(_finding_event())
        msg = _recv(conn, "STATUSTEXT")
        assert msg.get_signed() and conn.mav.signing.goodsig_count == 1
    other = bytes(reversed(KEY))
    with MavlinkLink(
        MavlinkSettings(device=f"udpout:127.0.0.1:{port}", vehicle="v1", signing_key=other)
    ) as link:
        link.send_alert(_finding_event(t_s=101.0))
        assert (
            conn.recv_match(type="STATUSTEXT", blocking=True, timeout=0.5) is None
        )  # rejected by the GCS
    assert conn.mav.signing.badsig_count >= 1


def test_long_text_goes_out_in_mavlink2_chunks(gcs):
    conn, port = gcs
    text = "v1 IMU1 accelerometer y: scale factor error 0.0021 (nominal 0, tolerance 0.001, sigma 0.0001) [F5]"
    with MavlinkLink(MavlinkSettings(device=f"udpout:127.0.0.1:{port}", vehicle="v1")) as link:
        n = link.send_text(text, Severity.NOTICE)
        chunks = [_recv(conn, "STATUSTEXT") for _ in range(n)]
    assert (
        n == 2
        and [c.chunk_seq for c in chunks] == [0, 1]
        and len({c.id for c in chunks}) == 1
        and chunks[0].id != 0
    )
    assert "".join(c.text for c in chunks) == text


def test_chunking_of_an_exact_multiple_ends_with_an_empty_chunk():
    msgs = statustext_messages("x" * 100, severity=Severity.INFO, chunk_id=9)
    assert [len(m.text) for m in msgs] == [50, 50, 0]


ALL_EVENTS = [
    _finding_event(),
    make_event(
        vehicle="v1",
        imu=12,
        t_s=1.0,
        predicate="F0",
        cause=StreamCause.OUT_OF_SHELL,
        severity=4,
        triad="gyro",
        estimate=-123456.789e-9,
        tolerance=3.3e-7,
    ),
    make_event(
        vehicle="v1",
        imu=0,
        t_s=1.0,
        predicate="timeout",
        cause=StreamCause.NO_DATA,
        severity=2,
        estimate=0.7512,
        tolerance=0.2,
        unit="s",
    ),
    make_event(
        vehicle="v1",
        imu=2,
        t_s=1.0,
        predicate="stale",
        cause=StreamCause.STUCK_VALUE,
        severity=3,
        triad="gyro",
        axis="z",
        estimate=1234567.0,
        unit="count",
    ),
    make_event(
        vehicle="v1",
        imu=255,
        t_s=1.0,
        predicate="cross_imu",
        cause=StreamCause.DISAGREEMENT,
        severity=4,
        triad="accel",
        estimate=-1.23456789e-300,
        tolerance=9.87654321e300,
        unit="m/s^2",
    ),
    make_event(
        vehicle="v1",
        imu=1,
        t_s=1.0,
        predicate="F9",
        cause=Cause.NON_ORTHOGONALITY,
        severity=3,
        triad="gyro",
        axis="yz",
        estimate=4.2e-4,
        tolerance=1e-4,
    ),
    make_event(
        vehicle="v1",
        imu=0,
        t_s=1.0,
        predicate="temperature",
        cause=StreamCause.TEMPERATURE_RANGE,
        severity=5,
        unit="weird-unit-xyz",
        estimate=-40.25,
        tolerance=-1.0e-200,
    ),
    make_event(
        vehicle="v1",
        imu=3,
        t_s=1.0,
        predicate="temperature",
        cause=StreamCause.TEMPERATURE_RANGE,
        severity=4,
        triad="accel",
        estimate=52.345,
        nominal=20.0,
        tolerance=40.0,
        unit="degC",
    ),
]


@pytest.mark.parametrize("event", ALL_EVENTS, ids=lambda e: e.predicate.value)
def test_alert_text_fits_and_keeps_instance_sensor_cause_number(event):
    text = alert_text(event)
    assert len(text) <= STATUSTEXT_MAX_CHARS
    assert text.startswith(f"IMU{event.imu} ")
    if event.triad is not None:
        assert {"accel": " ACC", "gyro": " GYR"}[event.triad.value] in text
    assert _CAUSE_WORD[event.cause] in text
    # The estimate survives to at least one significant digit (relative error < 50 %).
    number = float(
        re.search(r" (-?\d[\d.]*(?:e[-+]\d+)?)", text[len(f"IMU{event.imu}") :]).group(1)
    )
    assert number == pytest.approx(event.estimate, rel=0.5)


_CAUSE_WORD = {
    Cause.SCALE_FACTOR: "scale",
    Cause.NON_ORTHOGONALITY: "nonorth",
    StreamCause.OUT_OF_SHELL: "off-sphere",
    StreamCause.NO_DATA: "no data",
    StreamCause.STUCK_VALUE: "stuck",
    StreamCause.DISAGREEMENT: "disagree",
    StreamCause.TEMPERATURE_RANGE: "temp range",
}


def test_rate_limiter_keeps_the_ground_station_quiet():
    limiter = AlertRateLimiter(min_interval_s=10.0, max_per_s=1.0)
    e = _finding_event()
    other = make_event(
        vehicle="v1", imu=0, t_s=1.0, predicate="timeout", cause="no_data", severity=2
    )
    decisions = [
        limiter.allow(e, t) for t in np.arange(0.0, 30.0, 0.5)
    ]  # the same alert every 0.5 s for 30 s
    assert sum(decisions) == 3 and decisions[0] and decisions[20] and decisions[40]  # t = 0, 10, 20
    assert limiter.allow(other, 30.0) is True and limiter.allow(other, 30.1) is False
    assert limiter.suppressed == 58


# ------------------------------------------------------------------ IMU in


def _peer(port):
    """A simulated autopilot sending to our UDP port."""
    return use_mavlink2(
        mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    )


def _read(link, n_samples):
    """Batches read by the link until they hold ``n_samples`` samples (or WAIT_S passes)."""
    got, deadline = [], time.monotonic() + WAIT_S
    while sum(b.n_samples for b in got) < n_samples and time.monotonic() < deadline:
        got += link.read(0.1, gather_s=0.2)
    return got


ACC = np.array([0.12, -0.34, -9.79])
GYR = np.array([0.0123, -0.0045, 0.0067])

CASES = {
    # kind: (imu id in message, expected imu index, accel/gyro quantum, temperature quantum)
    ImuMessage.RAW_IMU: (1, 1, (STANDARD_GRAVITY_MPS2 * 1e-3, 1e-3), 0.01),
    ImuMessage.SCALED_IMU: (0, 0, (STANDARD_GRAVITY_MPS2 * 1e-3, 1e-3), 0.01),
    ImuMessage.SCALED_IMU2: (0, 1, (STANDARD_GRAVITY_MPS2 * 1e-3, 1e-3), 0.01),
    ImuMessage.SCALED_IMU3: (0, 2, (STANDARD_GRAVITY_MPS2 * 1e-3, 1e-3), 0.01),
    ImuMessage.HIGHRES_IMU: (2, 2, (1e-7, 1e-7), 1e-6),
}


@pytest.mark.parametrize("kind", list(CASES), ids=lambda k: k.value)
def test_imu_messages_from_a_peer_become_si_batches(kind):
    msg_id, imu, (qa, qg), qt = CASES[kind]
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        for k, t in enumerate((12.5, 12.51)):
            peer.mav.send(
                imu_message(
                    kind, t_s=t, accel_mps2=ACC * (1 + k), gyro_rps=GYR, temp_c=35.25, imu_id=msg_id
                )
            )
        batches = _read(link, 2)
        peer.close()
    # Both messages arrive within the gathering time: one batch of two samples.
    assert [(b.vehicle, b.imu, b.seq, b.n_samples) for b in batches] == [("v1", imu, 0, 2)]
    b = batches[0]
    for k in range(2):
        # Integer messages are quantized to the field's count (half a count at most); floats to float32.
        np.testing.assert_allclose(
            b.accel_mps2[k], ACC * (1 + k), atol=qa / 2 + 1e-6 * abs(ACC).max(), rtol=0
        )
        np.testing.assert_allclose(b.gyro_rps[k], GYR, atol=qg / 2 + 1e-7, rtol=0)
    np.testing.assert_allclose(b.temp_c, [35.25, 35.25], atol=qt)
    np.testing.assert_allclose(b.t_s, [12.5, 12.51], atol=1e-6, rtol=0)


def test_a_read_ends_at_its_gather_time_even_with_more_waiting(monkeypatch):
    """A reader behind its input hands the backlog over in several reads: one read stops once its
    gather time has passed, not when the socket is empty, and the next read goes on from there.

    A fake clock a second later at every look stands for a parse slower than the gather time."""
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        times = [1.0 + 0.01 * k for k in range(4)]
        for t in times:
            peer.mav.send(imu_message(ImuMessage.HIGHRES_IMU, t_s=t, accel_mps2=ACC, gyro_rps=GYR))
        # Loopback UDP is in the receive buffer when send returns: all four datagrams wait.
        assert select.select([link.connection.port], [], [], WAIT_S)[0]
        clock = iter(range(1_000_000))
        monkeypatch.setattr(mavlink_adapter, "time", SimpleNamespace(monotonic=lambda: next(clock)))
        reads = [link.read(0.1, gather_s=0.5) for _ in times]
        peer.close()
    assert [[b.n_samples for b in r] for r in reads] == [[1]] * 4
    np.testing.assert_allclose([b.t_s[0] for r in reads for b in r], times, atol=1e-6, rtol=0)


@needs_udp_drops
def test_datagrams_the_kernel_drops_are_counted():
    """A reader behind its input, with the least receive buffer: the kernel drops most of 300
    datagrams, and every one sent is either read or counted as dropped."""
    sent = 300
    settings = MavlinkSettings.from_dict(
        {"device": "udpin:127.0.0.1:0", "vehicle": "v1", "udp_rcvbuf_bytes": UDP_RCVBUF_MIN_BYTES}
    )
    with MavlinkLink(settings) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        for k in range(sent):
            peer.mav.send(
                imu_message(
                    ImuMessage.HIGHRES_IMU, t_s=1.0 + 1e-3 * k, accel_mps2=ACC, gyro_rps=GYR
                )
            )
        # Loopback UDP is in the receive buffer, or dropped, when send returns.
        got = []
        while batches := link.read(0.1):
            got += batches
        peer.close()
    read = sum(b.n_samples for b in got)
    assert 0 < read < sent // 10
    assert link.counters.messages == read
    assert link.counters.dropped_kernel == sent - read


@needs_rmem_max
def test_the_receive_buffer_granted_is_what_was_asked_up_to_rmem_max():
    rmem_max = int(RMEM_MAX.read_text())
    granted = []
    for asked in (UDP_RCVBUF_MIN_BYTES, rmem_max + 4096):
        settings = MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1", udp_rcvbuf_bytes=asked)
        with MavlinkLink(settings) as link:
            granted.append(link.udp_rcvbuf_granted_bytes)
    assert granted == [UDP_RCVBUF_MIN_BYTES, rmem_max]


def test_raw_imu_scale_is_configurable_and_zero_temperature_means_none():
    scale = ImuScale(
        accel_mps2_per_lsb=STANDARD_GRAVITY_MPS2 / 2048.0,
        gyro_rps_per_lsb=np.radians(1 / 16.4),
        temp_c_per_lsb=0.5,
    )
    msg = mavlink2.MAVLink_raw_imu_message(
        time_usec=2_000_000,
        xacc=0,
        yacc=0,
        zacc=-2048,
        xgyro=164,
        ygyro=0,
        zgyro=0,
        xmag=0,
        ymag=0,
        zmag=0,
        id=0,
        temperature=0,
    )
    s = decode_imu_message(msg, raw_scale=scale)
    assert s.accel_mps2 == (0.0, 0.0, -STANDARD_GRAVITY_MPS2) and s.gyro_rps[0] == pytest.approx(
        np.radians(10.0)
    )
    assert s.temp_c is None and s.t_s == 2.0
    assert decode_imu_message(mavlink2.MAVLink_heartbeat_message(0, 0, 0, 0, 0, 3)) is None


def test_highres_messages_that_do_not_flag_their_accel_and_gyro_as_updated_are_refused_and_counted():
    """A message whose fields_updated leaves out an accelerometer or gyro field holds no new
    measurement there (a held or zeroed value): read as a sample, one in twenty zeroed accelerometers
    kept the detector from ever seeing the unit at rest."""
    settings = MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v")
    counters = LinkCounters()
    batcher = ImuBatcher(settings, counters)
    msgs = [
        imu_message(
            ImuMessage.HIGHRES_IMU,
            t_s=0.01 * k,
            accel_mps2=(0.0, 0.0, -9.8),
            gyro_rps=(0.0, 0.0, 0.0),
        )
        for k in range(20)
    ]
    for k, bits in ((3, 0b111000), (7, 0b000111), (11, 0b111110)):
        msgs[k].fields_updated = bits
        msgs[k].xacc = msgs[k].xgyro = 0.0
    batcher.add(msgs)
    (batch,) = batcher.take()
    assert batch.n_samples == 17
    np.testing.assert_allclose(batch.t_s, [0.01 * k for k in range(20) if k not in (3, 7, 11)])
    assert counters.rejected == {"fields_not_updated": 3}


def _packed(system: int, times, kind=ImuMessage.HIGHRES_IMU) -> list[bytes]:
    """IMU messages of MAVLink system ``system`` (component 1), one at each of ``times``."""
    mav = mavlink2.MAVLink(None, srcSystem=system, srcComponent=1)
    return [imu_message(kind, t_s=t, accel_mps2=ACC, gyro_rps=GYR).pack(mav) for t in times]


def test_without_autopilot_system_the_first_imu_system_heard_is_the_only_one_read():
    """A ground station's HEARTBEAT, then two systems' IMU messages interleaved (system 3 first) and
    one of a third: only system 3's samples are in the batches, the others are counted by system.
    Merged, the two streams would be one IMU's (each hiding the other's faults)."""
    heartbeat = heartbeat_message().pack(mavlink2.MAVLink(None, srcSystem=255, srcComponent=190))
    first, second = _packed(3, np.arange(10) * 0.01), _packed(42, np.arange(10) * 0.01 + 0.0025)
    packets = [heartbeat, *(p for pair in zip(first, second, strict=True) for p in pair)]
    packets.append(_packed(9, [0.2], ImuMessage.SCALED_IMU)[0])
    counters = LinkCounters()
    batcher = ImuBatcher(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1"), counters)
    parser = mavlink2.MAVLink(None)
    for p in packets:
        batcher.add(parser.parse_buffer(p))
    (batch,) = batcher.take()
    np.testing.assert_allclose(batch.t_s, np.arange(10) * 0.01)
    assert counters.imu_system == 3 and counters.messages == 21
    assert counters.ignored_system == 11 and counters.ignored_systems == {42: 10, 9: 1}
    assert counters.imu_samples == {"HIGHRES_IMU": 10}


def test_a_system_handed_over_is_read_and_a_configured_one_comes_first():
    """A new reader of a link (a reader process restarted) is handed the system read before: that
    one's messages are read even when another's come first; ``autopilot_system`` overrides both."""
    packets = [*_packed(42, [0.0]), *_packed(3, [0.01]), *_packed(1, [0.02])]
    parser = mavlink2.MAVLink(None)
    messages = [m for p in packets for m in parser.parse_buffer(p)]
    for configured, handed, read in ((None, 3, 3), (1, 3, 1), (None, None, 42)):
        counters = LinkCounters()
        settings = MavlinkSettings(
            device="udpin:127.0.0.1:0", vehicle="v1", autopilot_system=configured
        )
        batcher = ImuBatcher(settings, counters, imu_system=handed)
        batcher.add(messages)
        (batch,) = batcher.take()
        assert list(batch.t_s) == [{42: 0.0, 3: 0.01, 1: 0.02}[read]]
        assert counters.imu_system == read and counters.ignored_system == 2


def test_settings_from_dict_and_message_selection():
    settings = MavlinkSettings.from_dict(
        {
            "device": "udpin:127.0.0.1:0",
            "vehicle": "v1",
            "messages": ["SCALED_IMU2"],
            "imu_index": {"SCALED_IMU2": 4},
            "signing_key_hex": KEY.hex(),
            "raw_scale": {
                "accel_mps2_per_lsb": 0.001,
                "gyro_rps_per_lsb": 0.001,
                "temp_c_per_lsb": 0.01,
            },
            "autopilot_system": 1,
        }
    )
    assert settings.signing_key == KEY and settings.messages == (ImuMessage.SCALED_IMU2,)
    with MavlinkLink(settings) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        peer.setup_signing(KEY, sign_outgoing=True)
        peer.mav.send(
            imu_message(ImuMessage.RAW_IMU, t_s=1.0, accel_mps2=ACC, gyro_rps=GYR)
        )  # not selected
        peer.mav.send(imu_message(ImuMessage.SCALED_IMU2, t_s=1.0, accel_mps2=ACC, gyro_rps=GYR))
        other = use_mavlink2(
            mavutil.mavlink_connection(
                f"udpout:127.0.0.1:{link.connection.port.getsockname()[1]}", source_system=9
            )
        )
        other.setup_signing(KEY, sign_outgoing=True)
        other.mav.send(
            imu_message(ImuMessage.SCALED_IMU2, t_s=2.0, accel_mps2=ACC, gyro_rps=GYR)
        )  # another system
        peer.mav.send(imu_message(ImuMessage.SCALED_IMU2, t_s=3.0, accel_mps2=ACC, gyro_rps=GYR))
        got = _read(link, 2)
        peer.close()
        other.close()
    assert {b.imu for b in got} == {4} and [t for b in got for t in b.t_s] == [1.0, 3.0]
    assert link.counters.ignored_system == 1 and link.counters.imu_samples == {"SCALED_IMU2": 2}


@pytest.mark.parametrize(
    "table,match",
    [
        ({"device": "udpin:127.0.0.1:0"}, "vehicle must be"),
        ({"device": "x", "vehicle": "v", "messages": ["ATTITUDE"]}, "known:"),
        ({"device": "x", "vehicle": "v", "signing_key_hex": "zz"}, "64 hexadecimal"),
        ({"device": "x", "vehicle": "v", "signing_key_hex": "00" * 16}, "32 bytes"),
        ({"device": "x", "vehicle": "v", "speed": 3}, "unknown mavlink setting"),
        ({"device": "x", "vehicle": "v", "udp_rcvbuf_bytes": 100}, "udp_rcvbuf_bytes must be"),
        ({"device": "x", "vehicle": "v", "udp_rcvbuf_bytes": "4M"}, "udp_rcvbuf_bytes must be"),
    ],
)
def test_bad_settings(table, match):
    with pytest.raises(ValueError, match=match):
        MavlinkSettings.from_dict(table)


def test_async_source_over_tcp():
    async def run():
        server = use_mavlink2(mavutil.mavlink_connection("tcpin:127.0.0.1:0", source_system=1))
        port = server.listen.getsockname()[1]
        with (
            MavlinkLink(MavlinkSettings(device=f"tcp:127.0.0.1:{port}", vehicle="v2")) as link,
            MavlinkSource(link, poll_s=0.05) as source,
        ):
            server.recv()  # accepts the connection the link made synchronously
            assert server.port is not None
            for k in range(5):
                server.mav.send(
                    imu_message(ImuMessage.HIGHRES_IMU, t_s=k * 0.01, accel_mps2=ACC, gyro_rps=GYR)
                )
            got = [await asyncio.wait_for(source.get(), WAIT_S)]
            while sum(b.n_samples for b in got) < 5:
                got.append(await asyncio.wait_for(source.get(), WAIT_S))
        server.close()
        return got

    got = asyncio.run(run())
    assert [b.seq for b in got] == list(range(len(got))) and {b.vehicle for b in got} == {"v2"}
    np.testing.assert_allclose(np.concatenate([b.t_s for b in got]), np.arange(5) * 0.01)


class ScriptedLink:
    """An ImuLink without a device: each read adds the next rejections (and kernel drops, and IMU
    messages of other systems as ``"system N"``, the link reading system 1) of ``steps`` and
    returns nothing (no GNSS either)."""

    def __init__(self, steps: list[dict[str, int]], **settings):
        self.settings = MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1", **settings)
        self.counters = LinkCounters(imu_system=1)
        self._steps = list(steps)
        self.done = threading.Event()

    def read(self, timeout_s: float, *, gather_s: float = 0.0) -> list:
        if self._steps:
            for reason, n in self._steps.pop(0).items():
                if reason == "dropped_kernel":
                    self.counters.dropped_kernel += n
                elif reason.startswith("system "):
                    system = int(reason.split()[1])
                    ignored = self.counters.ignored_systems
                    ignored[system] = ignored.get(system, 0) + n
                else:
                    self.counters.reject(reason, n)
        else:
            self.done.set()
            time.sleep(timeout_s)
        return []

    def take_gnss(self) -> None:
        return None


def warnings_while_read(link: ScriptedLink, caplog) -> list[str]:
    """The MAVLink log's warnings while a :class:`MavlinkSource` reads ``link`` through its steps."""

    async def run() -> None:
        with MavlinkSource(link, poll_s=0.01):  # type: ignore[arg-type]
            assert await asyncio.to_thread(link.done.wait, WAIT_S)

    with caplog.at_level("WARNING", logger="ins_health.mavlink"):
        asyncio.run(run())
    return [r.getMessage() for r in caplog.records]


def test_a_new_kind_of_rejection_is_logged_at_once_more_of_the_same_once_a_period(caplog):
    """Garbage, then a broken CRC a read later, then more of both: two log lines within the period."""
    link = ScriptedLink([{"garbage_bytes": 7}, {"bad_crc": 1}, {"bad_crc": 1, "garbage_bytes": 7}])
    said = [line for line in warnings_while_read(link, caplog) if "rejected" in line]
    assert len(said) == 2, said
    assert "7 garbage_bytes" in said[0] and "1 bad_crc" in said[1] and "garbage" not in said[1]


def test_kernel_drops_are_logged_at_once_then_once_a_period(caplog):
    """Drops seen on two reads within the period: one line, at the first."""
    link = ScriptedLink([{"dropped_kernel": 40}, {"dropped_kernel": 5}])
    said = [line for line in warnings_while_read(link, caplog) if "kernel dropped" in line]
    assert len(said) == 1 and "dropped 40 datagrams (40 in all)" in said[0], said


def test_each_other_system_is_logged_once_with_the_one_read_and_how_to_choose(caplog):
    """IMU messages of system 42, then of 42 and 7, then of 42 again: one line for each system, at once."""
    link = ScriptedLink([{"system 42": 5}, {"system 42": 5, "system 7": 1}, {"system 42": 3}])
    said = [line for line in warnings_while_read(link, caplog) if "system" in line]
    assert len(said) == 2, said
    for line, system in zip(said, (42, 7), strict=True):
        assert f"IMU messages of system {system} ignored" in line
        assert "come from system 1, the first heard" in line
        assert "[mavlink] autopilot_system" in line and "rejected.other_system" in line


def test_other_systems_are_not_logged_when_autopilot_system_is_configured(caplog):
    """Configured: the other systems are counted as before (other_system), with no log line."""
    link = ScriptedLink([{"system 42": 5}, {"system 7": 1}], autopilot_system=1)
    assert not [line for line in warnings_while_read(link, caplog) if "system" in line]


def test_no_pymavlink_global_state_is_touched():
    before = (os.environ.get("MAVLINK20"), mavutil.mavlink, mavutil.current_dialect)
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        peer.mav.send(imu_message(ImuMessage.RAW_IMU, t_s=1.0, accel_mps2=ACC, gyro_rps=GYR))
        assert _read(link, 1)  # a MAVLink 2 packet was parsed ...
        peer.close()
    assert (
        os.environ.get("MAVLINK20"),
        mavutil.mavlink,
        mavutil.current_dialect,
    ) == before  # ... without the global switch
    assert link.connection.port.fileno() == -1  # the context closed the socket


def test_serial_link_reads_imu_and_sends_alerts_through_a_pseudo_terminal():
    """A serial device as the service opens it (pyserial under pymavlink), the autopilot on the other end of a pty."""
    master, slave = os.openpty()
    try:
        with MavlinkLink(
            MavlinkSettings(device=os.ttyname(slave), vehicle="v3", baud=921600)
        ) as link:
            autopilot = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
            for k in range(3):
                os.write(
                    master,
                    imu_message(
                        ImuMessage.SCALED_IMU2, t_s=5.0 + 0.01 * k, accel_mps2=ACC, gyro_rps=GYR
                    ).pack(autopilot),
                )
            got = _read(link, 3)
            link.send_heartbeat()
            event = _finding_event(severity=Severity.ERROR)
            text = link.send_alert(event)
            ground = mavlink2.MAVLink(None)
            received, deadline = [], time.monotonic() + WAIT_S
            while len(received) < 2 and time.monotonic() < deadline:
                if select.select([master], [], [], 0.1)[0]:
                    received += [m for m in ground.parse_buffer(os.read(master, 4096)) or []]
    finally:
        os.close(master)
        os.close(slave)
    assert {(b.vehicle, b.imu) for b in got} == {("v3", 1)}
    assert [b.seq for b in got] == list(range(len(got)))
    np.testing.assert_allclose(np.concatenate([b.t_s for b in got]), [5.0, 5.01, 5.02], rtol=1e-12)
    np.testing.assert_allclose(
        got[-1].accel_mps2[-1], ACC, atol=STANDARD_GRAVITY_MPS2 * 1e-3 / 2 + 1e-6, rtol=0
    )
    assert [m.get_type() for m in received] == ["HEARTBEAT", "STATUSTEXT"]
    heartbeat, alert = received
    assert (
        heartbeat.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
        and heartbeat.get_srcComponent() == mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    )
    assert alert.severity == int(Severity.ERROR) and alert.text == text


# ------------------------------------------------------------------ batches and refused bytes


@settings(max_examples=60, deadline=None)
@given(st.lists(imu_messages, min_size=1, max_size=12))
def test_batches_hold_the_per_message_values_bit_for_bit(messages):
    """The link's batches hold, per IMU and message type in arrival order, exactly what
    decode_imu_message gives for each message (NaN included); an IMU index beyond 255 is counted."""
    parser = mavlink2.MAVLink(None)
    parsed = parser.parse_buffer(b"".join(m.pack(_MAV) for m in messages))
    counters = LinkCounters()
    batcher = ImuBatcher(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1"), counters)
    batcher.add(parsed)
    batches = batcher.take()
    by_kind: dict[str, dict[int, list]] = {}
    not_updated = 0
    for m in parsed:
        # The batcher orders message types by their first message, refused or not.
        imus = by_kind.setdefault(m.get_type(), {})
        if not highres_triads_updated(m):
            not_updated += 1
            continue
        s = decode_imu_message(m)
        imus.setdefault(s.imu, []).append(s)
    expected = [(imu, v) for imus in by_kind.values() for imu, v in imus.items() if imu <= 255]
    too_high = sum(len(v) for imus in by_kind.values() for imu, v in imus.items() if imu > 255)
    want_rejected = {"bad_value": too_high, "fields_not_updated": not_updated}
    assert counters.rejected == {k: n for k, n in want_rejected.items() if n}
    assert counters.messages == len(messages)
    assert [b.imu for b in batches] == [imu for imu, _ in expected]
    for k, (b, (_, want)) in enumerate(zip(batches, expected, strict=True)):
        # seq counts the batches of an IMU (two message types may feed one).
        assert b.seq == [c.imu for c in batches[:k]].count(b.imu) and b.vehicle == "v1"
        bits = lambda a: np.asarray(a, np.float64).view(np.uint64)  # noqa: E731
        assert np.array_equal(bits(b.t_s), bits([s.t_s for s in want]))
        assert np.array_equal(bits(b.accel_mps2), bits([s.accel_mps2 for s in want]))
        assert np.array_equal(bits(b.gyro_rps), bits([s.gyro_rps for s in want]))
        temps = [s.temp_c for s in want]
        if None in temps:
            assert b.temp_c is None
        else:
            assert np.array_equal(bits(b.temp_c), bits(temps))


def test_refused_bytes_are_counted_by_reason_and_cost_no_good_packet():
    """Datagrams of garbage, of a packet with a broken CRC and of a packet cut short, between good ones:
    every good sample is read and each refusal is counted (garbage in bytes)."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    good = [
        imu_message(ImuMessage.SCALED_IMU, t_s=1.0 + 0.01 * k, accel_mps2=ACC, gyro_rps=GYR).pack(
            mav
        )
        for k in range(4)
    ]
    broken = bytearray(good[0])
    broken[-1] ^= 0xFF
    garbage = b"\x00\x11garbage\x7f" * 3
    cut = good[1][:15]
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        for datagram in (good[0], garbage, good[1], bytes(broken), cut, good[2], good[3]):
            peer.write(datagram)
        got = _read(link, 4)
        peer.close()
    assert [t for b in got for t in b.t_s] == pytest.approx([1.0, 1.01, 1.02, 1.03])
    assert link.counters.rejected == {"garbage_bytes": len(garbage) + len(cut), "bad_crc": 1}


@pytest.mark.parametrize(
    "junk",
    [b"\xfd", b"\xfe", b"\x00\xfd\x01", "cut", "broken", b"\xfe\x39\x00\x01\x01\x0f"],
    ids=[
        "stray-v2-start",
        "stray-v1-start",
        "junk-around-a-start",
        "cut-packet",
        "length-hit",
        "unknown-message-header",
    ],
)
def test_junk_at_the_start_of_a_datagram_costs_no_good_packet_after_it(junk):
    """pymavlink read the byte after a stray start byte as a length and dropped that many bytes: the
    good packets after it in the datagram were lost, counted only as garbage (or, after the header of
    a message id the dialect does not know, decoded unchecked as that message). The frame is read
    again from the start byte inside it where a whole packet begins, so every good packet after the
    junk is read."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    good = [
        imu_message(ImuMessage.SCALED_IMU, t_s=1.0 + 0.01 * k, accel_mps2=ACC, gyro_rps=GYR).pack(
            mav
        )
        for k in range(12)
    ]
    if junk == "cut":
        junk = good[0][:15]
    elif junk == "broken":  # its length byte hit: the frame reaches into the packets after it
        junk = good[0][:1] + bytes([good[0][1] + 40]) + good[0][2:]
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        peer.write(junk + b"".join(good[1:6]))
        peer.write(b"".join(good[6:9]) + junk + b"".join(good[9:]))
        got = _read(link, 11)
        peer.close()
    assert [t for b in got for t in b.t_s] == pytest.approx([1.0 + 0.01 * k for k in range(1, 12)])
    assert sum(link.counters.rejected.values()) > 0


@pytest.mark.parametrize("accept_unsigned", [False, True])
def test_signing_refuses_unsigned_and_wrongly_signed_imu_messages(accept_unsigned):
    """With a key, an IMU message signed with it is read; one signed with another key or unsigned is
    refused and counted (unless accept_unsigned); a HEARTBEAT may come unsigned."""
    settings = MavlinkSettings(
        device="udpin:127.0.0.1:0", vehicle="v1", signing_key=KEY, accept_unsigned=accept_unsigned
    )
    with MavlinkLink(settings) as link:
        port = link.connection.port.getsockname()[1]
        senders = [_peer(port) for _ in range(3)]
        senders[0].setup_signing(KEY, sign_outgoing=True, link_id=1)
        senders[1].setup_signing(bytes(reversed(KEY)), sign_outgoing=True, link_id=2)
        for k, peer in enumerate(senders):
            peer.mav.send(
                imu_message(ImuMessage.SCALED_IMU, t_s=1.0 + k, accel_mps2=ACC, gyro_rps=GYR)
            )
        senders[2].mav.send(mavlink2.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3))
        got = _read(link, 3 if accept_unsigned else 1)
        time.sleep(0.2)
        got += link.read(0.1)
        for peer in senders:
            peer.close()
    times = [t for b in got for t in b.t_s]
    if accept_unsigned:
        assert times == [1.0, 2.0, 3.0] and link.counters.rejected == {}
    else:
        assert times == [1.0]
        assert link.counters.rejected == {"bad_signature": 1, "unsigned": 1}


def test_a_forged_packet_does_not_move_the_replay_window_of_a_genuine_stream():
    """A packet on the autopilot's stream (same link id, system, component) signed with another key and
    stamped a day ahead is refused, and the autopilot's next messages are still read (pymavlink alone
    would have taken the forged time stamp as the stream's and refused them as old)."""
    with MavlinkLink(
        MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1", signing_key=KEY)
    ) as link:
        port = link.connection.port.getsockname()[1]
        autopilot, forger = _peer(port), _peer(port)
        autopilot.setup_signing(KEY, sign_outgoing=True, link_id=1)
        ahead = autopilot.mav.signing.timestamp + 86_400 * 100_000
        forger.setup_signing(bytes(reversed(KEY)), link_id=1, initial_timestamp=ahead)
        for k, peer in enumerate((autopilot, forger, autopilot, autopilot)):
            peer.mav.send(
                imu_message(ImuMessage.SCALED_IMU, t_s=1.0 + k, accel_mps2=ACC, gyro_rps=GYR)
            )
        got = _read(link, 3)
        autopilot.close()
        forger.close()
    assert [t for b in got for t in b.t_s] == [1.0, 3.0, 4.0]
    assert link.counters.rejected == {"bad_signature": 1}


def test_a_datagram_of_start_bytes_is_read_again_only_a_bounded_number_of_times():
    """Each start byte tried inside a refused frame is one more frame sliced and checked: a datagram
    of 65,000 start bytes was 64,723 frames (0.4 s of the reader) instead of 233 when every one was
    tried. At most REREADS_MAX (a handful) more than pymavlink's own count, and the good packet of
    the next datagram is read."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    good = imu_message(ImuMessage.SCALED_IMU, t_s=1.0, accel_mps2=ACC, gyro_rps=GYR).pack(mav)
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        peer.write(b"\xfd" * 65_000)
        peer.write(good)
        got = _read(link, 1)
        peer.close()
    assert [t for b in got for t in b.t_s] == pytest.approx([1.0])
    frames = 65_000 // (253 + mavlink2.HEADER_LEN_V2 + 2)
    assert 0.9 * frames < link.counters.rejected["malformed"] <= frames + REREADS_MAX < 1.2 * frames


def test_packets_signed_with_the_key_but_stale_are_told_apart_from_forged_ones():
    """Refused either way, as pymavlink's replay rule says; but a packet signed with the key and refused
    for its time stamp (a replay, one stamped before the stream's window, a stream locked out after a
    packet stamped a day ahead) is counted as signing_stale, and a forged one is not. Bringing the
    window back after such a jump let recorded packets be replayed (a reception gap, or packets
    accepted before a clock went back), so the stream stays refused and the count says why."""
    with MavlinkLink(
        MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1", signing_key=KEY)
    ) as link:
        port = link.connection.port.getsockname()[1]
        autopilot, ahead, behind, forger, old_forger = (_peer(port) for _ in range(5))
        autopilot.setup_signing(KEY, sign_outgoing=True, link_id=1)
        now = autopilot.mav.signing.timestamp
        ahead.setup_signing(KEY, link_id=1, initial_timestamp=now + 86_400 * 100_000)
        behind.setup_signing(KEY, link_id=1, initial_timestamp=now - 3_600 * 100_000)
        forger.setup_signing(bytes(reversed(KEY)), link_id=1, initial_timestamp=now + 100)
        old_forger.setup_signing(bytes(reversed(KEY)), link_id=1, initial_timestamp=now - 100)

        def packet(peer, t_s):
            msg = imu_message(ImuMessage.SCALED_IMU, t_s=t_s, accel_mps2=ACC, gyro_rps=GYR)
            return msg.pack(peer.mav)

        read_once = packet(autopilot, 1.0)
        forged_old = packet(old_forger, 3.5)
        sent = [read_once, read_once, forged_old, packet(ahead, 2.0), packet(behind, 3.0)]
        sent += [packet(forger, 4.0), packet(autopilot, 5.0)]
        for datagram in sent:
            autopilot.write(datagram)
        got = _read(link, 2)
        time.sleep(0.2)
        got += link.read(0.1)
        for peer in (autopilot, ahead, behind, forger, old_forger):
            peer.close()
    assert [t for b in got for t in b.t_s] == [1.0, 2.0]
    assert link.counters.rejected == {"bad_signature": 5}
    # The replay, the packet from before the window and the locked-out stream's next packet.
    assert link.counters.signing_stale == 3


def test_a_packet_hit_by_a_bit_error_costs_only_itself():
    """A packet whose payload was damaged so that it holds a start byte and the header of a message the
    dialect does not know (159): read again from that start byte, pymavlink decoded the unknown id
    without a CRC and its length swallowed the good packets after it. The frame is read again only
    where a whole packet of the dialect decodes: here nowhere, so only the damaged packet is lost."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = [
        bytearray(
            imu_message(
                ImuMessage.HIGHRES_IMU, t_s=1.0 + 0.01 * k, accel_mps2=ACC, gyro_rps=GYR
            ).pack(mav)
        )
        for k in range(5)
    ]
    assert 159 not in mavlink2.mavlink_map
    packets[0][20:26] = bytes([mavlink2.PROTOCOL_MARKER_V1, 96, 0, 1, 1, 159])
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        peer.write(b"".join(bytes(p) for p in packets))
        got = _read(link, 4)
        peer.close()
    assert [t for b in got for t in b.t_s] == pytest.approx([1.01, 1.02, 1.03, 1.04])
    assert link.counters.rejected == {"bad_crc": 1}


def test_a_packet_carried_in_another_dialects_message_stays_its_payload():
    """A MAVLink 2 message of an id this dialect lacks (60000) holding a HIGHRES_IMU packet in its
    payload: pymavlink cannot check it, and it is read again only for a packet reaching past its end;
    the one inside is payload, not a sample. The packet after it is read."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    inner = imu_message(ImuMessage.HIGHRES_IMU, t_s=1234.5, accel_mps2=ACC, gyro_rps=GYR).pack(mav)
    payload = bytes(8) + inner + bytes(8)
    assert 60000 not in mavlink2.mavlink_map
    header = bytes([mavlink2.PROTOCOL_MARKER_V2, len(payload), 0, 0, 7, 1, 1])
    carrier = header + (60000).to_bytes(3, "little") + payload + b"\x00\x00"
    later = imu_message(ImuMessage.HIGHRES_IMU, t_s=2000.0, accel_mps2=ACC, gyro_rps=GYR).pack(mav)
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        peer.write(carrier + later)
        got = _read(link, 1)
        time.sleep(0.2)
        got += link.read(0.1)
        peer.close()
    assert [t for b in got for t in b.t_s] == [2000.0]
    assert link.counters.rejected == {}


def test_gps_raw_int_of_the_imus_system_is_kept_signed_others_counted():
    """A link read in the service's thread (``reader = "thread"``) with a signing key keeps the
    GPS_RAW_INT fields of the system its IMU messages come from, signed; one before any IMU
    message, one of another system and an unsigned one are counted, not kept."""
    settings = MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1", signing_key=KEY)
    (packed,) = gps_raw_int_messages([2.0], [[3.0, 4.0, 0.0]], [100.0])
    gps = mavlink2.MAVLink(None).decode(bytearray(packed))  # each peer packs it as its own
    with MavlinkLink(settings) as link:
        port = link.connection.port.getsockname()[1]
        autopilot, unsigned = _peer(port), _peer(port)
        other = use_mavlink2(
            mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=2)
        )
        for peer, link_id in ((autopilot, 1), (other, 2)):
            peer.setup_signing(KEY, sign_outgoing=True, link_id=link_id)
        autopilot.mav.send(gps)  # before any IMU message
        autopilot.mav.send(
            imu_message(ImuMessage.SCALED_IMU, t_s=1.0, accel_mps2=ACC, gyro_rps=GYR)
        )
        _read(link, 1)
        for peer in (autopilot, other, unsigned):
            peer.mav.send(gps)
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline and (
            link.counters.gnss_messages < 3 or "unsigned" not in link.counters.rejected
        ):
            link.read(0.1)
        rows = link.take_gnss()
        for peer in (autopilot, other, unsigned):
            peer.close()
    np.testing.assert_array_equal(rows, [[2e6, 3, 500, 3687, 100e3]])
    assert link.counters.gnss_messages == 3  # the unsigned one is pymavlink's refusal
    assert link.counters.rejected == {"gnss_other_system": 2, "unsigned": 1}
