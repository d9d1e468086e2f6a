"""OutboxWriter: events held in order while the outbox is unavailable, written once it is back."""

from __future__ import annotations

import asyncio
import sqlite3

from protocols.events import Predicate, Severity, StreamCause, make_event
from service.outbox import Outbox
from service.outbox_writer import OutboxWriter


def event(k: int):
    return make_event(vehicle="v", imu=0, t_s=float(k), predicate=Predicate.TIMEOUT,
                      cause=StreamCause.NO_DATA, severity=Severity.WARNING)  # fmt: skip


def test_events_are_held_in_order_while_the_file_is_locked_and_written_once_it_is_released(
    tmp_path,
):
    path = tmp_path / "o.sqlite"
    stored = []
    with Outbox(path, sinks=("s",)) as ob:
        writer = OutboxWriter(ob, on_stored=lambda n, v: stored.append((n, v)), clock=lambda: 0.0)
        assert writer.write([event(0)]) and stored == [(1, {"v"})]
        other = sqlite3.connect(path, isolation_level=None)
        other.execute("BEGIN EXCLUSIVE")
        assert not writer.write([event(1), event(2)])
        assert not writer.write([event(3)])
        assert writer.holding and writer.counters() == {
            "outbox.unavailable": 1,
            "outbox.write_failures": 2,
            "outbox.held_events": 3,
            "outbox.unavailable_episodes": 1,
        }
        other.execute("ROLLBACK")
        assert asyncio.run(writer.until_written())
        assert [p.id for p in ob.pending("s")] == [event(k).event_id for k in range(4)]
        assert stored == [(1, {"v"}), (3, {"v"})] and not writer.holding
        assert writer.counters()["outbox.unavailable"] == 0
        other.execute("BEGIN EXCLUSIVE")
        assert not writer.write([event(4)])
        writer.abandon()
        assert not asyncio.run(writer.until_written())
        other.execute("ROLLBACK")
        other.close()
        assert writer.counters()["outbox.unavailable_episodes"] == 2
