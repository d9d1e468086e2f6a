"""The durable outbox: every event is written here first, then delivered.

Events are stored in SQLite in WAL mode with ``synchronous=FULL`` so that a
committed event survives ``kill -9`` and a power cut. Each event is inserted
once by its id (``INSERT OR IGNORE``: the id is stable across retries and
restarts, so the same event produced again after a restart is not stored
twice) together with one *pending* row per sink. A sink's delivery task reads
its pending rows in insertion order, hands them to its transport, and acks the
ids the transport accepted; only then are the pending rows deleted. After a
crash the pending rows are still there, so the restarted service re-sends what
was not delivered, and nothing that was acked is sent again.

The outbox keeps delivered events for ``retain_delivered`` rows (a short
history for the status topic and for diagnosis of a fleet), then prunes the
oldest delivered ones, so the file stays bounded. ``max_bytes`` bounds the file
itself (SQLite's ``max_page_count``): beyond it a write fails as on a full disk.
A file already larger than a newly lowered ``max_bytes`` is pruned and compacted
when opened (:attr:`Outbox.over_limit_bytes` says what could not be given up).

Delivery is per (sink, vehicle): :meth:`Outbox.pending` takes one vehicle's events, and
:meth:`Outbox.pending_vehicles` says which vehicles have events waiting for a sink, so that a
vehicle nobody acknowledges holds up only its own events. Each sink's backlog is bounded on its
own (``max_pending``): beyond it the sink gives up its oldest pending events (the other sinks
still deliver them), counted in :attr:`Outbox.given_up`, so a ground station offline for days
neither fills the file nor withholds another sink's events. Nor does it slow the other vehicles:
each pending row carries its vehicle (schema version 2; a version-1 file is migrated when opened),
the lanes' counts are kept in memory with each commit, and an event no sink has pending any more
is flagged ``delivered``, so that reading a lane, the vehicles waiting, bounding a backlog and
pruning each touch only their own rows. With 100,000 events pending for one vehicle, schema 1 took
50–114 ms for each put, ack and ``pending_vehicles``; schema 2 the same as with none
(``benchmarks/bench_delivery.py --backlog``).

A write the outbox cannot make now — the disk (or ``max_bytes``) full, the file
locked by another process, an I/O error — raises :class:`OutboxUnavailable`
and changes nothing; the same call succeeds once space or the lock returns.
When the file is full, the delivered history gives way first: it is pruned and
the write tried once more. Waiting for another process's lock is bounded by
``busy_timeout_s`` so that a caller on an event loop is not held up.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import socket
import sqlite3
import struct
import threading
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from protocols.atomic_file import private_file

_TABLES = """
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    vehicle TEXT NOT NULL,
    payload BLOB NOT NULL,
    delivered INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS pending (
    seq INTEGER NOT NULL,
    sink TEXT NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0,
    vehicle TEXT NOT NULL DEFAULT '',
    PRIMARY KEY (sink, seq)
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""
# A lane's events, a sink's vehicles, whether an event is still pending anywhere and the delivered
# events to prune are each an index range: none of them reads the backlog of a vehicle nobody acks.
_INDEXES = """
CREATE INDEX IF NOT EXISTS events_vehicle ON events (vehicle, seq);
CREATE INDEX IF NOT EXISTS pending_lane ON pending (sink, vehicle, seq);
CREATE INDEX IF NOT EXISTS pending_seq ON pending (seq);
CREATE INDEX IF NOT EXISTS events_delivered ON events (seq) WHERE delivered = 1;
"""
# Version 1 had no vehicle in ``pending`` and no ``delivered`` flag: both are filled from the rows.
_MIGRATE_1_TO_2 = (
    "ALTER TABLE pending ADD COLUMN vehicle TEXT NOT NULL DEFAULT ''",
    "UPDATE pending SET vehicle = COALESCE((SELECT e.vehicle FROM events e WHERE e.seq = pending.seq), '')",
    "ALTER TABLE events ADD COLUMN delivered INTEGER NOT NULL DEFAULT 0",
    "CREATE INDEX IF NOT EXISTS pending_seq ON pending (seq)",
    "UPDATE events SET delivered = 1 WHERE NOT EXISTS (SELECT 1 FROM pending p WHERE p.seq = events.seq)",
    "UPDATE meta SET value = '2' WHERE key = 'schema_version'",
)

OUTBOX_SCHEMA_VERSION = 2
BUSY_TIMEOUT_S = 0.1
"""How long a write waits for another process's lock on the file before it is :class:`OutboxUnavailable`."""


class OutboxError(RuntimeError):
    """The outbox file cannot be used (wrong schema version, unknown sink)."""


class DataDirInUse(OutboxError):
    """Another process holds the data directory (:class:`DataDirLock`)."""


class DataDirLock:
    """Hold ``data_dir`` for the life of the process, and tell when it vanishes or is replaced.

    Two daemons on one data directory would both take frames, checkpoint the same units and publish
    the same status under one name; the second is refused (:class:`DataDirInUse`, naming the holder).
    Two holds: ``flock`` on ``data_dir/lock`` (the pid written in it), and a Unix socket in the
    abstract namespace named after the directory's absolute path. The file alone did not hold once
    the folder was deleted under the first daemon: a second one made it anew, locked the new file and
    ran beside the first; the name is not in the file system and goes only with the process.

    :meth:`problem` compares the lock file at its path with the one held (device and inode): a data
    directory removed or replaced under the daemon is a storage fault (the stores' open files are
    then ones the next start will not see).
    """

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = Path(data_dir)
        self._path = self.data_dir / "lock"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        name = hashlib.sha256(os.path.abspath(self.data_dir).encode()).hexdigest()
        address = f"\0ins-health/data/{name}"
        try:
            self._sock.bind(address)
        except OSError:
            self._sock.close()
            raise DataDirInUse(self._in_use(_peer_pid(address))) from None
        self._sock.listen(4)
        try:
            self._fd = os.open(private_file(self._path), os.O_RDWR)
        except BaseException:
            self._sock.close()
            raise
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(self._fd, 64, 0).decode("ascii", "replace").strip() or "unknown"
            self.close()
            raise DataDirInUse(self._in_use(holder)) from None
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, str(os.getpid()).encode(), 0)
        st = os.fstat(self._fd)
        self._identity = (st.st_dev, st.st_ino)

    def _in_use(self, holder: str) -> str:
        return f"{self.data_dir} is in use by another ins-health daemon (pid {holder}): give each its own data_dir"

    def problem(self) -> str | None:
        """Why the data directory is not the one held any more (None: it is)."""
        try:
            st = os.stat(self._path)
        except FileNotFoundError:
            return f"the data directory {self.data_dir} (or its lock file) was removed"
        except OSError as exc:
            return f"the data directory {self.data_dir} cannot be read ({exc})"
        if (st.st_dev, st.st_ino) != self._identity:
            return f"the data directory {self.data_dir} was replaced (its lock file is another)"
        return None

    def close(self) -> None:
        os.close(self._fd)
        self._sock.close()


def _peer_pid(address: str) -> str:
    """The pid of the process listening at an abstract Unix socket (SO_PEERCRED), or ``"unknown"``."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(address)
            pid, _uid, _gid = struct.unpack(
                "3i", probe.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12)
            )
        except OSError:
            return "unknown"
    return str(pid)


class OutboxUnavailable(OutboxError):
    """A read or write the outbox cannot make now (disk full, file locked, I/O error); nothing changed, retry later."""


@contextlib.contextmanager
def _unavailable_on_error() -> Iterator[None]:
    try:
        yield
    except sqlite3.OperationalError as exc:
        raise OutboxUnavailable(str(exc)) from exc


@dataclass(frozen=True)
class PendingEvent:
    """One event waiting for a sink: its id, vehicle, encoded bytes and how often it was tried."""

    seq: int
    id: str
    vehicle: str
    payload: bytes
    attempts: int


@dataclass(frozen=True)
class OutboxCounts:
    """Totals for the status topic."""

    stored: int
    pending_by_sink: dict[str, int]


class Outbox:
    """A durable, idempotent event store with per-sink delivery state.

    Parameters
    ----------
    path : SQLite file (created if missing); ``":memory:"`` for tests of logic only.
    sinks : names of the sinks every new event must reach (e.g. ``("zenoh", "mavlink")``).
    retain_delivered : how many delivered events to keep before pruning the oldest.
    max_bytes : the largest the file may grow (None: as large as the disk allows).
    max_pending : the most events each sink may have pending (None: unbounded); beyond it the
        sink's oldest are given up (:attr:`given_up`).
    busy_timeout_s : how long a write waits for another process's lock (:data:`BUSY_TIMEOUT_S`).

    Thread-safe: the connection is used under a lock, so a transport callback
    thread and the asyncio loop may both call it. A context manager; ``close``
    releases the file.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        sinks: Sequence[str],
        retain_delivered: int = 10_000,
        max_bytes: int | None = None,
        max_pending: int | None = None,
        busy_timeout_s: float = BUSY_TIMEOUT_S,
    ) -> None:
        if not sinks:
            raise ValueError("an outbox needs at least one sink")
        if retain_delivered < 0:
            raise ValueError(f"retain_delivered must be >= 0, got {retain_delivered!r}")
        if max_pending is not None and max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending!r}")
        self._max_pending = max_pending
        self.given_up: dict[str, int] = {}
        """Pending events each sink gave up (its backlog beyond ``max_pending``), since opened."""
        self._sinks = tuple(dict.fromkeys(str(s) for s in sinks))
        self._retain = int(retain_delivered)
        self._lock = threading.Lock()
        try:
            if str(path) != ":memory:":
                private_file(path)
            self._db = sqlite3.connect(
                str(path), isolation_level=None, check_same_thread=False, timeout=busy_timeout_s
            )
            self._db.execute("PRAGMA journal_mode=WAL")
            # FULL: a commit is on disk before put() returns (kill -9 and power loss safe).
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(_TABLES)
            self._open_schema(path)
            self._db.executescript(_INDEXES)
        except (sqlite3.DatabaseError, OSError) as exc:
            # Unlike the checkpoints it is not moved aside here: it may hold events not yet delivered.
            raise OutboxError(
                f"outbox {path} cannot be opened ({type(exc).__name__}: {exc}); it may hold events not "
                "yet delivered: move it aside (and look into it) to start with an empty outbox"
            ) from None
        self._refusal: str | None = None
        self.over_limit_bytes = 0
        """How far the file is above ``max_bytes`` once opened (0: within it); see :meth:`_bound`."""
        if max_bytes is not None:
            self._bound(int(max_bytes))
        self._waiting: dict[str, Counter[str]] = {s: Counter() for s in self._sinks}
        """Each (sink, vehicle)'s pending rows, kept with every commit: neither bounding a backlog nor
        the vehicles' counts on each delivery turn and status read the backlog."""
        for sink, vehicle, n in self._db.execute(
            "SELECT sink, vehicle, COUNT(*) FROM pending GROUP BY sink, vehicle"
        ):
            if sink in self._waiting:
                self._waiting[sink][vehicle] = int(n)

    def _count_waiting(self, delta: Mapping[tuple[str, str], int]) -> None:
        """Pending rows added (+) and removed (-) per (sink, vehicle) by a committed transaction."""
        for (sink, vehicle), n in delta.items():
            lane = self._waiting[sink]
            lane[vehicle] += n
            if lane[vehicle] <= 0:
                del lane[vehicle]

    def _open_schema(self, path: str | Path) -> None:
        """A new file marked with :data:`OUTBOX_SCHEMA_VERSION`, a version-1 file migrated to it, any other refused."""
        row = self._db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        if row is None:
            columns = {r[1] for r in self._db.execute("PRAGMA table_info(pending)")}
            # A version-1 file is marked when opened; unmarked (stopped before that) it has no events.
            version = OUTBOX_SCHEMA_VERSION if "vehicle" in columns else 1
            self._db.execute("INSERT INTO meta VALUES ('schema_version', ?)", (str(version),))
        else:
            version = int(row[0])
        if version == 1:

            def migrate() -> None:
                for sql in _MIGRATE_1_TO_2:
                    self._db.execute(sql)

            self._transaction(migrate)
        elif version != OUTBOX_SCHEMA_VERSION:
            self._db.close()
            raise OutboxError(
                f"outbox {path} has schema version {version}, this service writes {OUTBOX_SCHEMA_VERSION}: "
                "deliver or move the old file first"
            )

    def _bound(self, max_bytes: int) -> None:
        """Cap the file at ``max_bytes``; a file already larger gives up its delivered history first.

        SQLite never sets ``max_page_count`` below the file's page count, so a limit lowered
        since the file grew would silently not hold: the delivered history is pruned and the
        file compacted (``VACUUM``), and whatever is still above the limit (events not yet
        delivered) is left in :attr:`over_limit_bytes` for the caller to say.
        """
        page_bytes = int(self._db.execute("PRAGMA page_size").fetchone()[0])
        want = max(1, max_bytes // page_bytes)
        if int(self._db.execute("PRAGMA page_count").fetchone()[0]) > want:
            self._transaction(lambda: self._prune_locked(keep=0))
            self._db.execute("VACUUM")
            # In WAL mode the main file shrinks only when the compacted pages are checkpointed into it.
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        got = int(self._db.execute(f"PRAGMA max_page_count = {want}").fetchone()[0])
        self.over_limit_bytes = (got - want) * page_bytes

    def refuse_writes(self, reason: str | None) -> None:
        """Every later write is :class:`OutboxUnavailable` (``reason``); reads go on. For a file the next
        start will not see (its data directory removed or replaced): what it would take is lost there.
        ``None``: writes are taken again (the directory is back)."""
        self._refusal = reason

    def _writable(self) -> None:
        if self._refusal is not None:
            raise OutboxUnavailable(self._refusal)

    @property
    def sinks(self) -> tuple[str, ...]:
        return self._sinks

    def _check_sink(self, sink: str) -> None:
        if sink not in self._sinks:
            raise OutboxError(f"unknown sink {sink!r}; this outbox delivers to {self._sinks}")

    def put(self, event_id: str, vehicle: str, payload: bytes) -> bool:
        """Store one event durably and mark it pending for every sink.

        Returns True if the event was new, False if an event with this id was
        already stored (then nothing changes: the id is the deduplication key).
        """
        return self.put_many([(event_id, vehicle, payload)]) == 1

    def put_many(
        self,
        events: Iterable[tuple[str, str, bytes]],
        *,
        delivered: Mapping[str, Collection[str]] | None = None,
    ) -> int:
        """Store several events in one transaction; returns how many were new.

        ``delivered``: event id → the sinks that already have it (delivered from memory while
        the outbox was unavailable): no pending row is made for those.
        :class:`OutboxUnavailable` if they cannot be stored now (none is then).
        """
        rows = [(str(i), str(v), bytes(p)) for i, v, p in events]
        done = {} if delivered is None else delivered
        self._writable()
        with self._lock, _unavailable_on_error():
            try:
                return self._put_locked(rows, done)
            except sqlite3.OperationalError as exc:
                if exc.sqlite_errorname != "SQLITE_FULL":
                    raise
            # Full: the delivered history gives way to the events still to deliver.
            self._transaction(lambda: self._prune_locked(keep=0))
            return self._put_locked(rows, done)

    def _put_locked(
        self, rows: list[tuple[str, str, bytes]], done: Mapping[str, Collection[str]]
    ) -> int:
        new = 0
        delta: Counter[tuple[str, str]] = Counter()
        given_up: dict[str, int] = {}

        def insert() -> None:
            nonlocal new
            for event_id, vehicle, payload in rows:
                cur = self._db.execute(
                    "INSERT OR IGNORE INTO events (id, vehicle, payload) VALUES (?, ?, ?)",
                    (event_id, vehicle, payload),
                )
                if cur.rowcount == 1:
                    new += 1
                    seq = cur.lastrowid
                    to = [s for s in self._sinks if s not in done.get(event_id, ())]
                    self._db.executemany(
                        "INSERT INTO pending (seq, sink, vehicle) VALUES (?, ?, ?)",
                        [(seq, s, vehicle) for s in to],
                    )
                    delta.update((s, vehicle) for s in to)
                    if not to:
                        self._db.execute("UPDATE events SET delivered = 1 WHERE seq = ?", (seq,))
            if self._max_pending is not None:
                given_up.update(self._bound_pending_locked(self._max_pending, delta))
            self._prune_locked(keep=self._retain)

        self._transaction(insert)
        for sink, n in given_up.items():
            self.given_up[sink] = self.given_up.get(sink, 0) + n
        self._count_waiting(delta)
        return new

    def _bound_pending_locked(
        self, max_pending: int, delta: Counter[tuple[str, str]]
    ) -> dict[str, int]:
        """Each sink's oldest pending rows beyond ``max_pending`` deleted (counted in ``delta``); how many per sink."""
        out: dict[str, int] = {}
        for sink in self._sinks:
            now = self._waiting[sink].total() + sum(n for (s, _), n in delta.items() if s == sink)
            if now <= max_pending:
                continue
            rows = self._db.execute(
                "DELETE FROM pending WHERE sink = ? AND seq IN (SELECT seq FROM pending WHERE sink = ? "
                "ORDER BY seq LIMIT ?) RETURNING seq, vehicle",
                (sink, sink, now - max_pending),
            ).fetchall()
            self._mark_delivered_locked(s for s, _ in rows)
            delta.subtract((sink, v) for _, v in rows)
            out[sink] = len(rows)
        return out

    def _mark_delivered_locked(self, seqs: Iterable[int]) -> None:
        """Flag those of ``seqs`` no sink has pending any more: only flagged events are pruned."""
        self._db.executemany(
            "UPDATE events SET delivered = 1 WHERE seq = ? AND NOT EXISTS "
            "(SELECT 1 FROM pending p WHERE p.seq = events.seq)",
            [(int(s),) for s in seqs],
        )

    def _transaction(self, work: Callable[[], None]) -> None:
        """``work`` in one write transaction (the lock held): committed, or rolled back and raised."""
        self._db.execute("BEGIN IMMEDIATE")
        try:
            work()
            self._db.execute("COMMIT")
        except BaseException:
            # SQLite has already rolled back after some errors (a full disk).
            if self._db.in_transaction:
                self._db.execute("ROLLBACK")
            raise

    def pending(
        self, sink: str, *, vehicle: str | None = None, limit: int = 100
    ) -> list[PendingEvent]:
        """The oldest events not yet acked by ``sink`` (of ``vehicle`` only, when given), in insertion order."""
        self._check_sink(sink)
        where, args = ("", ()) if vehicle is None else (" AND p.vehicle = ?", (vehicle,))
        with self._lock, _unavailable_on_error():
            rows = self._db.execute(
                "SELECT e.seq, e.id, e.vehicle, e.payload, p.attempts FROM pending p JOIN events e ON e.seq = p.seq "
                f"WHERE p.sink = ?{where} ORDER BY p.seq LIMIT ?",
                (sink, *args, int(limit)),
            ).fetchall()
        return [PendingEvent(int(s), i, v, bytes(p), int(a)) for s, i, v, p, a in rows]

    def pending_vehicles(self, sink: str) -> dict[str, int]:
        """The vehicles with events pending for ``sink``, each with how many, oldest waiting first."""
        self._check_sink(sink)
        with self._lock, _unavailable_on_error():
            oldest = {
                v: self._db.execute(
                    "SELECT MIN(seq) FROM pending WHERE sink = ? AND vehicle = ?", (sink, v)
                ).fetchone()[0]
                for v in self._waiting[sink]
            }
            return {v: self._waiting[sink][v] for v in sorted(oldest, key=oldest.__getitem__)}

    def stored(self, *, limit: int = 1000) -> list[PendingEvent]:
        """The retained events (delivered or not), oldest first; ``attempts`` is 0 here."""
        with self._lock, _unavailable_on_error():
            rows = self._db.execute(
                "SELECT seq, id, vehicle, payload FROM events ORDER BY seq LIMIT ?", (int(limit),)
            ).fetchall()
        return [PendingEvent(int(q), i, v, bytes(p), 0) for q, i, v, p in rows]

    def ack(self, sink: str, seqs: Iterable[int]) -> None:
        """Mark events delivered to ``sink`` (they will not be sent to it again); :class:`OutboxUnavailable` as :meth:`put_many`."""
        self._ack(sink, "?", [int(s) for s in seqs])

    def ack_ids(self, sink: str, event_ids: Iterable[str]) -> None:
        """:meth:`ack` by event id (an event delivered from memory and stored meanwhile)."""
        self._ack(sink, "(SELECT seq FROM events WHERE id = ?)", [str(i) for i in event_ids])

    def _ack(self, sink: str, seq_sql: str, keys: list[int] | list[str]) -> None:
        self._check_sink(sink)
        if not keys:
            return

        acked: list[tuple[int, str]] = []

        def delete() -> None:
            acked.clear()
            for k in keys:
                acked.extend(
                    self._db.execute(
                        f"DELETE FROM pending WHERE sink = ? AND seq = {seq_sql} RETURNING seq, vehicle",
                        (sink, k),
                    )
                )
            self._mark_delivered_locked(s for s, _ in acked)
            self._prune_locked(keep=self._retain)

        self._writable()
        with self._lock, _unavailable_on_error():
            self._transaction(delete)
            gone: Counter[tuple[str, str]] = Counter()
            gone.subtract((sink, v) for _, v in acked)
            self._count_waiting(gone)

    def record_attempt(self, sink: str, seqs: Iterable[int]) -> None:
        """Count a failed delivery attempt (for the status topic and back-off)."""
        self._check_sink(sink)
        self._writable()
        with self._lock, _unavailable_on_error():
            self._db.executemany(
                "UPDATE pending SET attempts = attempts + 1 WHERE sink = ? AND seq = ?",
                [(sink, int(s)) for s in seqs],
            )

    def _prune_locked(self, *, keep: int) -> None:
        # Delete the oldest fully delivered events beyond ``keep`` most recent rows.
        self._db.execute(
            "DELETE FROM events WHERE delivered = 1 AND seq <= (SELECT COALESCE(MAX(seq), 0) FROM events) - ?",
            (keep,),
        )

    def contains(self, event_id: str) -> bool:
        """Whether an event with this id was ever stored (and not yet pruned)."""
        with self._lock, _unavailable_on_error():
            return (
                self._db.execute("SELECT 1 FROM events WHERE id = ?", (event_id,)).fetchone()
                is not None
            )

    def pending_elsewhere(self) -> dict[str, int]:
        """Events still pending for sinks this outbox does not deliver to (one removed from the
        configuration): they are kept, not pruned, until that sink is back."""
        with self._lock, _unavailable_on_error():
            rows = self._db.execute(
                "SELECT sink, COUNT(*) FROM pending GROUP BY sink ORDER BY sink"
            ).fetchall()
        return {str(k): int(n) for k, n in rows if k not in self._sinks}

    def counts(self) -> OutboxCounts:
        with self._lock, _unavailable_on_error():
            stored = self._db.execute("SELECT COUNT(*) FROM events").fetchone()[0]
            rows = dict(
                self._db.execute("SELECT sink, COUNT(*) FROM pending GROUP BY sink").fetchall()
            )
        return OutboxCounts(int(stored), {s: int(rows.get(s, 0)) for s in self._sinks})

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> Outbox:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
