"""File permissions: passports and session files readable by all (0644), the service's state private (0600).

A passport filed by root (``ins-health store put`` under sudo) must be readable
by the unit's service user; the outbox and the checkpoints are the service's
own and stay private. The modes hold whatever the umask: each test runs under
a umask that would give the opposite.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from estimators.session import ImuSession
from protocols.passport_codec import write_passport_json
from protocols.session_file import write_csv_session
from service.checkpoint import CheckpointStore
from service.demo import demo_passport
from service.outbox import Outbox
from service.passport_store import PassportStore


@contextmanager
def umask(mask: int) -> Iterator[None]:
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_passports_and_session_files_are_readable_by_all(tmp_path):
    passport, _g = demo_passport()
    session = ImuSession(np.arange(3) / 100.0, np.zeros((3, 3)), np.zeros((3, 3)), None)
    with umask(0o077):
        write_passport_json(passport, tmp_path / "unit.json")
        stored = PassportStore(tmp_path / "store").put("uav-1", 0, passport)
        write_csv_session(tmp_path / "s.csv", session)
    # Replacing a private file gives the new content the public mode too.
    (tmp_path / "old.json").write_text("{}")
    (tmp_path / "old.json").chmod(0o600)
    write_passport_json(passport, tmp_path / "old.json")
    modes = {p.name: oct(mode(p)) for p in (tmp_path / "unit.json", stored, tmp_path / "s.csv")}
    assert modes == {"unit.json": "0o644", stored.name: "0o644", "s.csv": "0o644"}
    assert mode(tmp_path / "old.json") == 0o644


def test_outbox_and_checkpoints_are_private_with_their_sqlite_side_files(tmp_path):
    with umask(0o000):
        with (
            Outbox(tmp_path / "data" / "outbox.sqlite", sinks=("zenoh",)) as ob,
            CheckpointStore(tmp_path / "data" / "checkpoints.sqlite") as cp,
        ):
            ob.put("a" * 32, "v1", b"event")
            cp.save("v1/0", {"n": 1})
            files = sorted((tmp_path / "data").iterdir())
            modes = {p.name: oct(mode(p)) for p in files}
    names = {
        f"{db}.sqlite{side}" for db in ("outbox", "checkpoints") for side in ("", "-wal", "-shm")
    }
    assert modes == dict.fromkeys(sorted(names), "0o600")


def test_an_existing_outbox_readable_by_all_is_made_private(tmp_path):
    path = tmp_path / "outbox.sqlite"
    Outbox(path, sinks=("zenoh",)).close()
    path.chmod(0o644)
    with Outbox(path, sinks=("zenoh",)):
        assert mode(path) == 0o600
