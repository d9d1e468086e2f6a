"""The durable outbox: idempotent by id, per-sink delivery state, survives reopen and kill -9."""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading

import pytest

from service.outbox import DataDirInUse, DataDirLock, Outbox, OutboxError, OutboxUnavailable


def ids(events):
    return [e.id for e in events]


def test_put_is_idempotent_by_id_and_pending_is_per_sink(tmp_path):
    with Outbox(tmp_path / "o.sqlite", sinks=("zenoh", "mavlink")) as ob:
        assert ob.put("a" * 32, "v1", b"A")
        assert not ob.put("a" * 32, "v1", b"A-again")  # same id: not stored twice
        assert (
            ob.put_many([("b" * 32, "v1", b"B"), ("a" * 32, "v1", b"A"), ("c" * 32, "v2", b"C")])
            == 2
        )
        assert ids(ob.pending("zenoh")) == ["a" * 32, "b" * 32, "c" * 32]
        assert ob.pending("zenoh")[0].payload == b"A"
        ob.ack("zenoh", [e.seq for e in ob.pending("zenoh", limit=2)])
        assert ids(ob.pending("zenoh")) == ["c" * 32]
        assert ids(ob.pending("mavlink")) == ["a" * 32, "b" * 32, "c" * 32]
        counts = ob.counts()
        assert counts.stored == 3 and counts.pending_by_sink == {"zenoh": 1, "mavlink": 3}
        with pytest.raises(OutboxError, match="unknown sink"):
            ob.pending("nope")


def test_pending_survives_reopen_and_acked_is_not_resent(tmp_path):
    path = tmp_path / "o.sqlite"
    with Outbox(path, sinks=("zenoh",)) as ob:
        ob.put_many([(f"{k:032x}", "v1", bytes([k])) for k in range(5)])
        ob.ack("zenoh", [e.seq for e in ob.pending("zenoh", limit=3)])
        ob.record_attempt("zenoh", [e.seq for e in ob.pending("zenoh")])
    with Outbox(path, sinks=("zenoh",)) as ob:
        pend = ob.pending("zenoh")
        assert ids(pend) == [f"{3:032x}", f"{4:032x}"]
        assert [e.attempts for e in pend] == [1, 1]
        assert not ob.put(
            f"{0:032x}", "v1", b"\x00"
        )  # still known by id: a re-detection is not re-sent


def test_delivered_events_are_pruned_beyond_retention(tmp_path):
    with Outbox(tmp_path / "o.sqlite", sinks=("s",), retain_delivered=3) as ob:
        ob.put_many([(f"{k:032x}", "v", b"x") for k in range(10)])
        undelivered = ob.pending("s")[-1]
        ob.ack("s", [e.seq for e in ob.pending("s")[:-1]])
        counts = ob.counts()
        # The three newest are kept (one of them undelivered); older delivered ones are gone.
        assert counts.stored == 3 and counts.pending_by_sink == {"s": 1}
        assert ob.contains(undelivered.id) and not ob.contains(f"{0:032x}")


def test_schema_version_mismatch_is_a_clear_error(tmp_path):
    path = tmp_path / "o.sqlite"
    Outbox(path, sinks=("s",)).close()
    db = sqlite3.connect(path)
    db.execute("UPDATE meta SET value='99' WHERE key='schema_version'")
    db.commit()
    db.close()
    with pytest.raises(OutboxError, match="schema version 99"):
        Outbox(path, sinks=("s",))


def test_concurrent_writers_from_threads(tmp_path):
    """Four threads put 50 events each through one outbox: all 200 are stored, none raised or hung."""
    errors: list[BaseException] = []

    with Outbox(tmp_path / "o.sqlite", sinks=("s",)) as ob:

        def write(t):
            try:
                for k in range(50):
                    ob.put(f"{t:016x}{k:016x}", "v", b"p")
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=write, args=(t,)) for t in range(4)]
        for th in threads:
            th.start()
        for th in threads:
            th.join(timeout=30)
        assert not any(th.is_alive() for th in threads), "a writer thread did not finish in 30 s"
        assert errors == []
        expected = sorted(f"{t:016x}{k:016x}" for t in range(4) for k in range(50))
        assert ob.counts().stored == 200 and sorted(ids(ob.pending("s", limit=1000))) == expected


_WRITER = r"""
import sys
from service.outbox import Outbox
ob = Outbox(sys.argv[1], sinks=("s",))
k = 0
while True:
    ob.put(f"{k:032x}", "v", b"payload")
    print(k, flush=True)
    k += 1
"""


KILL_AFTER = 200
"""The writer is killed once it has reported this many stored events (and one more)."""


def test_kill_9_while_writing_keeps_every_committed_event(tmp_path):
    """A writer is SIGKILLed mid-stream: every event it reported as stored is there, the file opens cleanly."""
    path = tmp_path / "o.sqlite"
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=os.getcwd(),
    )
    reported = -1
    for line in proc.stdout:
        reported = int(line)
        if reported >= KILL_AFTER:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    # The kill must land mid-stream: a writer that died or stopped early proves nothing.
    assert reported == KILL_AFTER, f"the writer stopped after reporting {reported} events"
    with Outbox(path, sinks=("s",)) as ob:
        got = ids(ob.pending("s", limit=100_000))
    assert got[: reported + 1] == [f"{k:032x}" for k in range(reported + 1)]
    assert len(got) == len(set(got))


def test_a_locked_file_is_unavailable_at_once_changes_nothing_and_is_written_once_released(
    tmp_path,
):
    """Another process's write lock (``BEGIN EXCLUSIVE``): put, ack and record_attempt raise
    OutboxUnavailable after the short busy timeout, reads still work (WAL), and the same calls succeed
    once the lock is released."""
    path = tmp_path / "o.sqlite"
    with Outbox(path, sinks=("s",)) as ob:
        ob.put("a" * 32, "v", b"A")
        other = sqlite3.connect(path, isolation_level=None)
        other.execute("BEGIN EXCLUSIVE")
        try:
            with pytest.raises(OutboxUnavailable, match="locked"):
                ob.put("b" * 32, "v", b"B")
            with pytest.raises(OutboxUnavailable, match="locked"):
                ob.ack("s", [ob.pending("s")[0].seq])
            with pytest.raises(OutboxUnavailable, match="locked"):
                ob.record_attempt("s", [ob.pending("s")[0].seq])
            assert ids(ob.pending("s")) == ["a" * 32] and ob.pending_vehicles("s") == {"v": 1}
        finally:
            other.execute("ROLLBACK")
            other.close()
        assert ob.put("b" * 32, "v", b"B")
        ob.ack("s", [ob.pending("s")[0].seq])
        assert ids(ob.pending("s")) == ["b" * 32]


def _fill(ob: Outbox, size: int) -> int:
    """Events of ``size`` bytes until the outbox is full; returns how many it took."""
    k = 0
    while True:
        try:
            ob.put(f"{k:032x}", "v", bytes(size))
        except OutboxUnavailable as exc:
            assert "database or disk is full" in str(exc)
            return k
        k += 1


def test_a_full_outbox_is_unavailable_and_the_delivered_history_gives_way(tmp_path):
    """max_bytes reached (SQLite's own 'database or disk is full', as on a full disk): nothing is
    stored while every event is pending; once some are delivered, the history of delivered events is
    pruned to make room and the new event is stored."""
    with Outbox(tmp_path / "o.sqlite", sinks=("s",), max_bytes=40 * 4096) as ob:
        n = _fill(ob, 1000)
        assert n > 50
        with pytest.raises(OutboxUnavailable, match="full"):
            ob.put("f" * 32, "v", bytes(1000))
        assert ob.counts().stored == n
        ob.ack("s", [e.seq for e in ob.pending("s", limit=20)])
        assert ob.put("f" * 32, "v", bytes(1000))
        counts = ob.counts()
        assert counts.stored == n + 1 - 20 and counts.pending_by_sink == {"s": n + 1 - 20}
        # The write refused first counted nothing.
        assert ob.pending_vehicles("s") == {"v": n + 1 - 20}


def test_a_limit_lowered_below_the_files_size_holds_from_the_next_open(tmp_path):
    """SQLite keeps ``max_page_count`` at the file's page count when asked for less: the outbox gives
    up its delivered history and compacts the file so that the lowered limit holds, and says how far
    above it the events not yet delivered keep it."""
    path = tmp_path / "o.sqlite"
    with Outbox(path, sinks=("s",)) as ob:
        ob.put_many([(f"{k:032x}", "v", bytes(400)) for k in range(1000)])
        ob.ack("s", [e.seq for e in ob.pending("s", limit=990)])
    assert path.stat().st_size > 100 * 4096
    with Outbox(path, sinks=("s",), max_bytes=40 * 4096) as ob:
        assert ob.over_limit_bytes == 0
        assert ob.counts().stored == 10 and ob.counts().pending_by_sink == {"s": 10}
        assert path.stat().st_size <= 40 * 4096
        assert _fill(ob, 400) > 100
        assert path.stat().st_size <= 40 * 4096
    with Outbox(path, sinks=("s",), max_bytes=8 * 4096) as ob:
        assert ob.counts().pending_by_sink["s"] > 100
        assert 0 < ob.over_limit_bytes <= path.stat().st_size - 8 * 4096


def test_events_pending_for_a_sink_no_longer_configured_are_reported(tmp_path):
    """They are kept (not pruned) until that sink is back: the daemon says so at start instead of
    keeping them for ever without a word."""
    with Outbox(tmp_path / "o.sqlite", sinks=("zenoh", "mavlink")) as ob:
        ob.put_many([(f"{k:032d}", "v1", b"E") for k in range(5)])
        ob.ack("zenoh", [e.seq for e in ob.pending("zenoh")])
        assert ob.pending_elsewhere() == {}
    with Outbox(tmp_path / "o.sqlite", sinks=("zenoh",)) as ob:
        assert ob.pending_elsewhere() == {"mavlink": 5}
        assert ob.counts().pending_by_sink == {"zenoh": 0}


def test_pending_per_vehicle_and_each_sinks_backlog_bounded_on_its_own(tmp_path):
    """Delivery per (sink, vehicle) reads one vehicle's events; a sink's backlog beyond ``max_pending``
    gives up its oldest (counted) while the other sink still has them all."""
    with Outbox(tmp_path / "o.sqlite", sinks=("zenoh", "mavlink"), max_pending=3) as ob:
        ob.put_many([(f"{k:032x}", "va" if k % 2 else "vb", bytes([k])) for k in range(3)])
        assert ob.pending_vehicles("zenoh") == {"vb": 2, "va": 1}
        assert ids(ob.pending("zenoh", vehicle="vb")) == [f"{k:032x}" for k in (0, 2)]
        ob.ack_ids("mavlink", [f"{k:032x}" for k in range(3)])
        ob.put_many([(f"{k:032x}", "va", b"x") for k in range(3, 6)])
        # zenoh had 6 pending: its 3 oldest given up; mavlink had 3: nothing given up.
        assert ob.given_up == {"zenoh": 3}
        assert ob.pending_vehicles("zenoh") == ob.pending_vehicles("mavlink") == {"va": 3}
        assert ids(ob.pending("zenoh")) == [f"{k:032x}" for k in (3, 4, 5)]
        assert ids(ob.pending("mavlink")) == [f"{k:032x}" for k in (3, 4, 5)]
        # An event a sink had from memory while the outbox was unavailable gets no pending row for it.
        ob.put_many([("f" * 32, "vb", b"F")], delivered={"f" * 32: {"mavlink"}})
        assert "f" * 32 in ids(ob.pending("zenoh")) and "f" * 32 not in ids(ob.pending("mavlink"))
        ob.refuse_writes("the data directory was removed")
        with pytest.raises(OutboxUnavailable, match="was removed"):
            ob.put("e" * 32, "va", b"E")
        assert ids(ob.pending("mavlink")) == [f"{k:032x}" for k in (3, 4, 5)]  # reads go on


def test_a_data_directory_is_held_also_once_deleted_and_its_replacement_is_told(tmp_path):
    """The lock file alone did not hold once the folder was deleted: a second daemon made it anew and
    ran beside the first."""
    data = tmp_path / "data"
    data.mkdir()
    lock = DataDirLock(data)
    try:
        assert lock.problem() is None
        with pytest.raises(DataDirInUse, match=f"pid {os.getpid()}"):
            DataDirLock(data)
        shutil.rmtree(data)
        assert "was removed" in lock.problem()
        data.mkdir()
        with pytest.raises(DataDirInUse):
            DataDirLock(data)
        (data / "lock").write_text("")
        assert "was replaced" in lock.problem()
    finally:
        lock.close()
    DataDirLock(data).close()  # free once the holder let go


_V1_DDL = """
CREATE TABLE events (seq INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT NOT NULL UNIQUE,
                     vehicle TEXT NOT NULL, payload BLOB NOT NULL);
CREATE TABLE pending (seq INTEGER NOT NULL, sink TEXT NOT NULL, attempts INTEGER NOT NULL DEFAULT 0,
                      PRIMARY KEY (sink, seq));
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE INDEX events_vehicle ON events (vehicle, seq);
INSERT INTO meta VALUES ('schema_version', '1');
"""
"""The schema of an outbox written before the lanes were keyed in ``pending`` (version 1)."""


def test_a_version_1_file_is_migrated_and_delivers_what_it_held(tmp_path):
    """A file written by outbox schema 1: its events pending per (sink, vehicle) and its delivered
    history are read as they were, once, in order; then everything delivered is pruned."""
    path = tmp_path / "o.sqlite"
    db = sqlite3.connect(path)
    db.executescript(_V1_DDL)
    old = [
        ("c" * 32, "va", b"C"),
        ("a" * 32, "va", b"A"),
        ("b" * 32, "vb", b"B"),
        ("d" * 32, "va", b"D"),
    ]
    db.executemany("INSERT INTO events (id, vehicle, payload) VALUES (?, ?, ?)", old)
    # c: delivered to both sinks; a, d: pending for both; b: for zenoh only, tried twice.
    db.executescript(
        "INSERT INTO pending (seq, sink) VALUES (2, 'zenoh'), (2, 'mavlink'), (4, 'zenoh'), (4, 'mavlink');"
        "INSERT INTO pending VALUES (3, 'zenoh', 2);"
    )
    db.commit()
    db.close()
    with Outbox(path, sinks=("zenoh", "mavlink"), retain_delivered=0) as ob:
        assert ob.pending_vehicles("zenoh") == {"va": 2, "vb": 1}
        assert ob.pending_vehicles("mavlink") == {"va": 2}
        assert ids(ob.pending("zenoh", vehicle="va")) == ["a" * 32, "d" * 32]
        assert [(e.id, e.payload, e.attempts) for e in ob.pending("zenoh", vehicle="vb")] == [
            ("b" * 32, b"B", 2)
        ]
        ob.put("e" * 32, "vb", b"E")
        ob.ack_ids("zenoh", ["a" * 32, "b" * 32, "d" * 32, "e" * 32])
        assert ob.counts().stored == 3  # a, d, e still pending for mavlink; c pruned as delivered
        ob.ack_ids("mavlink", ["a" * 32, "d" * 32, "e" * 32])
        assert ob.counts().stored == 0
    db = sqlite3.connect(path)
    assert db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone() == ("2",)
    db.close()


def test_delivery_and_pruning_read_only_the_rows_they_touch(tmp_path):
    """With a backlog nobody acks, no statement of a delivery turn (put, the sink's vehicles, a
    lane's events, its ack and the pruning) scans the events or pending table: each is an index
    search, so another vehicle's delivery does not slow with the backlog."""
    with Outbox(tmp_path / "o.sqlite", sinks=("zenoh",), max_pending=50, retain_delivered=5) as ob:
        ob.put_many([(f"{k:032x}", "stuck", b"x") for k in range(60)])
        statements: list[str] = []
        ob._db.set_trace_callback(statements.append)
        ob.put("f" * 32, "other", b"F")
        ob.pending_vehicles("zenoh")
        ob.ack_ids("zenoh", [e.id for e in ob.pending("zenoh", vehicle="other")])
        ob._db.set_trace_callback(None)
        plans = {
            sql: [row[3] for row in ob._db.execute(f"EXPLAIN QUERY PLAN {sql}")]
            for sql in statements
            if sql.split()[0] in ("SELECT", "INSERT", "UPDATE", "DELETE")
        }
        scans = {sql: p for sql, p in plans.items() if any(d.startswith("SCAN") for d in p)}
        assert plans and not scans
