"""The MAVLink link read in a child process (protocols.mavlink_process): same batches, counters and
alerts as the in-process link; a child that dies is said once and replaced; it never outlives the service."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from multiprocessing import Pipe
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from service_support import (
    free_udp_port,
    mavlink_packets,
    needs_udp_drops,
    receive_until,
    wait_until,
)

from estimators.conventions import Cause, Triad
from estimators.diagnosis import Finding
from estimators.sim import simulate, static_spec
from protocols import mavlink_process
from protocols.events import Predicate, Severity, StreamCause, event_from_finding, make_event
from protocols.mavlink_adapter import (
    DEFAULT_IMU_INDEX,
    ImuBatcher,
    ImuMessage,
    LinkCounters,
    LinkRejection,
    MavlinkSettings,
    alert_text,
    use_mavlink2,
)
from protocols.mavlink_process import (
    MavlinkProcessLink,
    ReaderProcessEnded,
    ReaderProcessFailed,
)
from protocols.mavlink_settings import UDP_RCVBUF_MIN_BYTES
from service.sinks import TRANSPORT_ERRORS

pytestmark = pytest.mark.network
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def session():
    return simulate(static_spec(duration_s=0.4, rate_hz=1000.0), seed=4).session


@pytest.fixture
def linked():
    """A process link on a fresh UDP port and an autopilot peer sending to it."""
    port = free_udp_port()
    link = MavlinkProcessLink(
        MavlinkSettings(device=f"udpin:127.0.0.1:{port}", vehicle="v1"), gather_s=0.005
    )
    peer = use_mavlink2(
        mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    )
    try:
        yield link, peer
    finally:
        peer.close()
        link.close()


def read_samples(link, n, *, timeout_s=20.0):
    """Batches from ``link`` until they hold ``n`` samples."""
    got = []
    deadline = time.monotonic() + timeout_s
    while sum(b.n_samples for b in got) < n:
        assert time.monotonic() < deadline, f"{sum(b.n_samples for b in got)} of {n} samples read"
        got += link.read(0.1)
    return got


def reading_until(link, done, *, timeout_s=10.0):
    """Read (the child's counters come in with what is read) until ``done()``."""
    deadline = time.monotonic() + timeout_s
    while not done():
        assert time.monotonic() < deadline, f"not done after {timeout_s} s: {link.counters}"
        link.read(0.05)


def send_each(peer, packets):
    """One datagram per packet, as a serial-to-UDP bridge forwards them."""
    for p in packets:
        peer.write(p)


def test_batches_counters_and_alerts_are_the_in_process_links(linked, session):
    link, peer = linked
    packets = {
        kind: mavlink_packets(session, kind, imu_id=2)
        for kind in (ImuMessage.HIGHRES_IMU, ImuMessage.SCALED_IMU2)
    }
    send_each(peer, packets[ImuMessage.HIGHRES_IMU][:200])
    peer.write(b"\x00\x01\x02junk")
    send_each(peer, packets[ImuMessage.SCALED_IMU2][:100])
    batches = read_samples(link, 300)

    # The same bytes through the in-process batcher: the same values to the bit.
    expected = ImuBatcher(link.settings, LinkCounters())
    parser = mavlink2.MAVLink(None)
    for p in [*packets[ImuMessage.HIGHRES_IMU][:200], *packets[ImuMessage.SCALED_IMU2][:100]]:
        expected.add(parser.parse_buffer(p))
    want = {b.imu: b for b in expected.take()}
    for imu, ref in want.items():
        mine = [b for b in batches if b.imu == imu]
        assert [b.seq for b in mine] == list(range(len(mine)))
        for name in ("t_s", "accel_mps2", "gyro_rps"):
            got = np.concatenate([getattr(b, name) for b in mine])
            np.testing.assert_array_equal(got, getattr(ref, name))
        assert all(not b.t_s.flags.writeable for b in mine)
    assert sorted(want) == [1, 2]  # SCALED_IMU2 is IMU 1; HIGHRES_IMU id 2 is IMU 2
    reading_until(link, lambda: link.counters.rejected.get(LinkRejection.GARBAGE_BYTES) == 7)
    assert link.counters.messages == 300
    assert link.counters.imu_samples == {"HIGHRES_IMU": 200, "SCALED_IMU2": 100}

    finding = Finding("F5", Triad.ACCEL, "y", Cause.SCALE_FACTOR, 2.1e-3, 0.0, 1.0e-3, 1.0e-4)
    event = event_from_finding(finding, vehicle="v1", imu=2, t_s=0.2)
    link.send_heartbeat()
    assert link.send_alert(event) == alert_text(event)
    assert link.send_text("x" * 120, Severity.INFO) == 3
    got = receive_until(
        peer,
        ["HEARTBEAT", "STATUSTEXT"],
        lambda ms: len(ms) >= 5,
        timeout_s=10,
        what="the heartbeat, the alert and the long text",
    )
    texts = [m for m in got if m.get_type() == "STATUSTEXT"]
    assert texts[0].text == alert_text(event) and texts[0].severity == event.severity
    assert "".join(m.text for m in texts[1:]) == "x" * 120
    wait_until(
        lambda: (
            (link.counters.alerts_sent, link.counters.heartbeats_sent, link.counters.texts_sent)
            == (1, 1, 3)
        ),
        timeout_s=10,
        what=lambda: f"the sends counted: {link.counters}",
    )


def test_samples_that_make_no_frame_are_counted_once_by_the_service(session):
    """The child sends fields; the service makes the batches, so it counts what makes no frame
    (here an IMU index beyond 255: HIGHRES_IMU id 100 on a base of 200) once, and the rest goes on."""
    port = free_udp_port()
    settings = MavlinkSettings(
        device=f"udpin:127.0.0.1:{port}",
        vehicle="v1",
        imu_index={**DEFAULT_IMU_INDEX, ImuMessage.HIGHRES_IMU: 200},
    )
    peer = use_mavlink2(
        mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    )
    with MavlinkProcessLink(settings, gather_s=0.005) as link:
        try:
            send_each(peer, mavlink_packets(session, ImuMessage.HIGHRES_IMU, imu_id=100)[:30])
            send_each(peer, mavlink_packets(session, ImuMessage.HIGHRES_IMU, imu_id=5)[:40])
            got = read_samples(link, 40)
            reading_until(link, lambda: link.counters.messages == 70)
        finally:
            peer.close()
        assert {b.imu for b in got} == {205}
        assert link.counters.rejected == {"bad_value": 30}
        assert link.counters.imu_samples == {"HIGHRES_IMU": 70}


@needs_udp_drops
def test_datagrams_the_kernel_drops_at_the_childs_socket_reach_the_services_counters(session):
    """The child's socket with the least receive buffer and 2,000 datagrams in a burst, sent faster
    than the child parses: every one is read or counted as dropped, in the service's counters."""
    port = free_udp_port()
    settings = MavlinkSettings(
        device=f"udpin:127.0.0.1:{port}", vehicle="v1", udp_rcvbuf_bytes=UDP_RCVBUF_MIN_BYTES
    )
    peer = use_mavlink2(
        mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    )
    packets = mavlink_packets(session, ImuMessage.HIGHRES_IMU) * 5
    with MavlinkProcessLink(settings, gather_s=0.005) as link:
        try:
            send_each(peer, packets)
            reading_until(
                link,
                lambda: link.counters.messages + link.counters.dropped_kernel == len(packets),
            )
        finally:
            peer.close()
    assert 0 < link.counters.dropped_kernel < len(packets)
    assert link.udp_rcvbuf_granted_bytes == UDP_RCVBUF_MIN_BYTES


def test_a_killed_child_is_said_once_replaced_and_numbering_and_counters_go_on(linked, session):
    link, peer = linked
    packets = mavlink_packets(session, ImuMessage.HIGHRES_IMU)
    send_each(peer, packets[:100])
    before = read_samples(link, 100)
    first = link.pid
    os.kill(first, signal.SIGKILL)
    with pytest.raises(ReaderProcessEnded, match="exit code -9"):
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            link.read(0.1)
    # A sink's transport error: the event stays in the outbox and is retried.
    with pytest.raises(TRANSPORT_ERRORS):
        link.send_heartbeat()
    assert link.read(0.1) == [] and link.restarts == 1 and link.pid not in (None, first)
    send_each(peer, packets[100:250])
    after = read_samples(link, 150)
    assert [b.seq for b in [*before, *after]] == list(range(len(before) + len(after)))
    np.testing.assert_array_equal(
        np.concatenate([b.t_s for b in after]),
        np.round(session.t_s[100:250] * 1e6) * 1e-6,
    )
    assert link.counters.messages == 250
    link.send_heartbeat()
    assert link.counters.heartbeats_sent == 1


def test_the_system_read_is_kept_across_a_child_restart(linked, session):
    """Without autopilot_system the first child reads the first system heard (the peer, system 1);
    a second system interleaved is left out and counted by system in the service's counters. The
    child that replaces a killed one reads system 1 too, though system 42's messages come first."""
    link, peer = linked
    packets = mavlink_packets(session, ImuMessage.HIGHRES_IMU)
    other = mavlink_packets(
        session, ImuMessage.HIGHRES_IMU, mav=mavlink2.MAVLink(None, srcSystem=42)
    )
    send_each(peer, [p for pair in zip(packets[:100], other[:100], strict=True) for p in pair])
    before = read_samples(link, 100)
    reading_until(link, lambda: link.counters.messages == 200)
    expected_t_s = np.round(session.t_s * 1e6) * 1e-6
    np.testing.assert_array_equal(np.concatenate([b.t_s for b in before]), expected_t_s[:100])
    assert link.counters.imu_system == 1 and link.counters.ignored_systems == {42: 100}
    os.kill(link.pid, signal.SIGKILL)
    with pytest.raises(ReaderProcessEnded):
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            link.read(0.1)
    assert link.read(0.1) == [] and link.restarts == 1
    send_each(peer, [*other[100:150], *packets[100:250]])
    after = read_samples(link, 150)
    reading_until(link, lambda: link.counters.messages == 400)
    np.testing.assert_array_equal(np.concatenate([b.t_s for b in after]), expected_t_s[100:250])
    assert link.counters.imu_system == 1 and link.counters.ignored_systems == {42: 150}
    assert link.counters.ignored_system == 150
    assert link.counters.imu_samples == {"HIGHRES_IMU": 250}


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_to_the_group_leaves_the_child_to_the_service_and_close_ends_it(
    linked, session, sig
):
    link, peer = linked
    child = link.pid
    # systemd signals every process of the unit, a closed terminal its process group (SIGHUP, which
    # the service logs and ignores): the child goes on until the service closes it.
    os.kill(child, sig)
    send_each(peer, mavlink_packets(session, ImuMessage.HIGHRES_IMU)[:50])
    read_samples(link, 50)
    assert link.pid == child
    t0 = time.monotonic()
    link.close()
    assert time.monotonic() - t0 < 5.0
    assert not Path(f"/proc/{child}").exists() or _zombie(child)
    assert link.read(0.1) == []


def _zombie(pid):
    return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"


def test_a_device_that_cannot_be_opened_is_one_error_naming_it_and_no_child_is_left():
    children = _children()
    with pytest.raises(ReaderProcessFailed, match=r"/dev/ins-health-no-such-port: SerialException"):
        MavlinkProcessLink(MavlinkSettings(device="/dev/ins-health-no-such-port", vehicle="v1"))
    assert _children() == children


def test_a_child_of_another_pipe_version_is_refused_naming_both(monkeypatch):
    """A reader process from other files than the service's (the package replaced under it, then a
    child started) speaks another pipe version: refused with both said, no child left, not misread."""
    children = _children()
    monkeypatch.setattr(mavlink_process, "PROTOCOL_VERSION", mavlink_process.PROTOCOL_VERSION + 1)
    with pytest.raises(ReaderProcessFailed, match=r"speaks version 2, this service 3"):
        MavlinkProcessLink(MavlinkSettings(device="udpin:127.0.0.1:0", vehicle="v1"))
    assert _children() == children


def _children():
    me = str(os.getpid())
    return {
        p.name
        for p in Path("/proc").iterdir()
        if p.name.isdigit() and (p / "stat").exists() and _field(p, 3) == me and _field(p, 2) != "Z"
    }


def _field(proc_dir, k):
    try:
        return (proc_dir / "stat").read_text().rsplit(")", 1)[1].split()[k - 2]
    except (OSError, IndexError):
        return None


def test_the_child_ends_when_the_service_is_killed(tmp_path):
    port = free_udp_port()
    script = textwrap.dedent(
        f"""
        import sys, time
        from protocols.mavlink_adapter import MavlinkSettings
        from protocols.mavlink_process import MavlinkProcessLink
        link = MavlinkProcessLink(MavlinkSettings(device="udpin:127.0.0.1:{port}", vehicle="v1"))
        print(link.pid, flush=True)
        time.sleep(60)
        """
    )
    service = subprocess.Popen(
        [sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    try:
        assert service.stdout is not None
        child = int(service.stdout.readline())
        service.kill()
        service.wait(10)
        wait_until(
            lambda: not Path(f"/proc/{child}").exists() or _zombie(child),
            timeout_s=10,
            what="the orphaned reader to end",
        )
    finally:
        service.kill()
        service.wait(10)


class _StalledDevice:
    """A device whose first write stalls past the reply bound (a peer that stopped reading) and whose
    next one fails (the link then gone)."""

    def __init__(self):
        self.writes = 0
        self.release = threading.Event()

    def send_alert(self, event):
        self.writes += 1
        if self.writes == 1:
            self.release.wait(10.0)
            return "the first alert"
        raise OSError("the link is gone")


def test_a_reply_that_comes_after_its_call_timed_out_is_not_taken_for_the_next_calls(
    linked, monkeypatch
):
    """An alert whose write stalled past the reply bound is a TimeoutError (retried); its late reply
    must not answer the retry: the retry's write failed, so it is an error, not an alert sent (before:
    the stale 'sent' was its answer, the failed alert was acked and lost, and every later call got the
    answer of the one before)."""
    link, _peer = linked
    monkeypatch.setattr(mavlink_process, "REPLY_TIMEOUT_S", 0.2)
    device = _StalledDevice()
    ours, childs = Pipe()
    link._cmd.close()  # the real child ends; the device's commands are served by a thread here
    link._cmd = ours
    threading.Thread(
        target=mavlink_process._commands, args=(device, childs, threading.Event()), daemon=True
    ).start()
    alert = make_event(vehicle="v1", imu=0, t_s=1.0, predicate=Predicate.TIMEOUT,
                       cause=StreamCause.NO_DATA, severity=Severity.WARNING)  # fmt: skip
    with pytest.raises(TimeoutError):
        link.send_alert(alert)
    device.release.set()
    wait_until(lambda: ours.poll(), timeout_s=10, what="the late reply")
    with pytest.raises(ReaderProcessFailed, match="the link is gone"):
        link.send_alert(alert)
