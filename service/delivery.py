"""One sink's deliveries, a lane per vehicle: a vehicle whose receiver does not acknowledge holds up
only its own events.

The delivery of a sink (:class:`SinkDelivery`) starts a lane for each vehicle with events pending
for the sink — in the outbox (:meth:`~service.outbox.Outbox.pending_vehicles`) or held in memory
while the outbox cannot take them (:meth:`~service.outbox_writer.OutboxWriter.held_vehicles`). A
lane hands its vehicle's events to the transport in the order they were raised, stored ones first
(they were raised before any held one), and acks each as it is accepted. An event the transport
refuses (no acknowledgement within ``ack_timeout_s``, the alert policy deferring it, the link gone)
ends the lane; the vehicle is tried again ``retry_s`` later while the other vehicles' lanes go on.
With one vehicle's ground station offline, the others' events left within the same time as with
all online (``benchmarks/bench_delivery.py``); before, delivery took the outbox in order and
stopped at the first event without an acknowledgement, for every vehicle.

An ack the outbox cannot record now (it is unavailable) is kept in memory and recorded with the
next one, or by a retry every :data:`RECORD_RETRY_S` and once more as the delivery ends; the event is
not sent again meanwhile, and its vehicle's lane is not started again for it (after a ``kill -9`` it
is sent again, and receivers drop the repeat by id). Once ``stop`` is set, a refused vehicle is not tried again, and :meth:`SinkDelivery.run`
returns when no lane is left.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Callable
from typing import Any

from protocols.events import Event, EventError, decode_event
from service.outbox import Outbox, OutboxUnavailable, PendingEvent
from service.outbox_writer import HeldEvent, OutboxWriter
from service.sinks import TRANSPORT_ERRORS, EventSink

LANE_BATCH = 16
"""Stored events a lane reads from the outbox at a time."""
RECORD_RETRY_S = 1.0
"""How often acks the outbox refused are tried again while nothing else records them, s (a locked
file holds the loop for the outbox's busy timeout at each try)."""


class SinkDelivery:
    """The lanes of one sink (module docstring).

    Parameters
    ----------
    sink : the transport.
    outbox, writer : where the pending events are (stored, held).
    retry_s : how long a refused vehicle waits before it is tried again, s.
    idle : called when the delivery waits with nothing to hand over (the intake need not wait for it).
    sent : called, from any thread, once the transport holds an event a lane took.
    count : counts a service counter (``delivery.<sink>.retries``, ``outbox.undecodable``).
    transport_error : told of a send the transport raised on (the event is retried).
    beat : the delivery's progress (for its supervisor).
    """

    def __init__(
        self,
        sink: EventSink,
        outbox: Outbox,
        writer: OutboxWriter,
        *,
        retry_s: float,
        idle: Callable[[], None],
        sent: Callable[[], None],
        count: Callable[[str], None],
        transport_error: Callable[[BaseException], None],
        beat: Callable[[], None],
    ) -> None:
        self.sink = sink
        self._outbox = outbox
        self._writer = writer
        self._retry_s = retry_s
        self._idle = idle
        self._sent = sent
        self._count = count
        self._transport_error = transport_error
        self._beat = beat
        self._unrecorded: set[str] = set()
        """Ids of stored events delivered whose ack the outbox could not record yet."""

    def pending_vehicles(self) -> dict[str, int]:
        """Each vehicle's events waiting for this sink (stored and held); the stored ones as far as the outbox answers."""
        out = self._writer.held_vehicles(self.sink.name)
        with contextlib.suppress(OutboxUnavailable):
            for v, n in self._outbox.pending_vehicles(self.sink.name).items():
                # A vehicle whose pending rows are all delivered (acks not recorded) has no lane to run.
                if n > len(self._unrecorded) or self._stored(v):
                    out[v] = out.get(v, 0) + n
        return out

    def _stored(self, vehicle: str) -> list[PendingEvent]:
        """``vehicle``'s oldest stored events still to deliver (not those delivered, acks unrecorded)."""
        stored = self._outbox.pending(
            self.sink.name, vehicle=vehicle, limit=LANE_BATCH + len(self._unrecorded)
        )
        return [p for p in stored if p.id not in self._unrecorded][:LANE_BATCH]

    async def run(self, wake: asyncio.Event, stop: asyncio.Event) -> None:
        """Lanes until ``stop`` is set and none is left (module docstring); ``wake`` is set when events come."""
        loop = asyncio.get_running_loop()
        lanes: dict[str, asyncio.Task[bool]] = {}
        retry_at: dict[str, float] = {}
        record_at = -math.inf
        try:
            while True:
                now = loop.time()
                if self._unrecorded and record_at <= now:
                    self._ack([])
                    record_at = now + RECORD_RETRY_S
                started = False
                for vehicle in self.pending_vehicles():
                    if vehicle not in lanes and retry_at.get(vehicle, -math.inf) <= now:
                        lanes[vehicle] = asyncio.create_task(self._lane(vehicle))
                        started = True
                if not started:
                    self._sent()
                for vehicle in [v for v, t in retry_at.items() if t <= now and v not in lanes]:
                    del retry_at[vehicle]  # due with nothing pending (given up meanwhile)
                later = [t for t in retry_at.values() if math.isfinite(t)]
                if not lanes and stop.is_set() and not later:
                    if self._unrecorded:
                        self._ack([])
                    return
                if not lanes:
                    self._idle()
                woken = asyncio.ensure_future(wake.wait())
                waits: list[asyncio.Future[Any]] = [woken, *lanes.values()]
                if self._unrecorded:
                    later.append(record_at)
                timeout_s = None if not later else max(0.0, min(later) - now)
                try:
                    await asyncio.wait(
                        waits, timeout=timeout_s, return_when=asyncio.FIRST_COMPLETED
                    )
                finally:
                    woken.cancel()
                wake.clear()
                for vehicle, task in list(lanes.items()):
                    if not task.done():
                        continue
                    del lanes[vehicle]
                    if task.result():
                        retry_at.pop(vehicle, None)
                    else:
                        retry_at[vehicle] = (
                            math.inf if stop.is_set() else loop.time() + self._retry_s
                        )
                self._beat()
        finally:
            for task in lanes.values():
                task.cancel()
            await asyncio.gather(*lanes.values(), return_exceptions=True)

    async def _lane(self, vehicle: str) -> bool:
        """``vehicle``'s events to the transport in order until none is left (True) or one is refused (False)."""
        while True:
            stored = []
            with contextlib.suppress(OutboxUnavailable):
                stored = self._stored(vehicle)
            if stored:
                acked: list[str] = []
                for p in stored:
                    try:
                        event = decode_event(p.payload)
                    except EventError:
                        self._count("outbox.undecodable")
                        acked.append(p.id)
                        continue
                    if not await self._deliver(event):
                        self._ack(acked)
                        with contextlib.suppress(OutboxUnavailable):
                            # Only a count for the status topic: nothing is lost when it cannot be written.
                            self._outbox.record_attempt(self.sink.name, [p.seq])
                        return False
                    acked.append(p.id)
                self._ack(acked)
                continue
            held = self._writer.next_held(self.sink.name, vehicle)
            if held is None:
                return True
            if not await self._deliver(held.event):
                return False
            self._delivered_held(held)

    async def _deliver(self, event: Event) -> bool:
        try:
            ok = await self.sink.deliver(event, sent=self._sent)
        except TRANSPORT_ERRORS as exc:
            self._transport_error(exc)
            ok = False
        if not ok:
            self._count(f"delivery.{self.sink.name}.retries")
        return ok

    def _ack(self, ids: list[str]) -> None:
        """Record ``ids`` (and acks not yet recorded) as delivered; kept in memory while the outbox refuses."""
        todo = self._unrecorded | set(ids)
        try:
            self._outbox.ack_ids(self.sink.name, sorted(todo))
        except OutboxUnavailable:
            self._unrecorded = todo
            return
        self._unrecorded = set()

    def _delivered_held(self, held: HeldEvent) -> None:
        if not self._writer.delivered(self.sink.name, held):
            # The outbox took it while the transport had it: its pending row is acked there.
            self._ack([held.event.event_id])

    @property
    def unrecorded(self) -> int:
        """Acks delivered but not yet recorded in the outbox."""
        return len(self._unrecorded)
