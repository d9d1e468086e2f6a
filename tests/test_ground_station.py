"""A ground station no one here wrote: MAVProxy on 127.0.0.1 receives the daemon's HEARTBEAT and alerts.

The daemon listens on UDP as the shipped configuration does (``udpin``);
MAVProxy (PyPI package MAVProxy, headless) connects to it as the ground
station of a vehicle and forwards what it receives to a plain pymavlink
listener (``--out``), which checks each message. The IMU reaches the daemon
as Zenoh frames of the vehicle the MAVLink link speaks for, so the link
carries only ground-station traffic.
"""

from __future__ import annotations

import functools
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from service_support import (
    ServiceThread,
    batches_of,
    free_udp_port,
    of_type,
    receive_until,
    service_config,
    wait_subscribed,
    zenoh_client_config,
    zenoh_router,
)

from protocols.events import Predicate, Severity, decode_event
from protocols.mavlink_adapter import alert_text
from protocols.zenoh_adapter import FramePublisher, frame_key
from service.demo import demo_passport, demo_scenario
from service.passport_store import PassportStore

pytestmark = pytest.mark.network
MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
VEHICLE = "mav1"


@functools.cache
def unit():
    passport, g = demo_passport()
    sc = demo_scenario()
    # From shortly before landing: the +3 % z scale fault gives F0 (warning), then F6 (error).
    return passport, g, sc.session.select(sc.session.t_s >= sc.landing_s - 0.5)


def test_mavproxy_sees_the_daemons_heartbeat_and_alerts_with_their_severity(tmp_path):
    passport, g, session = unit()
    store = PassportStore(tmp_path / "passports")
    store.put(VEHICLE, 0, passport)
    link_port, out_port = free_udp_port(), free_udp_port()
    with zenoh_router() as zport:
        cfg = service_config(
            tmp_path, port=zport, passport_dir=store.root, site={"gravity_mps2": g},
            validity={"timeout_s": 60.0},
            mavlink={"enabled": True, "device": f"udpin:127.0.0.1:{link_port}", "vehicle": VEHICLE},
        )  # fmt: skip
        listener = mavutil.mavlink_connection(f"udpin:127.0.0.1:{out_port}")
        with ServiceThread(cfg) as svc:
            gcs = subprocess.Popen(
                [
                    str(MAVPROXY),
                    f"--master=udpout:127.0.0.1:{link_port}",
                    f"--out=udpout:127.0.0.1:{out_port}",
                    "--non-interactive",
                    "--no-state",
                    "--default-modules=",
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                cwd=tmp_path,
            )
            try:
                # The daemon answers MAVProxy's heartbeat with its own (then it knows where the GCS is).
                receive_until(
                    listener, ["HEARTBEAT"], lambda m: bool(m), timeout_s=60, what="the daemon's HEARTBEAT through MAVProxy"
                )  # fmt: skip
                with zenoh.open(zenoh_client_config(zport)) as vehicle:
                    wait_subscribed(vehicle, frame_key(VEHICLE, 0))
                    with FramePublisher(
                        vehicle, VEHICLE, 0, congestion_control=zenoh.CongestionControl.BLOCK
                    ) as pub:
                        for batch in batches_of(session, vehicle=VEHICLE, imu=0, batch_samples=100):
                            pub.publish(batch)
                got = receive_until(
                    listener, ["STATUSTEXT", "HEARTBEAT"], lambda m: len(of_type(m, "STATUSTEXT")) >= 2,
                    timeout_s=60, what="two STATUSTEXT through MAVProxy",
                )  # fmt: skip
            finally:
                gcs.terminate()
                console, _ = gcs.communicate(timeout=30)
                listener.close()
            stored = svc.call(
                lambda: [decode_event(p.payload) for p in svc.service.outbox.stored()]
            )
    assert [e.predicate for e in stored] == [Predicate.F0, Predicate.F6]
    texts = [(m.severity, m.text) for m in of_type(got, "STATUSTEXT")]
    assert texts == [
        (int(Severity.WARNING), alert_text(stored[0])),
        (int(Severity.ERROR), alert_text(stored[1])),
    ]
    heartbeat = of_type(got, "HEARTBEAT")[0]
    assert heartbeat.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert (heartbeat.get_srcSystem(), heartbeat.get_srcComponent()) == (
        cfg.mavlink.link.source_system,
        mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER,
    )
    # MAVProxy took the daemon for the vehicle and showed each alert on its console.
    assert "Detected vehicle 1:191" in console
    assert all(f"AP: {text}" in console for _, text in texts), console
