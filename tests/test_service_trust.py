"""Who and what the daemon trusts, against the real daemon and router processes (issue 29): whose
acknowledgements count, which clocks its cross-IMU check can compare, which source owns a
vehicle's stream, which configuration values it takes."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
import zenoh
from pymavlink import mavutil
from service_support import (
    batches_of,
    disagreeing_pair,
    free_udp_port,
    mavlink_packets,
    run_fleet,
    wait_subscribed,
    wait_until,
)
from test_service_faults import (
    ROOT,
    ServiceProcess,
    ground_and_vehicle,
    offline_fleet,
    publish_blocking,
    put_store,
    unit,
    write_config,
)
from test_service_hostile import to_the_fault

from protocols.events import Predicate
from protocols.mavlink_adapter import ImuMessage
from protocols.zenoh_adapter import EventReceiver, FramePublisher, frame_key
from service.config import ServiceConfig

pytestmark = pytest.mark.network


def test_only_the_ground_stations_of_ack_from_acknowledge(tmp_path):
    """``[zenoh] ack_from = ["gs-1"]``: a peer answering every acknowledgement query under another
    name (it took the event) does not make it delivered: its answers are refused, counted on the
    status topic and logged, and the event is retried until gs-1 comes and takes it, once."""
    v = "uav-t"
    frames = to_the_fault(v, batch_samples=100)
    want = [e.event_id for e in run_fleet(offline_fleet(), frames, finish=False)]
    assert len(want) == 1
    passports = put_store(tmp_path, [(v, 0)])
    with ground_and_vehicle(tmp_path, passports) as (config, ground, vehicle, status):
        config.write_text(config.read_text().replace("[zenoh]\n", '[zenoh]\nack_from = ["gs-1"]\n'))
        intruder, station = [], []
        daemon = ServiceProcess(config)
        try:
            with EventReceiver(ground, lambda e: intruder.append(e.event_id), name="intruder"):
                wait_subscribed(vehicle, frame_key(v, 0))
                publish_blocking(vehicle, frames)
                # Asked again: the first answer did not count.
                wait_until(lambda: status.counter(v, "service.zenoh.acks_refused") >= 2,
                           timeout_s=60, what=lambda: f"refused answers ({status.get(v)})")  # fmt: skip
                assert intruder == want
                with EventReceiver(ground, lambda e: station.append(e.event_id), name="gs-1"):
                    wait_until(
                        lambda: station == want, timeout_s=30, what=lambda: f"gs-1 ({station})"
                    )
        finally:
            code = daemon.terminate()
    assert code == 0, daemon.lines
    assert station == want
    refused = [line for line in daemon.lines if "acknowledgement(s) refused" in line]
    assert refused and "intruder" in refused[0] and "['gs-1']" in refused[0], daemon.lines


UNIX_S = 1.7e9
"""IMU0 of the mixed-clock vehicles stamps Unix time (its samples from 1.7e9 s), IMU1 time since boot."""


def _on_two_clocks(vehicle: str, batch_samples: int, imu1_shift_s=lambda seq: 0.0):
    """The disagreeing pair (IMU1 0.1 g off from 66 s), IMU0 on a Unix clock and IMU1 since boot,
    moved by ``imu1_shift_s(seq)``."""
    return [
        dataclasses.replace(b, t_s=b.t_s + (UNIX_S if b.imu == 0 else imu1_shift_s(b.seq)))
        for b in disagreeing_pair(vehicle, batch_samples=batch_samples)
    ]


def _publish_in_turn(session, frames) -> None:
    pubs = {}
    try:
        for b in frames:
            if (b.vehicle, b.imu) not in pubs:
                pubs[(b.vehicle, b.imu)] = FramePublisher(
                    session, b.vehicle, b.imu, congestion_control=zenoh.CongestionControl.BLOCK
                )
            pubs[(b.vehicle, b.imu)].publish(b)
    finally:
        for pub in pubs.values():
            pub.close()


def test_cross_imu_on_a_unix_and_a_boot_clock_offline_as_on_one_clock():
    """Offline (the fleet as replay runs it), 0.1 s frames taken in turn: aligned, the mixed clocks
    give the events of one clock, the 0.1 g disagreement among them; before, the comparison never
    ran and said nothing."""
    one_clock = run_fleet(
        offline_fleet(), disagreeing_pair("uav-c", batch_samples=20), finish=False
    )
    fleet = offline_fleet()
    mixed = run_fleet(fleet, _on_two_clocks("uav-c", 20), finish=False)
    assert [(e.predicate, e.imu) for e in mixed] == [(e.predicate, e.imu) for e in one_clock]
    assert (Predicate.CROSS_IMU, 1) in [(e.predicate, e.imu) for e in mixed]
    assert fleet.cross_not_running("uav-c", 0) is None


def test_cross_imu_on_mixed_clocks_in_the_daemon(tmp_path):
    """uav-c: IMU0 on Unix time, IMU1 since boot, a steady offset, 0.5 s frames (arrival bounds the
    offset to 0.25 s; the rotations tell it): the disagreement of IMU1 reaches the ground station. uav-d: IMU1's clock drifts 3 s a frame against IMU0's: no comparison, and
    the status and the log say why."""
    steady = _on_two_clocks("uav-c", 100)
    drifting = _on_two_clocks("uav-d", 100, lambda seq: 3.0 * seq)[:40]
    passports = put_store(tmp_path, [])
    with ground_and_vehicle(tmp_path, passports) as (config, ground, vehicle, status):
        got = []
        daemon = ServiceProcess(config)
        try:
            with EventReceiver(ground, lambda e: got.append((e.vehicle, e.predicate, e.imu))):
                wait_subscribed(vehicle, frame_key("uav-d", 0))
                _publish_in_turn(vehicle, drifting)

                def said() -> bool:
                    st = status.get("uav-d")
                    return st is not None and any(
                        "cross-IMU not running: " in imu.detail for imu in st.imus
                    )

                wait_until(
                    said, timeout_s=60, what=lambda: f"the status of uav-d ({status.get('uav-d')})"
                )
                _publish_in_turn(vehicle, steady)
                wait_until(
                    lambda: (
                        {("uav-c", Predicate.CROSS_IMU, 0), ("uav-c", Predicate.CROSS_IMU, 1)}
                        <= set(got)
                    ),
                    timeout_s=120,
                    what=lambda: f"the cross-IMU events of uav-c ({got}; {status.get('uav-c')})",
                )
        finally:
            code = daemon.terminate()
    assert code == 0, daemon.lines
    assert not [g for g in got if g[0] == "uav-d" and g[1] is Predicate.CROSS_IMU]
    off = [
        line
        for line in daemon.lines
        if "uav-d IMU" in line and "cross-IMU check not running" in line
    ]
    assert off and "stamps time on another clock" in off[0], daemon.lines


def test_zenoh_frames_of_the_mavlink_vehicle_are_refused(tmp_path):
    """The daemon reads vehicle mav1's IMU over MAVLink; a local process then publishes healthy frames
    as mav1 on Zenoh (they hid the autopilot's stuck gyro and made a false recovery): refused unread,
    counted as frames.rejected.other_source and logged, none in mav1's stream, while another
    vehicle's Zenoh frames are taken."""
    sc = unit()[2]
    healthy = list(batches_of(sc.session, vehicle="mav1", imu=0, batch_samples=100))[:20]
    other = list(batches_of(sc.session, vehicle="uav-z", imu=0, batch_samples=100))[:5]
    packets = mavlink_packets(sc.session.select(sc.session.t_s < 2.0), ImuMessage.SCALED_IMU)
    port = free_udp_port()
    passports = put_store(tmp_path, [])
    with ground_and_vehicle(tmp_path, passports) as (config, _ground, vehicle, status):
        mavlink = (
            f'[mavlink]\nenabled = true\ndevice = "udpin:127.0.0.1:{port}"\nvehicle = "mav1"\n'
        )
        config.write_text(config.read_text() + mavlink)
        daemon = ServiceProcess(config)
        autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1)
        try:
            for k in range(0, len(packets), 20):
                autopilot.write(b"".join(packets[k : k + 20]))
            wait_until(lambda: status.counter("mav1", "imu0.samples.accepted") == len(packets),
                       timeout_s=60, what=lambda: f"mav1 over MAVLink ({status.get('mav1')})")  # fmt: skip
            wait_subscribed(vehicle, frame_key("uav-z", 0))
            publish_blocking(vehicle, healthy)
            publish_blocking(vehicle, other)
            wait_until(
                lambda: (
                    status.counter("mav1", "frames.rejected.other_source") == len(healthy)
                    and status.counter("uav-z", "imu0.frames.accepted") == len(other)
                ),
                timeout_s=60,
                what=lambda: f"the refusals on the status topic ({status.get('mav1')})",
            )
            assert status.counter("mav1", "imu0.samples.accepted") == len(packets)
            assert status.counter("mav1", "imu0.frames.rejected.other_source") == 0
        finally:
            autopilot.close()
            code = daemon.terminate()
    assert code == 0, daemon.lines
    refused = [line for line in daemon.lines if "other_source" in line]
    assert refused and "vehicle mav1 is fed by another input (MAVLink)" in refused[0], daemon.lines


def test_the_default_mavlink_vehicle_is_no_plausible_fleet_name():
    """It was "mav1": a name a fleet's vehicle could have, and a frame key anyone could publish on."""
    assert ServiceConfig().mavlink.link.vehicle == "mavlink.autopilot"


def test_a_window_beyond_memory_is_refused_at_start_in_one_line(tmp_path):
    """``[validity] error_window_samples = 1000000000000`` passed validation: the daemon said running,
    then every frame failed on a 931 GiB allocation. Now the start refuses it: one line, exit 2."""
    config = write_config(tmp_path, 7447, tmp_path / "passports")
    config.write_text(config.read_text() + "error_window_samples = 1000000000000\n")
    run = subprocess.run(
        [sys.executable, "-m", "service.cli", "run", "--config", str(config)],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2, run.stderr
    assert len(lines) == 1 and "[validity] error_window_samples must be at most 600000" in lines[0]
