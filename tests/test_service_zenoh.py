"""The service over real Zenoh sessions on 127.0.0.1: a router, a vehicle, a ground station, one or two instances."""

from __future__ import annotations

import functools
import threading

import pytest
import zenoh
from service_support import (
    EventStream,
    ServiceThread,
    batches_of,
    run_fleet,
    service_config,
    wait_subscribed,
    wait_until,
    zenoh_client_config,
    zenoh_router,
)

from protocols.events import ImuState, Predicate
from protocols.zenoh_adapter import EventReceiver, FramePublisher, frame_key, subscribe_status
from service.demo import demo_passport, demo_scenario
from service.passport_store import PassportStore
from service.pipeline import FleetProcessor, PipelineOptions

pytestmark = pytest.mark.network
QUIET = {"timeout_s": 60.0}


@functools.cache
def unit():
    passport, g = demo_passport()
    return passport, g, demo_scenario()


def expected_events(vehicle: str, *, until_s: float | None = None) -> list:
    """What the pipeline gives offline for the same frames (the service must say the same)."""
    passport, g, _sc = unit()
    fleet = FleetProcessor(
        passports=lambda v, i: passport,
        options=PipelineOptions(gravity_mps2=g, gravity_rel_err=1e-4),
    )
    return run_fleet(fleet, frames(vehicle, until_s=until_s), finish=False)


def frames(vehicle: str, *, until_s: float | None = None) -> list:
    sc = unit()[2]
    out = list(batches_of(sc.session, vehicle=vehicle, imu=0, batch_samples=100))
    return out if until_s is None else [b for b in out if b.t_s[-1] <= until_s]


def store_with(tmp_path, vehicles):
    passport = unit()[0]
    store = PassportStore(tmp_path / "passports")
    for v in vehicles:
        store.put(v, 0, passport)
    return store.root


def publish(session, batches) -> None:
    """Publish frames losslessly (BLOCK: a burst must not be shed the way a live vehicle's frames may be)."""
    with FramePublisher(
        session,
        batches[0].vehicle,
        batches[0].imu,
        congestion_control=zenoh.CongestionControl.BLOCK,
    ) as pub:
        for b in batches:
            pub.publish(b)


def test_frames_published_by_one_session_are_diagnosed_and_events_arrive_at_another(tmp_path):
    v = "uav-1"
    g = unit()[1]
    with zenoh_router() as port:
        # A long timeout: the end of the stream must not add a timeout event while the test looks.
        cfg = service_config(
            tmp_path,
            port=port,
            passport_dir=store_with(tmp_path, [v]),
            site={"gravity_mps2": g},
            validity=QUIET,
        )
        with (
            ServiceThread(cfg),
            zenoh.open(zenoh_client_config(port)) as vehicle,
            zenoh.open(zenoh_client_config(port)) as ground,
        ):
            got, statuses = [], []
            lock = threading.Lock()
            wire = EventStream(ground)
            with EventReceiver(ground, lambda e: got.append(e)):
                subscribe_status(
                    ground, lambda s: (lock.acquire(), statuses.append(s), lock.release())
                )
                wait_subscribed(vehicle, frame_key(v, 0))
                publish(vehicle, frames(v))
                want = expected_events(v)
                wait_until(lambda: len(got) >= len(want), timeout_s=60, what="the F0 and F6 events")
                assert [e.event_id for e in got] == [e.event_id for e in want]
                assert [e.predicate for e in got] == [Predicate.F0, Predicate.F6]
                # Each event was put on the wire once (acknowledged on the first try).
                wait_until(
                    lambda: len(wire.snapshot()) >= 2, timeout_s=10, what="the events on the wire"
                )
                assert wire.snapshot() == [e.event_id for e in want]

                def settled():
                    with lock:
                        return any(
                            s.counters.get("imu0.samples.accepted") == unit()[2].session.n_samples
                            for s in statuses
                        )

                wait_until(settled, timeout_s=30, what="a status with every sample counted")
            with lock:
                last = [s for s in statuses if s.vehicle == v][-1]
            assert last.service == "ins-health" and last.imus[0].state is ImuState.FAULT
            assert last.counters["service.frames.dropped_overload"] == 0


def test_a_vehicles_state_is_saved_as_soon_as_its_event_is_stored_and_no_other(tmp_path):
    """With an hour between periodic checkpoints, the vehicle whose F0 event is stored is saved at
    once: a kill -9 then cannot leave an event without the state that raised it. Another vehicle
    streaming meanwhile waits for the period (saving every changed unit after each event cost a
    fleet's loop tens of ms per event)."""
    v, other = "uav-1", "uav-2"
    g = unit()[1]
    until_s = expected_events(v)[0].t_s + 1.0
    assert [e.predicate for e in expected_events(v, until_s=until_s)] == [Predicate.F0]
    quiet_until_s = expected_events(other)[0].t_s - 5.0
    assert expected_events(other, until_s=quiet_until_s) == []
    with zenoh_router() as port:
        cfg = service_config(
            tmp_path,
            port=port,
            passport_dir=store_with(tmp_path, [v, other]),
            name="soon",
            site={"gravity_mps2": g},
            validity=QUIET,
            service={"checkpoint_period_s": 3600.0},
        )
        with ServiceThread(cfg) as svc, zenoh.open(zenoh_client_config(port)) as vehicle:
            wait_subscribed(vehicle, frame_key(other, 0))
            publish(vehicle, frames(other, until_s=quiet_until_s))
            wait_until(
                lambda: (
                    svc.service.fleet.pipelines.get((other, 0)) is not None
                    and svc.service.fleet.pipelines[(other, 0)].n_samples
                    == sum(b.n_samples for b in frames(other, until_s=quiet_until_s))
                ),
                timeout_s=60,
                what="the other vehicle's frames taken",
            )
            publish(vehicle, frames(v, until_s=until_s))
            wait_until(lambda: svc.service.events_stored >= 1, timeout_s=60, what="the F0 event")
            wait_until(
                lambda: svc.call(lambda: svc.service.checkpoints.load(f"{v}/0")) is not None,
                timeout_s=10,
                what="the checkpoint of the unit that raised it",
            )
            assert svc.call(lambda: svc.service.checkpoints.load(f"{other}/0")) is None


def test_two_instances_share_a_fleet_by_key_expression(tmp_path):
    """alpha-* vehicles go to instance A, bravo-* to B; each handles its own, nothing is handled twice."""
    g = unit()[1]
    vehicles = ["alpha-1", "bravo-1"]
    until = unit()[2].fault_s + 2.0
    with zenoh_router() as port:
        root = store_with(tmp_path, vehicles)
        cfg_a = service_config(
            tmp_path,
            port=port,
            passport_dir=root,
            name="svc-a",
            site={"gravity_mps2": g},
            validity=QUIET,
            zenoh={"frames_key": "ins/alpha-$*/imu/*"},
        )
        cfg_b = service_config(
            tmp_path,
            port=port,
            passport_dir=root,
            name="svc-b",
            site={"gravity_mps2": g},
            validity=QUIET,
            zenoh={"frames_key": "ins/bravo-$*/imu/*"},
        )
        with (
            ServiceThread(cfg_a) as a,
            ServiceThread(cfg_b) as b,
            zenoh.open(zenoh_client_config(port)) as vehicle,
            zenoh.open(zenoh_client_config(port)) as ground,
        ):
            got = []
            wire = EventStream(ground)
            with EventReceiver(ground, lambda e: got.append(e)):
                for v in vehicles:
                    wait_subscribed(vehicle, frame_key(v, 0))
                    publish(vehicle, frames(v, until_s=until))
                want = {e.event_id for v in vehicles for e in expected_events(v, until_s=until)}
                wait_until(
                    lambda: len(got) >= len(want), timeout_s=60, what="the events of both vehicles"
                )
                assert {e.event_id for e in got} == want and len(got) == len(want) == 2
                wait_until(
                    lambda: len(wire.snapshot()) >= 2, timeout_s=10, what="the events on the wire"
                )
                assert sorted(wire.snapshot()) == sorted(want)
            assert a.call(lambda: sorted(a.service.fleet.pipelines)) == [("alpha-1", 0)]
            assert b.call(lambda: sorted(b.service.fleet.pipelines)) == [("bravo-1", 0)]
            assert (
                a.call(lambda: a.service.events_stored) == 1
                and b.call(lambda: b.service.events_stored) == 1
            )
