"""Who and what the daemon trusts, against the real daemon and router processes (issue 29): whose
acknowledgements count, which clocks its cross-IMU check can compare, which source owns a
vehicle's stream, which configuration values it takes."""

from __future__ import annotations

import pytest
from service_support import run_fleet, wait_subscribed, wait_until
from test_service_faults import (
    ServiceProcess,
    ground_and_vehicle,
    offline_fleet,
    publish_blocking,
    put_store,
)
from test_service_hostile import to_the_fault

from protocols.zenoh_adapter import EventReceiver, frame_key

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
