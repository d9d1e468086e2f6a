"""A sink's delivery, a lane per vehicle (service.delivery): a vehicle whose events are refused holds up
only its own; held events are delivered from memory; once stopping, a refused vehicle is not retried."""

from __future__ import annotations

import asyncio
import sqlite3
import time

from protocols.events import Event, Predicate, Severity, StreamCause, make_event
from service.delivery import SinkDelivery
from service.outbox import Outbox
from service.outbox_writer import OutboxWriter


def event(vehicle: str, k: int) -> Event:
    return make_event(vehicle=vehicle, imu=0, t_s=float(k), predicate=Predicate.TIMEOUT,
                      cause=StreamCause.NO_DATA, severity=Severity.WARNING)  # fmt: skip


class Sink:
    """A transport whose receiver for ``offline`` never acknowledges; what it accepted, in order."""

    name = "s"

    def __init__(self, offline: set[str]):
        self.offline = offline
        self.accepted: list[Event] = []
        self.refused = 0

    async def deliver(self, event: Event, *, sent) -> bool:
        sent()
        await asyncio.sleep(0.01)  # the transport's round trip
        if event.vehicle in self.offline:
            self.refused += 1
            return False
        self.accepted.append(event)
        return True

    def close(self) -> None:
        pass


def test_a_refused_vehicle_holds_up_only_its_own_events_and_memory_is_delivered_too(tmp_path):
    path = tmp_path / "o.sqlite"

    async def scenario() -> tuple[Sink, list[str], list[str]]:
        sink = Sink(offline={"b"})
        wake, stop = asyncio.Event(), asyncio.Event()
        with Outbox(path, sinks=("s",)) as outbox:
            writer = OutboxWriter(outbox, on_stored=lambda n, v: wake.set(), on_held=wake.set,
                                  clock=time.monotonic)  # fmt: skip
            delivery = SinkDelivery(sink, outbox, writer, retry_s=0.05, idle=lambda: None,
                                    sent=lambda: None, count=lambda name: None,
                                    transport_error=print, beat=lambda: None)  # fmt: skip
            task = asyncio.create_task(delivery.run(wake, stop))
            # b's event comes first, then a's: a's go while b's is refused again and again.
            writer.write([event("b", 0)])
            writer.write([event("a", k) for k in range(1, 4)])
            lock = sqlite3.connect(path, isolation_level=None)
            lock.execute("BEGIN EXCLUSIVE")
            writer.write([event("a", 4)])  # held: delivered from memory
            for _ in range(200):
                if len(sink.accepted) == 4:
                    break
                await asyncio.sleep(0.01)
            lock.execute("ROLLBACK")
            lock.close()
            assert writer.flush()
            stop.set()
            wake.set()
            await asyncio.wait_for(task, 5.0)
            return sink, [p.id for p in outbox.pending("s")], [p.id for p in outbox.stored()]

    sink, pending, stored = asyncio.run(scenario())
    assert [e.event_id for e in sink.accepted] == [event("a", k).event_id for k in range(1, 5)]
    assert sink.refused >= 2  # b was tried again meanwhile
    # Only b's event is left; a's held event was stored as delivered.
    assert pending == [event("b", 0).event_id] and event("a", 4).event_id in stored


def test_a_vehicle_whose_waiting_events_were_given_up_is_not_waited_for_in_a_spin(tmp_path):
    """A refused vehicle's retry came due with nothing of it pending any more (its events given up
    meanwhile): the delivery's wait had a timeout of 0 from then on and turned the loop for good."""

    async def scenario() -> int:
        sink = Sink(offline={"b"})
        wake, stop = asyncio.Event(), asyncio.Event()
        beats = []
        with Outbox(tmp_path / "o.sqlite", sinks=("s",)) as outbox:
            writer = OutboxWriter(outbox, on_stored=lambda n, v: wake.set(), on_held=wake.set,
                                  clock=time.monotonic)  # fmt: skip
            delivery = SinkDelivery(sink, outbox, writer, retry_s=0.05, idle=lambda: None,
                                    sent=lambda: None, count=lambda name: None,
                                    transport_error=print, beat=lambda: beats.append(1))  # fmt: skip
            task = asyncio.create_task(delivery.run(wake, stop))
            writer.write([event("b", 0)])
            while sink.refused == 0:
                await asyncio.sleep(0.01)
            outbox.ack_ids("s", [event("b", 0).event_id])  # as a sink's backlog bound gives it up
            await asyncio.sleep(0.3)
            before = len(beats)
            await asyncio.sleep(0.5)
            stop.set()
            wake.set()
            await asyncio.wait_for(task, 5.0)
            return len(beats) - before

    # Idle: no turn at all (a spin made thousands in 0.5 s).
    assert asyncio.run(scenario()) <= 2


def test_an_ack_the_outbox_refused_is_recorded_once_it_takes_writes_and_not_waited_for_in_a_spin(
    tmp_path,
):
    """An event delivered while the outbox takes no write (locked here; read-only or removed in the
    field): its ack is kept in memory. The vehicle has nothing else to deliver, so the delivery waits
    (before: its pending row started a lane that found nothing, again and again, thousands of turns in
    0.5 s), and once the outbox takes writes again the ack is recorded without another event coming
    (before: only with the next ack, so a restart sent the event a second time)."""
    path = tmp_path / "o.sqlite"

    async def scenario() -> tuple[int, bool, int]:
        sink = Sink(offline=set())
        wake, stop = asyncio.Event(), asyncio.Event()
        beats = []
        with Outbox(path, sinks=("s",)) as outbox:
            writer = OutboxWriter(outbox, on_stored=lambda n, v: wake.set(), on_held=wake.set,
                                  clock=time.monotonic)  # fmt: skip
            writer.write([event("a", 0)])
            lock = sqlite3.connect(path, isolation_level=None)
            lock.execute("BEGIN EXCLUSIVE")
            delivery = SinkDelivery(sink, outbox, writer, retry_s=0.05, idle=lambda: None,
                                    sent=lambda: None, count=lambda name: None,
                                    transport_error=print, beat=lambda: beats.append(1))  # fmt: skip
            task = asyncio.create_task(delivery.run(wake, stop))
            while not sink.accepted:
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.3)
            before = len(beats)
            await asyncio.sleep(0.5)
            turns = len(beats) - before
            lock.execute("ROLLBACK")
            lock.close()
            for _ in range(500):
                if not outbox.pending("s"):
                    break
                await asyncio.sleep(0.01)
            recorded = not outbox.pending("s")
            stop.set()
            wake.set()
            await asyncio.wait_for(task, 5.0)
            return turns, recorded, len(sink.accepted)

    turns, recorded, sent = asyncio.run(scenario())
    assert turns <= 2 and recorded and sent == 1, (turns, recorded, sent)
