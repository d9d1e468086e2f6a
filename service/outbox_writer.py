"""The service's events into the outbox, in the order they were raised; what it cannot take now is held.

A write the outbox cannot make (:class:`~service.outbox.OutboxUnavailable`: the disk
full, the file locked by another process, an I/O error) loses nothing: the events
are held in memory, in order, every event raised after them is held behind them,
and :meth:`OutboxWriter.until_written` writes them, retrying with back-off
(:data:`RETRY_MIN_S` doubling up to :data:`RETRY_MAX_S`), once the outbox takes
writes again. While events are held the outbox is *unavailable*, and the rest of
the service holds back so that state never gets ahead of the events:

* the intake takes no frame (back-pressure: frames wait in the sources' bounded
  queues, and beyond them are dropped and counted as ``dropped_overload``), so a
  frame is either processed with its events in the outbox or not processed;
* checkpoints wait: a checkpoint of state whose events are not in the outbox
  would, after ``kill -9``, resume past events that were never stored;
* the timeout checks wait (the silence is the service's, not the IMUs').

The memory held is bounded by construction: while events are held no frame is
taken, so they are at most the events of one group of frames (the intake's
``QUEUED_SAMPLES_MAX`` samples) and of one timeout check of the fleet.

The status topic carries ``outbox.unavailable`` (1 while events are held),
``outbox.write_failures`` (writes that failed), ``outbox.held_events`` and
``outbox.unavailable_episodes``; the log says when the outbox becomes
unavailable (with the reason) and when it is back (after how long, how many
events it then took).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from protocols.events import Event, encode_event
from service.log_setup import logger
from service.outage import Outage
from service.outbox import Outbox, OutboxUnavailable

RETRY_MIN_S = 0.05
RETRY_MAX_S = 2.0

log = logger("outbox")


class OutboxWriter:
    """Events into ``outbox`` in order, held while it is unavailable (module docstring).

    Parameters
    ----------
    outbox : the durable outbox.
    on_stored : told how many new events each successful write stored and the vehicles of the
        events it wrote (wakes the deliveries, saves those vehicles' state).
    clock : a monotonic clock (how long the outbox was unavailable).
    """

    def __init__(
        self,
        outbox: Outbox,
        *,
        on_stored: Callable[[int, set[str]], None],
        clock: Callable[[], float],
    ) -> None:
        self._outbox = outbox
        self._on_stored = on_stored
        self._held: list[Event] = []
        self._outage = Outage(clock)
        self._abandoned = False

    @property
    def holding(self) -> bool:
        """Whether events wait for the outbox (it is unavailable)."""
        return bool(self._held)

    def write(self, events: list[Event]) -> bool:
        """Store ``events`` after any held ones; False if they are held (the outbox is unavailable)."""
        self._held.extend(events)
        return self.flush()

    def flush(self) -> bool:
        """Try once to write the held events; True when none is held any more."""
        if not self._held:
            return True
        try:
            new = self._outbox.put_many(
                (e.event_id, e.vehicle, encode_event(e)) for e in self._held
            )
        except OutboxUnavailable as exc:
            if self._outage.failed():
                log.error(
                    "outbox unavailable (%s): %d event(s) held in memory, frames wait "
                    "(dropped beyond the queue, counted); retrying",
                    exc, len(self._held),
                )  # fmt: skip
            return False
        written, self._held = self._held, []
        if (lasted := self._outage.ended()) is not None:
            log.warning(
                "outbox available again after %.1f s: %d held event(s) written, frames taken again",
                lasted, len(written),
            )  # fmt: skip
        if new:
            self._on_stored(new, {e.vehicle for e in written})
        return True

    async def until_written(self, *, on_retry: Callable[[], None] | None = None) -> bool:
        """Retry with back-off until nothing is held (True), or until :meth:`abandon` (False).

        ``on_retry`` is called before each wait (the waiting task is alive: a supervisor's beat).
        """
        delay_s = RETRY_MIN_S
        while not self.flush():
            if self._abandoned:
                return False
            if on_retry is not None:
                on_retry()
            await asyncio.sleep(delay_s)
            delay_s = min(2.0 * delay_s, RETRY_MAX_S)
        return True

    def abandon(self) -> None:
        """Stop waiting (the service is stopping): the held events are lost, and the log says how many.

        The checkpoints waited for them, so the next start resumes from before the frames
        that raised them.
        """
        self._abandoned = True
        if self._held:
            log.error(
                "stopping with the outbox unavailable: %d held event(s) could not be stored and are lost",
                len(self._held),
            )

    def counters(self) -> dict[str, int]:
        """For the status topic (module docstring)."""
        return {
            "outbox.unavailable": int(self.holding),
            "outbox.held_events": len(self._held),
            **self._outage.counters("outbox"),
        }
