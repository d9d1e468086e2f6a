"""Where events are delivered: an :class:`EventSink` per transport (Zenoh events, MAVLink STATUSTEXT alerts)."""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

from protocols.events import Event
from protocols.mavlink_adapter import ImuLink
from protocols.zenoh_adapter import (
    Acknowledgement,
    EventPublisher,
    Session,
    ZenohError,
)
from protocols.zenoh_settings import AckMode
from service.alert_policy import AlertPolicy

TRANSPORT_ERRORS = (ZenohError, OSError, ConnectionError, ValueError)
"""What a transport raises when its link is gone: zenoh errors, socket errors, and pymavlink's
``ValueError`` for a write on a closed port. The event stays in the outbox and is retried."""


class EventSink(Protocol):
    """A transport that events are delivered to; ``deliver`` returns True once the transport accepted the event.

    ``sent`` is called, from any thread, once the transport holds the event (before a wait for
    acknowledgements): the service's intake then goes on with the rest of a group of frames.
    """

    name: str

    async def deliver(self, event: Event, *, sent: Callable[[], None]) -> bool: ...

    def close(self) -> None: ...


class ZenohEventSink:
    """Events on ``ins/<vehicle>/health/events`` (reliable, blocking), acknowledged as configured.

    Each publish waits for its acknowledgements (up to ``ack_timeout_s``) in a thread of the sink's
    own pool of up to ``max_lanes`` threads (one per vehicle delivering at once,
    :mod:`service.delivery`): in the loop's default pool (6 threads on 2 cores) six vehicles whose
    ground stations are offline held every thread, and the others' events waited behind them.
    """

    name = "zenoh"

    def __init__(
        self,
        session: Session,
        *,
        ack: AckMode,
        ack_timeout_s: float,
        min_acks: int,
        max_lanes: int,
        ack_from: tuple[str, ...] = (),
    ):
        self._publisher = EventPublisher(
            session, ack=ack, ack_timeout_s=ack_timeout_s, min_acks=min_acks, ack_from=ack_from
        )
        self._pool = ThreadPoolExecutor(max_workers=max_lanes, thread_name_prefix="zenoh-events")

    @property
    def refused(self) -> tuple[int, Acknowledgement | None]:
        """Acknowledgements refused (their receiver not in ``ack_from``) and the last one."""
        return self._publisher.refused, self._publisher.last_refused

    async def deliver(self, event: Event, *, sent: Callable[[], None]) -> bool:
        # publish() blocks up to the acknowledgement timeout: keep it off the loop.
        publish = functools.partial(self._publisher.publish, event, on_put=sent)
        return await asyncio.get_running_loop().run_in_executor(self._pool, publish)

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._publisher.close()


class MavlinkAlertSink:
    """STATUSTEXT alerts (:func:`protocols.mavlink_adapter.alert_text`) for the events of the link's vehicle."""

    name = "mavlink"

    def __init__(self, link: ImuLink, *, policy: AlertPolicy, clock: Callable[[], float]):
        self.link = link
        self.policy = policy
        self._clock = clock
        self.other_vehicles = 0

    async def deliver(self, event: Event, *, sent: Callable[[], None]) -> bool:
        if event.vehicle != self.link.settings.vehicle:
            self.other_vehicles += 1
            return True
        decision = self.policy.decide(event, self._clock())
        if decision is None:
            return False
        if decision:
            # A serial port may block on a full buffer: keep the write off the loop.
            await asyncio.to_thread(self.link.send_alert, event)
            sent()
        return True

    async def heartbeat(self) -> None:
        await asyncio.to_thread(self.link.send_heartbeat)

    def close(self) -> None:
        """The link belongs to the service; closing the sink leaves it open."""
