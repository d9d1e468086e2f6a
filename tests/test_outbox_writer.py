"""OutboxWriter: events held in order while the outbox is unavailable, delivered from memory meanwhile,
written once it is back with a pending row only for the sinks that do not have them yet."""

from __future__ import annotations

import logging
import sqlite3
import time
from unittest import mock

from protocols.events import Predicate, Severity, StreamCause, make_event
from protocols.log_rate import LOG_PERIOD_S
from service.outbox import Outbox
from service.outbox_writer import OutboxWriter


def event(k: int, vehicle: str = "v"):
    return make_event(vehicle=vehicle, imu=0, t_s=float(k), predicate=Predicate.TIMEOUT,
                      cause=StreamCause.NO_DATA, severity=Severity.WARNING)  # fmt: skip


def test_events_are_held_in_order_delivered_from_memory_and_written_once_the_file_is_released(
    tmp_path,
):
    path = tmp_path / "o.sqlite"
    stored, held = [], []
    with Outbox(path, sinks=("a", "b")) as ob:
        writer = OutboxWriter(ob, on_stored=lambda n, v: stored.append((n, v)),
                              on_held=lambda: held.append(1), clock=lambda: 0.0)  # fmt: skip
        writer.write([event(0)])
        assert stored == [(1, {"v"})] and not held
        other = sqlite3.connect(path, isolation_level=None)
        other.execute("BEGIN EXCLUSIVE")
        writer.write([event(1), event(2)])
        writer.write([event(3, vehicle="w")])
        assert writer.holding and len(held) == 2
        assert writer.counters() == {
            "outbox.unavailable": 1,
            # Once events are held the service's storage task retries, not every write.
            "outbox.write_failures": 1,
            "outbox.held_events": 3,
            "outbox.held_dropped_delivered": 0,
            "outbox.held_lost": 0,
            "outbox.unavailable_episodes": 1,
        }
        # Sink a takes vehicle v's held events from memory, in order; w's are apart.
        assert writer.held_vehicles("a") == {"v": 2, "w": 1}
        first = writer.next_held("a", "v")
        assert first is not None and first.event == event(1)
        assert writer.delivered("a", first) and writer.next_held("a", "v").event == event(2)
        assert writer.undelivered
        other.execute("ROLLBACK")
        assert writer.flush() and stored == [(1, {"v"}), (3, {"v", "w"})] and not writer.holding
        # Stored once; sink a is not sent event 1 again, sink b is.
        assert [p.id for p in ob.pending("a")] == [event(k).event_id for k in (0, 2)] + [
            event(3, "w").event_id
        ]
        assert [p.id for p in ob.pending("b")] == [event(k).event_id for k in (0, 1, 2)] + [
            event(3, "w").event_id
        ]
        # An event the transport held while it was written: not held any more, acked in the outbox.
        assert not writer.delivered("b", first)
        assert writer.counters()["outbox.unavailable"] == 0
        other.execute("BEGIN EXCLUSIVE")
        writer.write([event(4)])
        assert writer.stop() == 1
        other.execute("ROLLBACK")
        other.close()
        assert writer.counters()["outbox.unavailable_episodes"] == 2


def _held_by_a_lock(ob, path, *, max_held):
    """A writer holding at most ``max_held`` events, and another connection's lock on the file."""
    writer = OutboxWriter(ob, on_stored=lambda n, v: None, on_held=lambda: None,
                          clock=lambda: 0.0, max_held=max_held)  # fmt: skip
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    return writer, other


def test_memory_is_bounded_giving_up_the_oldest_delivered_everywhere_first(tmp_path):
    path = tmp_path / "o.sqlite"
    with Outbox(path, sinks=("a",)) as ob:
        writer, other = _held_by_a_lock(ob, path, max_held=3)
        writer.write([event(k) for k in range(3)])
        middle = writer.next_held("a", "v")
        assert middle is not None
        writer.delivered("a", middle)  # event 0 is with every sink
        writer.write([event(3)])
        assert [writer.next_held("a", "v").event] == [event(1)]
        assert writer.counters()["outbox.held_dropped_delivered"] == 1
        writer.write([event(4)])
        # Nothing delivered everywhere is left: the oldest goes, counted as lost.
        assert writer.counters()["outbox.held_lost"] == 1
        assert writer.next_held("a", "v").event == event(2)
        other.execute("ROLLBACK")
        other.close()
        assert writer.flush()
        assert [p.id for p in ob.pending("a")] == [event(k).event_id for k in (2, 3, 4)]


def test_events_given_up_past_the_bound_are_logged_at_a_bounded_rate(tmp_path, caplog):
    """A storm past ``max_held``: one line at once, then none until the period is over; the next line
    says all that was given up since (the counts and the ids), at the latest at a status tick."""
    path = tmp_path / "o.sqlite"
    with Outbox(path, sinks=("a",)) as ob:
        writer, other = _held_by_a_lock(ob, path, max_held=2)
        with caplog.at_level(logging.WARNING, logger="ins_health.outbox"):
            for k in range(50):
                writer.write([event(k)])
            lines = [r.getMessage() for r in caplog.records if "max_held_events" in r.getMessage()]
            assert len(lines) == 1 and "1 not yet delivered everywhere are given up" in lines[0]
            with mock.patch(
                "protocols.log_rate.time.monotonic", return_value=time.monotonic() + LOG_PERIOD_S
            ):
                assert writer.counters()["outbox.held_lost"] == 48
            lines = [r.getMessage() for r in caplog.records if "max_held_events" in r.getMessage()]
        other.execute("ROLLBACK")
        other.close()
        assert len(lines) == 2 and "47 not yet delivered everywhere are given up" in lines[1]
        assert event(1).event_id in lines[1] and "and 27 more" in lines[1]
