"""The service's events into the outbox, in the order they were raised; what it cannot take now is
held in memory and delivered from there.

A write the outbox cannot make (:class:`~service.outbox.OutboxUnavailable`: the disk
full or read-only, the file locked by another process, an I/O error, the data directory
gone) loses nothing and silences nothing: the events are held in memory, in order,
every event raised after them is held behind them, and the deliveries take them from
memory (:meth:`OutboxWriter.next_held`) while detection goes on. :meth:`OutboxWriter.flush`
(retried by the service with back-off, :data:`RETRY_MIN_S` doubling up to
:data:`RETRY_MAX_S`) writes them once the outbox takes writes again, each with a pending
row only for the sinks that do not have it yet.

The memory is bounded: beyond ``max_held`` events the oldest that every sink already has
are given up first (their place in the delivered history is lost: counted as
``outbox.held_dropped_delivered``), then the oldest (``outbox.held_lost``: a sink never
had it); both are said in the log, at most one line per
:data:`~protocols.log_rate.LOG_PERIOD_S` (a storm of events past the bound would otherwise log a
line each; what grew since is said by the next line, at the latest at the next status tick,
:meth:`OutboxWriter.counters`). Checkpoints wait while a held event is not yet with
every sink (:attr:`OutboxWriter.undelivered`): a checkpoint ahead of it would, after
``kill -9``, resume past an event that exists nowhere.

The status topic carries ``outbox.unavailable`` (1 while events are held),
``outbox.write_failures``, ``outbox.held_events``, ``outbox.unavailable_episodes`` and
the two counts of events given up; the log says when the outbox becomes unavailable
(with the reason) and when it is back (after how long, how many events it then took).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass, field

from protocols.events import Event, encode_event
from protocols.log_rate import LogRate
from service.log_setup import logger
from service.outage import Outage
from service.outbox import Outbox, OutboxUnavailable

RETRY_MIN_S = 0.05
RETRY_MAX_S = 2.0
MAX_HELD_DEFAULT = 10_000
"""Events held in memory at most while the outbox is unavailable (``[service] max_held_events``)."""
LOST_IDS_LOGGED = 20
"""Ids of the events given up named in one log line at most (the count says all)."""

log = logger("outbox")


@dataclass
class HeldEvent:
    """An event the outbox could not take yet, and the sinks that have it already."""

    event: Event
    payload: bytes
    done: set[str] = field(default_factory=set)


class OutboxWriter:
    """Events into ``outbox`` in order, held and delivered from memory while it is unavailable (module docstring).

    Parameters
    ----------
    outbox : the durable outbox.
    on_stored : told how many new events each successful write stored and the vehicles of the
        events it wrote (wakes the deliveries, saves those vehicles' state).
    on_held : called when events are held (wakes the deliveries: they take them from memory).
    clock : a monotonic clock (how long the outbox was unavailable).
    max_held : events held in memory at most (module docstring).
    """

    def __init__(
        self,
        outbox: Outbox,
        *,
        on_stored: Callable[[int, set[str]], None],
        on_held: Callable[[], None],
        clock: Callable[[], float],
        max_held: int = MAX_HELD_DEFAULT,
    ) -> None:
        if max_held < 1:
            raise ValueError(f"max_held must be >= 1, got {max_held!r}")
        self._outbox = outbox
        self._sinks = frozenset(outbox.sinks)
        self._on_stored = on_stored
        self._on_held = on_held
        self._max_held = int(max_held)
        self._held: list[HeldEvent] = []
        self._outage = Outage(clock)
        self.dropped_delivered = 0
        self.lost = 0
        self._bound_log = LogRate()
        self._lost_ids: list[str] = []
        """The first ids given up since the last log line (:data:`LOST_IDS_LOGGED`)."""

    @property
    def holding(self) -> bool:
        """Whether events wait for the outbox (it is unavailable)."""
        return bool(self._held)

    @property
    def undelivered(self) -> bool:
        """Whether a held event is not yet with every sink."""
        return any(h.done < self._sinks for h in self._held)

    def unavailable_s(self) -> float | None:
        """How long the outbox has refused the held events, s (None: it takes them)."""
        return self._outage.lasted() if self._held else None

    def write(self, events: Collection[Event]) -> None:
        """Store ``events`` after any held ones; held (and delivered from memory) when the outbox cannot take them."""
        if not events:
            return
        # While events are held the service's storage task retries (with back-off): a write tried
        # here for every event raised would hold the loop for the outbox's busy timeout each time.
        retrying = self.holding
        self._held.extend(HeldEvent(e, encode_event(e)) for e in events)
        if retrying or not self.flush():
            self._bound()
            self._on_held()

    def flush(self) -> bool:
        """Try once to write the held events; True when none is held any more."""
        if not self._held:
            return True
        try:
            new = self._outbox.put_many(
                ((h.event.event_id, h.event.vehicle, h.payload) for h in self._held),
                delivered={h.event.event_id: h.done for h in self._held if h.done},
            )
        except OutboxUnavailable as exc:
            if self._outage.failed():
                log.error(
                    "outbox unavailable (%s): %d event(s) held in memory and delivered from there, "
                    "detection goes on; retrying",
                    exc, len(self._held),
                )  # fmt: skip
            return False
        written, self._held = self._held, []
        if (lasted := self._outage.ended()) is not None:
            log.warning(
                "outbox available again after %.1f s: %d held event(s) written",
                lasted, len(written),
            )  # fmt: skip
        if new:
            self._on_stored(new, {h.event.vehicle for h in written})
        return True

    def _bound(self) -> None:
        """At most ``max_held`` events: the oldest every sink has go first, then the oldest (module docstring)."""
        excess = len(self._held) - self._max_held
        if excess <= 0:
            return
        delivered = [h for h in self._held if h.done >= self._sinks][:excess]
        gone = {id(h) for h in delivered}
        lost = [h for h in self._held if id(h) not in gone][: excess - len(delivered)]
        gone |= {id(h) for h in lost}
        self._held = [h for h in self._held if id(h) not in gone]
        self.dropped_delivered += len(delivered)
        self.lost += len(lost)
        room = LOST_IDS_LOGGED - len(self._lost_ids)
        self._lost_ids.extend(h.event.event_id for h in lost[: max(0, room)])
        self._log_bound()

    def _log_bound(self) -> None:
        """Say the events given up since the last line, when a line is due (module docstring)."""
        new = self._bound_log.due({"delivered": self.dropped_delivered, "lost": self.lost})
        if not new:
            return
        lost = new.get("lost", 0)
        more = f" and {lost - len(self._lost_ids)} more" if lost > len(self._lost_ids) else ""
        log.warning(
            "outbox unavailable and %d events held (max_held_events): %d delivered everywhere are "
            "not kept for the history, %d not yet delivered everywhere are given up (%s%s); counted "
            "as outbox.held_dropped_delivered and outbox.held_lost",
            self._max_held, new.get("delivered", 0), lost,
            ", ".join(self._lost_ids) or "none", more,
        )  # fmt: skip
        self._lost_ids = []

    def next_held(self, sink: str, vehicle: str) -> HeldEvent | None:
        """The oldest held event of ``vehicle`` that ``sink`` does not have yet."""
        return next(
            (h for h in self._held if h.event.vehicle == vehicle and sink not in h.done), None
        )

    def held_vehicles(self, sink: str) -> dict[str, int]:
        """The vehicles with held events ``sink`` does not have yet, each with how many."""
        out: dict[str, int] = {}
        for h in self._held:
            if sink not in h.done:
                out[h.event.vehicle] = out.get(h.event.vehicle, 0) + 1
        return out

    def delivered(self, sink: str, held: HeldEvent) -> bool:
        """``sink`` has ``held``: True when it is still held (marked so), False when the outbox took it meanwhile."""
        if not any(h is held for h in self._held):
            return False
        held.done.add(sink)
        return True

    def stop(self) -> int:
        """The service stops: the held events are said (how many every sink has, how many are lost); their number."""
        if self._held:
            everywhere = sum(h.done >= self._sinks for h in self._held)
            log.error(
                "stopping with the outbox unavailable: %d held event(s) could not be stored (%d of "
                "them delivered to every sink, %d lost for at least one); exiting non-zero",
                len(self._held), everywhere, len(self._held) - everywhere,
            )  # fmt: skip
        return len(self._held)

    def counters(self) -> dict[str, int]:
        """For the status topic (module docstring); the events given up since the last log line are said when due."""
        self._log_bound()
        return {
            "outbox.unavailable": int(self.holding),
            "outbox.held_events": len(self._held),
            "outbox.held_dropped_delivered": self.dropped_delivered,
            "outbox.held_lost": self.lost,
            **self._outage.counters("outbox"),
        }
