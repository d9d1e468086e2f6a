"""The passport store: one checksummed, versioned file per (vehicle, IMU).

Layout: ``<root>/<vehicle>/imu<n>.passport.json``. Each file is a JSON
*entry*::

    {"type": "ins.health.passport-entry", "entry_version": 1,
     "vehicle": "uav-7", "imu": 0,
     "sha256": "<hex digest of the canonical JSON of the passport>",
     "passport": { ...estimators.passport.Passport.to_dict()... }}

* **Atomic writes**: a temporary file in the same directory, flushed and
  fsynced, ``os.replace``, then the directory fsynced; a reader sees the old
  entry or the new one, never a torn file, even across a power cut.
* **Checksums**: SHA-256 over the canonical JSON of the passport map (sorted
  keys, no spaces), so a flipped bit or a hand edit that bypassed the store
  is caught before any number reaches the diagnosis.
* **Schema versions**: the entry has its own version; the passport inside
  carries its ``schema_version`` and is validated by
  :meth:`estimators.passport.Passport.from_dict` (a newer version is a
  :class:`~estimators.passport.PassportVersionError` with a hint).

A missing or unusable entry is a :class:`PassportStoreError` that names the
vehicle, the IMU, the file and the reason; :meth:`PassportStore.scan` collects
them per unit so the service starts the units that are fine and reports the
others.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from estimators.passport import Passport, PassportError
from protocols._schema import SchemaError, check_imu, check_vehicle
from protocols.atomic_file import atomic_write_bytes

ENTRY_TYPE = "ins.health.passport-entry"
ENTRY_VERSION = 1
SUPPORTED_ENTRY_VERSIONS = (1,)
MAX_ENTRY_BYTES = 1 << 20
_FILE_RE = re.compile(r"^imu(\d{1,3})\.passport\.json$")


class PassportStoreError(ValueError):
    """A unit's passport cannot be used; the message names vehicle, IMU, file and reason."""

    def __init__(self, vehicle: str, imu: int, path: Path, reason: str):
        super().__init__(f"passport of {vehicle} IMU{imu} ({path}): {reason}")
        self.vehicle, self.imu, self.path, self.reason = vehicle, imu, path, reason


def passport_checksum(passport_map: dict[str, Any]) -> str:
    """SHA-256 hex digest of the canonical JSON of a passport map."""
    text = json.dumps(passport_map, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class StoreScan:
    """What :meth:`PassportStore.scan` found: usable passports and per-unit errors."""

    passports: dict[tuple[str, int], Passport] = field(default_factory=dict)
    errors: dict[tuple[str, int], PassportStoreError] = field(default_factory=dict)


class PassportStore:
    """A directory of passport entries keyed by (vehicle, IMU index)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def path_for(self, vehicle: str, imu: int) -> Path:
        try:
            check_vehicle(vehicle, error=SchemaError)
            check_imu(imu, error=SchemaError)
        except SchemaError as exc:
            raise ValueError(f"not a valid unit key ({vehicle!r}, {imu!r}): {exc}") from None
        return self.root / vehicle / f"imu{imu}.passport.json"

    def put(self, vehicle: str, imu: int, passport: Passport) -> Path:
        """Store ``passport`` for (vehicle, IMU) atomically; returns the file written."""
        path = self.path_for(vehicle, imu)
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
        atomic_write_bytes(
            path, (json.dumps(entry, indent=2, allow_nan=False) + "\n").encode("utf-8")
        )
        return path

    def get(self, vehicle: str, imu: int) -> Passport:
        """The passport of (vehicle, IMU); :class:`PassportStoreError` if missing or unusable."""
        path = self.path_for(vehicle, imu)

        def fail(reason: str) -> PassportStoreError:
            return PassportStoreError(vehicle, imu, path, reason)

        try:
            size = path.stat().st_size
        except FileNotFoundError:
            raise fail("missing: no passport file for this unit") from None
        if size > MAX_ENTRY_BYTES:
            raise fail(f"{size} bytes exceeds the limit of {MAX_ENTRY_BYTES}")
        try:
            entry = json.loads(path.read_bytes().decode("utf-8"), parse_constant=_reject_constant)
        except (UnicodeDecodeError, ValueError) as exc:
            raise fail(f"corrupt: not valid JSON ({exc})") from None
        if not isinstance(entry, dict):
            raise fail(f"corrupt: top level must be an object, got {type(entry).__name__}")
        if entry.get("type") != ENTRY_TYPE:
            hint = (
                " (a bare passport file: add it with `ins-health store put`)"
                if entry.get("type") == "ins.health.passport"
                else ""
            )
            raise fail(f"not a passport-store entry: type {entry.get('type')!r}{hint}")
        version = entry.get("entry_version")
        if type(version) is not int or version not in SUPPORTED_ENTRY_VERSIONS:
            raise fail(
                f"entry version {version!r} is not supported (this build reads {list(SUPPORTED_ENTRY_VERSIONS)})"
            )
        if entry.get("vehicle") != vehicle or entry.get("imu") != imu:
            raise fail(
                f"entry is for {entry.get('vehicle')!r} IMU{entry.get('imu')!r}: filed under the wrong unit"
            )
        body = entry.get("passport")
        if not isinstance(body, dict):
            raise fail("corrupt: the entry has no passport object")
        try:
            digest = passport_checksum(body)
        except ValueError as exc:
            raise fail(f"corrupt: {exc}") from None
        if digest != entry.get("sha256"):
            raise fail(
                f"checksum mismatch (stored {str(entry.get('sha256'))[:12]}…, content {digest[:12]}…): the file was altered"
            )
        try:
            return Passport.from_dict(body)
        except PassportError as exc:
            raise fail(str(exc)) from None

    def keys(self) -> list[tuple[str, int]]:
        """Every (vehicle, IMU) with an entry file, sorted."""
        out: list[tuple[str, int]] = []
        if not self.root.is_dir():
            return out
        for vdir in sorted(p for p in self.root.iterdir() if p.is_dir()):
            for f in sorted(vdir.iterdir()):
                m = _FILE_RE.match(f.name)
                if m and int(m.group(1)) <= 255:
                    out.append((vdir.name, int(m.group(1))))
        return out

    def scan(self, expected: Iterable[tuple[str, int]] = ()) -> StoreScan:
        """Load every entry (and report each ``expected`` unit that has none)."""
        scan = StoreScan()
        for key in sorted(set(self.keys()) | set(expected)):
            try:
                scan.passports[key] = self.get(*key)
            except PassportStoreError as exc:
                scan.errors[key] = exc
            except ValueError as exc:
                scan.errors[key] = PassportStoreError(key[0], key[1], self.root / key[0], str(exc))
        return scan


def _reject_constant(name: str) -> None:
    raise ValueError(f"non-finite number {name} is not allowed")
