"""Checkpoints of the per-IMU estimator state, so a restart keeps its positions.

A pipeline's ``state_dict()`` is encoded by :mod:`protocols.checkpoint_codec`
(numpy arrays keep dtype and shape exactly) and stored in SQLite (WAL,
``synchronous=FULL``) under the pipeline's key. One row per (vehicle, IMU): a checkpoint replaces the last
one atomically, so a crash leaves either the old or the new state, never a mix.
Each row carries a schema version; a row of another version is reported and
ignored (the unit starts fresh) rather than fed to an estimator that would
misread it.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from protocols.atomic_file import private_file
from protocols.checkpoint_codec import CheckpointError, decode_state, encode_state

CHECKPOINT_SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS checkpoints (
    key TEXT PRIMARY KEY,
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


class CheckpointStore:
    """Per-unit estimator state in one SQLite file. A context manager; thread-safe."""

    def __init__(self, path: str | Path) -> None:
        if str(path) != ":memory:":
            private_file(path)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
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

    def save_encoded(self, payloads: dict[str, bytes], *, now_unix_s: float | None = None) -> None:
        """:meth:`save_many` for states already encoded with :func:`encode_state`."""
        stamp = time.time() if now_unix_s is None else float(now_unix_s)
        rows = [(k, CHECKPOINT_SCHEMA_VERSION, stamp, bytes(p)) for k, p in payloads.items()]
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.executemany("INSERT OR REPLACE INTO checkpoints VALUES (?, ?, ?, ?)", rows)
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def load(self, key: str) -> Checkpoint | None:
        """The last checkpoint of ``key``, or None if there is none.

        Raises :class:`CheckpointError` for a row of another schema version or
        undecodable content.
        """
        with self._lock:
            row = self._db.execute(
                "SELECT version, saved_unix_s, payload FROM checkpoints WHERE key = ?", (key,)
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
        stamp = time.time() if now_unix_s is None else float(now_unix_s)
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute(
                    "INSERT INTO quarantined SELECT key, version, saved_unix_s, payload, ?, ? "
                    "FROM checkpoints WHERE key = ?",
                    (stamp, str(reason), key),
                )
                self._db.execute("DELETE FROM checkpoints WHERE key = ?", (key,))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def quarantined(self) -> list[tuple[str, str]]:
        """``(key, reason)`` of every checkpoint moved aside, oldest first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT key, reason FROM quarantined ORDER BY moved_unix_s, rowid"
            ).fetchall()
        return [(str(k), str(r)) for k, r in rows]

    def keys(self) -> list[str]:
        with self._lock:
            return [
                r[0]
                for r in self._db.execute("SELECT key FROM checkpoints ORDER BY key").fetchall()
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
