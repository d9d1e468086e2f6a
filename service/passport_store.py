"""The passport store: one checksummed, versioned file per (vehicle, IMU).

The files and their format (layout, checksum, entry version) are
:mod:`protocols.passport_entry`. A missing or unusable entry is a
:class:`PassportStoreError` that names the vehicle, the IMU, the file and the
reason; :meth:`PassportStore.scan` collects them per unit so the service starts
the units that are fine and reports the others.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from estimators.passport import Passport
from protocols.passport_entry import (
    PassportEntryError,
    entry_keys,
    entry_path,
    read_entry,
    write_entry,
)


class PassportStoreError(ValueError):
    """A unit's passport cannot be used; the message names vehicle, IMU, file and reason."""

    def __init__(self, vehicle: str, imu: int, path: Path, reason: str):
        super().__init__(f"passport of {vehicle} IMU{imu} ({path}): {reason}")
        self.vehicle, self.imu, self.path, self.reason = vehicle, imu, path, reason


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
        """The entry file of (vehicle, IMU); ``ValueError`` for an invalid key."""
        return entry_path(self.root, vehicle, imu)

    def put(self, vehicle: str, imu: int, passport: Passport) -> Path:
        """Store ``passport`` for (vehicle, IMU) atomically; returns the file written."""
        return write_entry(self.path_for(vehicle, imu), vehicle, imu, passport)

    def get(self, vehicle: str, imu: int) -> Passport:
        """The passport of (vehicle, IMU); :class:`PassportStoreError` if missing or unusable."""
        path = self.path_for(vehicle, imu)
        try:
            return read_entry(path, vehicle, imu)
        except PassportEntryError as exc:
            raise PassportStoreError(vehicle, imu, path, str(exc)) from None

    def keys(self) -> list[tuple[str, int]]:
        """Every (vehicle, IMU) with an entry file, sorted."""
        return entry_keys(self.root)

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
