"""Checkpoints of the per-IMU estimator state, so a restart keeps its positions.

A pipeline's ``state_dict()`` is encoded by :mod:`protocols.checkpoint_codec`
(numpy arrays keep dtype and shape exactly) and stored in SQLite (WAL,
``synchronous=FULL``) under the pipeline's key. One row per (vehicle, IMU): a checkpoint replaces the last
one atomically, so a crash leaves either the old or the new state, never a mix.
Each row carries a schema version; a row of another version is reported and
ignored (the unit starts fresh) rather than fed to an estimator that would
misread it.

A vehicle with two or more units also has one row of its cross-IMU state
(table ``cross_imu``, :meth:`~service.pipeline.FleetProcessor.checkpoint_states`),
written in the same transaction as its units' rows, so that a restart neither
forgets nor re-raises a disagreement. A file written before that table existed
has no such rows: its vehicles resume their units and start the cross-IMU
comparison afresh.

A checkpoint the store cannot write now (disk full, the file locked by another process, an I/O
error) is :class:`CheckpointUnavailable` and changes nothing. Waiting for another process's lock
is bounded by :data:`BUSY_TIMEOUT_S`, as the outbox's, since the daemon writes from its event
loop. The daemon does not stop for it (:class:`SaveFailures`): checkpoints only save work, the
units' state stays in memory and is written once the store takes writes again.
"""

from __future__ import annotations

import math
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from protocols._schema import check_imu, check_vehicle
from protocols.atomic_file import private_file
from protocols.checkpoint_codec import CheckpointError, decode_state, encode_state
from protocols.events import EventError
from service.log_setup import logger
from service.outage import Outage

CHECKPOINT_SCHEMA_VERSION = 1
BUSY_TIMEOUT_S = 0.1
"""How long a write waits for another process's lock on the file before it is :class:`CheckpointUnavailable`
(SQLite's default, 5 s, held the daemon's whole event loop that long at each attempt)."""
RETRY_MIN_S = 0.1
RETRY_MAX_S = 5.0
"""A checkpoint that failed is tried again after :data:`RETRY_MIN_S`, doubling up to this."""

log = logger("checkpoints")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS checkpoints (
    key TEXT PRIMARY KEY,
    version INTEGER NOT NULL,
    saved_unix_s REAL NOT NULL,
    payload BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS cross_imu (
    vehicle TEXT PRIMARY KEY,
    version INTEGER NOT NULL,
    saved_unix_s REAL NOT NULL,
    payload BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS quarantined (
    key TEXT NOT NULL,
    version INTEGER,
    saved_unix_s REAL,
    payload BLOB,
    moved_unix_s REAL NOT NULL,
    reason TEXT NOT NULL
);
"""


@dataclass(frozen=True)
class Checkpoint:
    """One stored state: its key, when it was saved (Unix time, s) and the state dict."""

    key: str
    saved_unix_s: float
    state: dict[str, Any]


def checkpoint_unit(key: str) -> tuple[str, int]:
    """(vehicle, IMU) of a unit's checkpoint key ``"<vehicle>/<imu>"``; :class:`CheckpointError`
    for a key that names no unit (a row written by hand, or by another program)."""
    vehicle, sep, imu = key.rpartition("/")
    try:
        if not sep or not imu.isdigit():
            raise ValueError(f"not <vehicle>/<imu>: {key!r}")
        return check_vehicle(vehicle, error=EventError), check_imu(int(imu), error=EventError)
    except ValueError as exc:  # EventError is one
        raise CheckpointError(f"checkpoint key names no unit ({exc})") from None


def open_checkpoints(path: Path) -> tuple[CheckpointStore, str | None]:
    """The checkpoint store at ``path``, and why a file that could not be opened was moved aside.

    Checkpoints only save work (a unit without one starts fresh), so a file SQLite cannot open
    (cut, overwritten, a directory in its place) is renamed ``<name>.unreadable-<unix time>``, its
    journal files with it, and a new one is made: refusing to start would stop the service for
    good under its supervisor. None when the file opened.
    """
    try:
        return CheckpointStore(path), None
    except (sqlite3.DatabaseError, OSError) as exc:
        why = f"{type(exc).__name__}: {exc}"
    aside = path.with_name(f"{path.name}.unreadable-{int(time.time())}")
    for suffix in ("", "-wal", "-shm"):
        part = path.with_name(path.name + suffix)
        if part.exists() or part.is_symlink():
            part.rename(aside.with_name(aside.name + suffix))
    return CheckpointStore(path), f"{path} could not be opened ({why}); moved aside to {aside}"


class CheckpointUnavailable(RuntimeError):
    """A checkpoint that cannot be written now (disk full, file locked, I/O error); nothing changed."""


class SaveFailures:
    """Checkpoints the store could not write: counted, logged once per episode, retried with back-off.

    A failed save is not an error of the daemon: the units' state is in memory and their checkpoint
    is written by the next attempt (after :attr:`retry_s`, :data:`RETRY_MIN_S` doubling up to
    :data:`RETRY_MAX_S`), with the state they have then. The log says when the store becomes
    unavailable (with the reason) and when a checkpoint is saved again (after how long); the status
    topic carries ``checkpoints.unavailable`` (1 while the last attempt failed),
    ``checkpoints.write_failures`` (attempts that failed) and ``checkpoints.unavailable_episodes``.

    ``clock``: a monotonic clock (how long the store was unavailable).
    """

    def __init__(self, *, clock: Callable[[], float]) -> None:
        self._outage = Outage(clock)
        self.retry_s = RETRY_MIN_S
        """How long to wait before the next attempt, after a failed one."""

    @property
    def unavailable(self) -> bool:
        """Whether the last checkpoint attempt failed."""
        return self._outage.ongoing

    def unavailable_s(self) -> float | None:
        """How long saves have failed, s (None: the last one was saved)."""
        return self._outage.lasted()

    def failed(self, exc: CheckpointUnavailable, units: int) -> None:
        """An attempt to save ``units`` units' state failed: counted, :attr:`retry_s` set for the next one."""
        if self._outage.failed():
            log.error(
                "checkpoints cannot be saved (%s): the state of %d unit(s) is kept in memory and saved "
                "once the store takes writes again (retrying; fault detection goes on, a restart "
                "meanwhile resumes from the last checkpoint saved)",
                exc, units,
            )  # fmt: skip
        self.retry_s = min(RETRY_MAX_S, RETRY_MIN_S * 2.0 ** (self._outage.failures_now - 1))

    def saved(self, units: int) -> None:
        """A checkpoint of ``units`` units was written: the end of an episode of failures, if any."""
        failed = self._outage.failures_now
        if (lasted := self._outage.ended()) is None:
            return
        log.warning(
            "checkpoints saved again after %.1f s unavailable (%d attempt(s) failed): %d unit(s) written",
            lasted, failed, units,
        )  # fmt: skip
        self.retry_s = RETRY_MIN_S

    def counters(self) -> dict[str, int]:
        """For the status topic (class docstring)."""
        return {
            "checkpoints.unavailable": int(self.unavailable),
            **self._outage.counters("checkpoints"),
        }


class CheckpointStore:
    """Per-unit estimator state in one SQLite file. A context manager; thread-safe.

    ``busy_timeout_s``: how long a write waits for another process's lock (:data:`BUSY_TIMEOUT_S`).
    """

    def __init__(self, path: str | Path, *, busy_timeout_s: float = BUSY_TIMEOUT_S) -> None:
        if str(path) != ":memory:":
            private_file(path)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(
            str(path), isolation_level=None, check_same_thread=False, timeout=busy_timeout_s
        )
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)

    def save(self, key: str, state: dict[str, Any], *, now_unix_s: float | None = None) -> None:
        """Replace the checkpoint of ``key`` atomically."""
        self.save_many({key: state}, now_unix_s=now_unix_s)

    def save_many(
        self, states: dict[str, dict[str, Any]], *, now_unix_s: float | None = None
    ) -> None:
        """Replace several checkpoints in one transaction (all or none)."""
        self.save_encoded({k: encode_state(s) for k, s in states.items()}, now_unix_s=now_unix_s)

    def save_encoded(
        self,
        payloads: dict[str, bytes],
        *,
        cross: dict[str, bytes] | None = None,
        now_unix_s: float | None = None,
    ) -> None:
        """:meth:`save_many` for states already encoded with :func:`encode_state`.

        ``cross``: encoded cross-IMU states by vehicle, written in the same transaction.
        """
        stamp = time.time() if now_unix_s is None else float(now_unix_s)
        rows = [(k, CHECKPOINT_SCHEMA_VERSION, stamp, bytes(p)) for k, p in payloads.items()]
        vehicles = [
            (v, CHECKPOINT_SCHEMA_VERSION, stamp, bytes(p)) for v, p in (cross or {}).items()
        ]
        with self._lock:
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    self._db.executemany(
                        "INSERT OR REPLACE INTO checkpoints VALUES (?, ?, ?, ?)", rows
                    )
                    self._db.executemany(
                        "INSERT OR REPLACE INTO cross_imu VALUES (?, ?, ?, ?)", vehicles
                    )
                    self._db.execute("COMMIT")
                except BaseException:
                    # SQLite has already rolled back after some errors (a full disk).
                    if self._db.in_transaction:
                        self._db.execute("ROLLBACK")
                    raise
            except sqlite3.OperationalError as exc:
                raise CheckpointUnavailable(str(exc)) from exc

    def load(self, key: str) -> Checkpoint | None:
        """The last checkpoint of ``key``, or None if there is none.

        Raises :class:`CheckpointError` for a row of another schema version or
        undecodable content.
        """
        return self._load("checkpoints", "key", key)

    def load_cross(self, vehicle: str) -> Checkpoint | None:
        """The last cross-IMU state of ``vehicle`` (None if none); :class:`CheckpointError` as :meth:`load`."""
        return self._load("cross_imu", "vehicle", vehicle)

    def _load(self, table: str, column: str, key: str) -> Checkpoint | None:
        with self._lock:
            row = self._db.execute(
                f"SELECT version, saved_unix_s, payload FROM {table} WHERE {column} = ?", (key,)
            ).fetchone()
        if row is None:
            return None
        version, saved, payload = row
        if int(version) != CHECKPOINT_SCHEMA_VERSION:
            raise CheckpointError(
                f"checkpoint {key!r} has schema version {version}, expected {CHECKPOINT_SCHEMA_VERSION}"
            )
        try:
            state = decode_state(bytes(payload))
        except CheckpointError as exc:
            raise CheckpointError(f"checkpoint {key!r} cannot be decoded: {exc}") from None
        return Checkpoint(key, float(saved), state)

    def quarantine(self, key: str, reason: str, *, now_unix_s: float | None = None) -> None:
        """Move the checkpoint of ``key`` aside (table ``quarantined``, with why), so the unit starts fresh.

        The row is kept for inspection but never loaded again: a state that failed once would fail
        on every later start.
        """
        self._move_aside("checkpoints", "key", key, key, reason, now_unix_s)

    def quarantine_cross(
        self, vehicle: str, reason: str, *, now_unix_s: float | None = None
    ) -> None:
        """:meth:`quarantine` for a vehicle's cross-IMU state (kept as ``"<vehicle>/cross_imu"``)."""
        self._move_aside(
            "cross_imu", "vehicle", vehicle, f"{vehicle}/cross_imu", reason, now_unix_s
        )

    def _move_aside(
        self, table: str, column: str, key: str, kept_as: str, reason: str, now: float | None
    ) -> None:
        stamp = time.time() if now is None else float(now)
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute(
                    f"INSERT INTO quarantined SELECT ?, version, saved_unix_s, payload, ?, ? "
                    f"FROM {table} WHERE {column} = ?",
                    (kept_as, stamp, str(reason), key),
                )
                self._db.execute(f"DELETE FROM {table} WHERE {column} = ?", (key,))
                self._db.execute("COMMIT")
            except BaseException:
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
                raise

    def quarantined(self) -> list[tuple[str, str]]:
        """``(key, reason)`` of every checkpoint moved aside, oldest first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT key, reason FROM quarantined ORDER BY moved_unix_s, rowid"
            ).fetchall()
        return [(str(k), str(r)) for k, r in rows]

    def keys(self, *, saved_since_unix_s: float = -math.inf) -> list[str]:
        """Keys of the units' checkpoints, those saved at or after ``saved_since_unix_s`` only."""
        with self._lock:
            return [
                r[0]
                for r in self._db.execute(
                    "SELECT key FROM checkpoints WHERE saved_unix_s >= ? ORDER BY key",
                    (saved_since_unix_s,),
                ).fetchall()
            ]

    def delete(self, key: str) -> None:
        with self._lock:
            self._db.execute("DELETE FROM checkpoints WHERE key = ?", (key,))

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> CheckpointStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
