"""The passport store's files: one checksummed, versioned JSON entry per (vehicle, IMU).

Layout: ``<root>/<vehicle>/imu<n>.passport.json``. Each file is a JSON
*entry*::

    {"type": "ins.health.passport-entry", "entry_version": 1,
     "vehicle": "uav-7", "imu": 0,
     "sha256": "<hex digest of the canonical JSON of the passport>",
     "passport": { ...estimators.passport.Passport.to_dict()... }}

* **Atomic writes** (:mod:`protocols.atomic_file`): a reader sees the old entry
  or the new one, never a torn file, even across a power cut.
* **Checksums**: SHA-256 over the canonical JSON of the passport map (sorted
  keys, no spaces), so a flipped bit or a hand edit that bypassed the store
  is caught before any number reaches the diagnosis.
* **Schema versions**: the entry has its own version; the passport inside
  carries its ``schema_version`` and is validated by
  :meth:`estimators.passport.Passport.from_dict` (a newer version is a
  :class:`~estimators.passport.PassportVersionError` with a hint).

* **Only regular files of bounded size are read, without blocking**: the path is
  stat'ed first (a FIFO, a device, a directory or a symlink to one is refused
  before it is opened), opened with ``O_NONBLOCK`` and checked again with
  ``fstat`` (a file swapped in between is refused too), and at most
  :data:`MAX_ENTRY_BYTES` are read. JSON nested too deeply for the parser is a
  refusal, not a ``RecursionError``.

An unusable entry raises :class:`PassportEntryError` with a one-line reason and
a short :class:`EntryProblem` code (for counters); :mod:`service.passport_store`
names the unit and the file around it.
"""

from __future__ import annotations

import enum
import hashlib
import json
import os
import re
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from estimators.passport import Passport, PassportError
from protocols._schema import MAX_IMU_INDEX, SchemaError, check_imu, check_vehicle
from protocols.atomic_file import atomic_write_bytes
from protocols.passport_codec import JsonNestingError, parse_json

ENTRY_TYPE = "ins.health.passport-entry"
ENTRY_VERSION = 1
SUPPORTED_ENTRY_VERSIONS = (1,)
MAX_ENTRY_BYTES = 1 << 20
_FILE_RE = re.compile(r"^imu(0|[1-9]\d{0,2})\.passport\.json$")


class EntryProblem(enum.Enum):
    """Why an entry cannot be used, as a short name for counters (the message says more)."""

    MISSING = "missing"
    NOT_REGULAR = "not_a_regular_file"
    TOO_LARGE = "too_large"
    UNREADABLE = "unreadable"
    CORRUPT = "corrupt"
    NESTED = "nested_too_deeply"
    NOT_ENTRY = "not_an_entry"
    VERSION = "unsupported_version"
    MISFILED = "misfiled"
    CHECKSUM = "checksum_mismatch"
    INVALID = "invalid_passport"


class PassportEntryError(ValueError):
    """An entry that cannot be used; the message is the reason (``missing: …``, ``corrupt: …``, …)."""

    def __init__(self, message: str, problem: EntryProblem):
        super().__init__(message)
        self.problem = problem


def entry_path(root: Path, vehicle: str, imu: int) -> Path:
    """Where the entry of (vehicle, IMU) lives under ``root``; ``ValueError`` for an invalid key."""
    try:
        check_vehicle(vehicle, error=SchemaError)
        check_imu(imu, error=SchemaError)
    except SchemaError as exc:
        raise ValueError(f"not a valid unit key ({vehicle!r}, {imu!r}): {exc}") from None
    return root / vehicle / f"imu{imu}.passport.json"


def _vehicle_files(root: Path) -> Iterator[tuple[Path, Path, re.Match[str] | None]]:
    """(vehicle folder, file, the file name's entry match) for every file in a folder of ``root``."""
    if not root.is_dir():
        return
    for vdir in sorted(p for p in root.iterdir() if p.is_dir()):
        for f in sorted(vdir.iterdir()):
            yield vdir, f, _FILE_RE.match(f.name)


def entry_keys(root: Path) -> list[tuple[str, int]]:
    """Every (vehicle, IMU) with an entry file under ``root``, sorted."""
    return [
        (vdir.name, int(m.group(1)))
        for vdir, _, m in _vehicle_files(root)
        if m and int(m.group(1)) <= MAX_IMU_INDEX
    ]


def stray_files(root: Path) -> list[tuple[Path, str]]:
    """Every file under ``root`` that :func:`entry_keys` does not read, with why (hidden files skipped).

    A passport copied in by hand as ``imu01.passport.json``, ``imu300…`` or
    straight into ``root`` is never used by the daemon; saying so is the only
    way its owner learns it.
    """
    if not root.is_dir():
        return []
    out = [
        (top, f"not in a vehicle folder (entries are {root}/<vehicle>/imu<n>.passport.json)")
        for top in root.iterdir()
        if not top.name.startswith(".") and not top.is_dir()
    ]
    for vdir, f, m in _vehicle_files(root):
        if vdir.name.startswith(".") or f.name.startswith("."):
            continue
        if m is None:
            why = f"not an entry name (imu<n>.passport.json, n in 0..{MAX_IMU_INDEX} without leading zeros)"
            out.append((f, why))
        elif int(m.group(1)) > MAX_IMU_INDEX:
            out.append((f, f"IMU index {m.group(1)} is beyond 0..{MAX_IMU_INDEX}"))
    return sorted(out)


def passport_checksum(passport_map: dict[str, Any]) -> str:
    """SHA-256 hex digest of the canonical JSON of a passport map."""
    text = json.dumps(passport_map, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def write_entry(path: Path, vehicle: str, imu: int, passport: Passport) -> Path:
    """Write the entry of ``passport`` for (vehicle, IMU) to ``path`` atomically (folders created)."""
    body = passport.to_dict()
    entry = {
        "type": ENTRY_TYPE,
        "entry_version": ENTRY_VERSION,
        "vehicle": vehicle,
        "imu": imu,
        "sha256": passport_checksum(body),
        "passport": body,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_bytes(
        path, (json.dumps(entry, indent=2, allow_nan=False) + "\n").encode("utf-8")
    )


def read_entry(path: Path, vehicle: str, imu: int) -> Passport:
    """The passport in the entry file ``path``, checked to be filed for (vehicle, IMU).

    Raises :class:`PassportEntryError` for a missing, non-regular, oversized,
    corrupt, too deeply nested, altered, unsupported or misfiled entry, or an
    invalid passport in it. Never blocks on the file (module docstring).
    """
    text = _read_regular(path)
    try:
        entry = parse_json(text.decode("utf-8"))
    except JsonNestingError as exc:
        raise PassportEntryError(f"corrupt: {exc}", EntryProblem.NESTED) from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise PassportEntryError(f"corrupt: not valid JSON ({exc})", EntryProblem.CORRUPT) from None
    if not isinstance(entry, dict):
        raise PassportEntryError(
            f"corrupt: top level must be an object, got {type(entry).__name__}",
            EntryProblem.CORRUPT,
        )
    if entry.get("type") != ENTRY_TYPE:
        hint = (
            " (a bare passport file: add it with `ins-health store put`)"
            if entry.get("type") == "ins.health.passport"
            else ""
        )
        raise PassportEntryError(
            f"not a passport-store entry: type {entry.get('type')!r}{hint}", EntryProblem.NOT_ENTRY
        )
    version = entry.get("entry_version")
    if type(version) is not int or version not in SUPPORTED_ENTRY_VERSIONS:
        raise PassportEntryError(
            f"entry version {version!r} is not supported (this build reads {list(SUPPORTED_ENTRY_VERSIONS)})",
            EntryProblem.VERSION,
        )
    if entry.get("vehicle") != vehicle or entry.get("imu") != imu:
        raise PassportEntryError(
            f"entry is for {entry.get('vehicle')!r} IMU{entry.get('imu')!r}: filed under the wrong unit",
            EntryProblem.MISFILED,
        )
    body = entry.get("passport")
    if not isinstance(body, dict):
        raise PassportEntryError("corrupt: the entry has no passport object", EntryProblem.CORRUPT)
    try:
        digest = passport_checksum(body)
    except RecursionError:
        raise PassportEntryError(
            "corrupt: JSON nested too deeply to check", EntryProblem.NESTED
        ) from None
    except ValueError as exc:
        raise PassportEntryError(f"corrupt: {exc}", EntryProblem.CORRUPT) from None
    if digest != entry.get("sha256"):
        raise PassportEntryError(
            f"checksum mismatch (stored {str(entry.get('sha256'))[:12]}…, content {digest[:12]}…): the file was altered",
            EntryProblem.CHECKSUM,
        )
    try:
        return Passport.from_dict(body)
    except PassportError as exc:
        raise PassportEntryError(str(exc), EntryProblem.INVALID) from None


def _read_regular(path: Path) -> bytes:
    """The bytes of ``path`` if it is a regular file of at most :data:`MAX_ENTRY_BYTES`; never blocks."""
    try:
        before = os.stat(path)
    except FileNotFoundError:
        raise PassportEntryError(
            "missing: no passport file for this unit", EntryProblem.MISSING
        ) from None
    except OSError as exc:
        raise PassportEntryError(
            f"unreadable: {exc.strerror or exc}", EntryProblem.UNREADABLE
        ) from None
    _check_regular(before)
    try:
        # O_NONBLOCK: should a FIFO be swapped in after the stat, opening it does not wait for a writer.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise PassportEntryError(
            f"unreadable: {exc.strerror or exc}", EntryProblem.UNREADABLE
        ) from None
    try:
        _check_regular(os.fstat(fd))
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(MAX_ENTRY_BYTES + 1)
    except OSError as exc:
        raise PassportEntryError(
            f"unreadable: {exc.strerror or exc}", EntryProblem.UNREADABLE
        ) from None
    finally:
        os.close(fd)
    if len(data) > MAX_ENTRY_BYTES:
        raise PassportEntryError(
            f"more than {MAX_ENTRY_BYTES} bytes (the limit)", EntryProblem.TOO_LARGE
        )
    return data


_NOT_REGULAR = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a device"),
    (stat.S_ISBLK, "a device"),
)


def _check_regular(st: os.stat_result) -> None:
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _NOT_REGULAR if test(st.st_mode)), "not a file")
        raise PassportEntryError(
            f"not a regular file ({kind}): refused unread", EntryProblem.NOT_REGULAR
        )
    if st.st_size > MAX_ENTRY_BYTES:
        raise PassportEntryError(
            f"{st.st_size} bytes exceeds the limit of {MAX_ENTRY_BYTES}", EntryProblem.TOO_LARGE
        )
