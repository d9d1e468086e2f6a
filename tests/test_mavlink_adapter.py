"""MAVLink with a real pymavlink peer on 127.0.0.1: IMU messages in SI, HEARTBEAT, STATUSTEXT, signing."""

import asyncio
import os
import re
import select
import time

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from estimators.conventions import STANDARD_GRAVITY_MPS2, Cause, Triad
from estimators.diagnosis import Finding
from protocols.events import Severity, StreamCause, event_from_finding, make_event
from protocols.mavlink_adapter import (
    STATUSTEXT_MAX_CHARS,
    AlertRateLimiter,
    ImuMessage,
    ImuScale,
    MavlinkLink,
    MavlinkSettings,
    MavlinkSource,
    alert_text,
    decode_imu_message,
    imu_message,
    statustext_messages,
    use_mavlink2,
)

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
        batches = [link.recv_batch(WAIT_S) for _ in range(2)]
        peer.close()
    for k, b in enumerate(batches):
        assert (b.vehicle, b.imu, b.seq, b.n_samples) == ("v1", imu, k, 1)
        # Integer messages are quantized to the field's count (half a count at most); floats to float32.
        np.testing.assert_allclose(
            b.accel_mps2[0], ACC * (1 + k), atol=qa / 2 + 1e-6 * abs(ACC).max(), rtol=0
        )
        np.testing.assert_allclose(b.gyro_rps[0], GYR, atol=qg / 2 + 1e-7, rtol=0)
        np.testing.assert_allclose(b.temp_c, [35.25], atol=qt)
    assert batches[0].t_s[0] == pytest.approx(12.5, abs=1e-6) and batches[1].t_s[
        0
    ] == pytest.approx(12.51, abs=1e-6)


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
        other.mav.send(
            imu_message(ImuMessage.SCALED_IMU2, t_s=2.0, accel_mps2=ACC, gyro_rps=GYR)
        )  # another system
        peer.mav.send(imu_message(ImuMessage.SCALED_IMU2, t_s=3.0, accel_mps2=ACC, gyro_rps=GYR))
        got = [link.recv_batch(WAIT_S) for _ in range(3)]
        peer.close()
        other.close()
    assert [(b.imu, b.t_s[0]) if b is not None else None for b in got] == [(4, 1.0), None, (4, 3.0)]
    assert link.counters.ignored_system == 1 and link.counters.imu_samples == {"SCALED_IMU2": 2}


@pytest.mark.parametrize(
    "table,match",
    [
        ({"device": "udpin:127.0.0.1:0"}, "vehicle must be"),
        ({"device": "x", "vehicle": "v", "messages": ["ATTITUDE"]}, "known:"),
        ({"device": "x", "vehicle": "v", "signing_key_hex": "zz"}, "64 hexadecimal"),
        ({"device": "x", "vehicle": "v", "signing_key_hex": "00" * 16}, "32 bytes"),
        ({"device": "x", "vehicle": "v", "speed": 3}, "unknown mavlink setting"),
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
            got = [await asyncio.wait_for(source.get(), WAIT_S) for _ in range(5)]
        server.close()
        return got

    got = asyncio.run(run())
    assert [b.seq for b in got] == [0, 1, 2, 3, 4] and {b.vehicle for b in got} == {"v2"}


def test_no_pymavlink_global_state_is_touched():
    before = (os.environ.get("MAVLINK20"), mavutil.mavlink, mavutil.current_dialect)
    with MavlinkLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1")) as link:
        peer = _peer(link.connection.port.getsockname()[1])
        peer.mav.send(imu_message(ImuMessage.RAW_IMU, t_s=1.0, accel_mps2=ACC, gyro_rps=GYR))
        assert link.recv_batch(WAIT_S) is not None  # a MAVLink 2 packet was parsed ...
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
            got = [link.recv_batch(WAIT_S) for _ in range(3)]
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
    assert [(b.vehicle, b.imu, b.seq) for b in got] == [("v3", 1, 0), ("v3", 1, 1), ("v3", 1, 2)]
    np.testing.assert_allclose(
        got[2].accel_mps2[0], ACC, atol=STANDARD_GRAVITY_MPS2 * 1e-3 / 2 + 1e-6, rtol=0
    )
    assert [m.get_type() for m in received] == ["HEARTBEAT", "STATUSTEXT"]
    heartbeat, alert = received
    assert (
        heartbeat.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
        and heartbeat.get_srcComponent() == mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    )
    assert alert.severity == int(Severity.ERROR) and alert.text == text
