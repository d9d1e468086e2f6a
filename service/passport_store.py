"""The passport store: one checksummed, versioned file per (vehicle, IMU).

The files and their format (layout, checksum, entry version) are
:mod:`protocols.passport_entry`. A missing or unusable entry is a
:class:`PassportStoreError` that names the vehicle, the IMU, the file and the
reason; :meth:`PassportStore.scan` collects them per unit so the service starts
the units that are fine and reports the others. The store remembers which
units it refused and why (:meth:`PassportStore.rejected_counts`, for the status
topic), whether at the start or when a unit's first frame makes it read one.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from estimators.passport import Passport
from protocols.passport_entry import (
    EntryProblem,
    PassportEntryError,
    entry_keys,
    entry_path,
    read_entry,
    stray_files,
    write_entry,
)


class PassportStoreError(ValueError):
    """A unit's passport cannot be used; the message names vehicle, IMU, file and reason."""

    def __init__(self, vehicle: str, imu: int, path: Path, reason: str, problem: str):
        super().__init__(f"passport of {vehicle} IMU{imu} ({path}): {reason}")
        self.vehicle, self.imu, self.path, self.reason = vehicle, imu, path, reason
        self.problem = problem
        """A short name of the reason for counters (:class:`~protocols.passport_entry.EntryProblem`, or ``bad_key``)."""


@dataclass(frozen=True)
class StoreScan:
    """What :meth:`PassportStore.scan` found: usable passports and per-unit errors."""

    passports: dict[tuple[str, int], Passport] = field(default_factory=dict)
    errors: dict[tuple[str, int], PassportStoreError] = field(default_factory=dict)
    strays: list[tuple[Path, str]] = field(default_factory=list)
    """Files in the store that are no unit's entry, with why (:func:`~protocols.passport_entry.stray_files`)."""


class PassportStore:
    """A directory of passport entries keyed by (vehicle, IMU index)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self._rejected: dict[tuple[str, int], str] = {}

    def path_for(self, vehicle: str, imu: int) -> Path:
        """The entry file of (vehicle, IMU); ``ValueError`` for an invalid key."""
        return entry_path(self.root, vehicle, imu)

    def put(self, vehicle: str, imu: int, passport: Passport) -> Path:
        """Store ``passport`` for (vehicle, IMU) atomically; returns the file written."""
        return write_entry(self.path_for(vehicle, imu), vehicle, imu, passport)

    def get(self, vehicle: str, imu: int) -> Passport:
        """The passport of (vehicle, IMU); :class:`PassportStoreError` if missing or unusable."""
        try:
            path = self.path_for(vehicle, imu)
        except ValueError as exc:
            self._rejected[(vehicle, imu)] = "bad_key"
            raise PassportStoreError(
                vehicle, imu, self.root / vehicle, str(exc), "bad_key"
            ) from None
        try:
            passport = read_entry(path, vehicle, imu)
        except PassportEntryError as exc:
            if exc.problem is EntryProblem.MISSING:
                # Not a refusal, and not kept: a peer inventing vehicle ids would grow it without end
                # (100,000 ids held 10 MiB).
                self._rejected.pop((vehicle, imu), None)
            else:
                self._rejected[(vehicle, imu)] = exc.problem.value
            raise PassportStoreError(vehicle, imu, path, str(exc), exc.problem.value) from None
        self._rejected.pop((vehicle, imu), None)
        return passport

    def rejected_counts(self) -> dict[str, int]:
        """How many units the last read of their entry refused, per reason (``missing`` is not a refusal)."""
        return dict(Counter(self._rejected.values()))

    def keys(self) -> list[tuple[str, int]]:
        """Every (vehicle, IMU) with an entry file, sorted."""
        return entry_keys(self.root)

    def scan(self, expected: Iterable[tuple[str, int]] = ()) -> StoreScan:
        """Load every entry (and report each ``expected`` unit that has none, and every stray file)."""
        scan = StoreScan(strays=stray_files(self.root))
        for key in sorted(set(self.keys()) | set(expected)):
            try:
                scan.passports[key] = self.get(*key)
            except PassportStoreError as exc:
                scan.errors[key] = exc
        return scan
