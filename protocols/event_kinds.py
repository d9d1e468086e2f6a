"""What an event names: the check that failed (:class:`Predicate`), its stream-level causes
(:class:`StreamCause`), its severity (:class:`Severity`), and the error an unusable one raises
(:class:`EventError`). :mod:`protocols.events` holds the events themselves and their schemas and
states these again; they live here so that what only names them (the pipeline's options, which
F0's configuration and so ``calibrate``'s own-session check load) does not load the events'
schemas, their coverage and hashlib.
"""

from __future__ import annotations

from enum import Enum, IntEnum, StrEnum
from typing import Any

from protocols._schema import Reason, SchemaError


class EventError(SchemaError):
    """An event or status message that cannot be used; ``reason`` says why."""


class Severity(IntEnum):
    """Event severity; values equal MAVLink's ``MAV_SEVERITY`` (0 most severe)."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


class Predicate(StrEnum):
    """Which check failed: F0…F9 of methods.md M1, gross plausibility at rest, or a stream-validity check."""

    F0 = "F0"
    F1 = "F1"
    F2 = "F2"
    F3 = "F3"
    F4 = "F4"
    F5 = "F5"
    F6 = "F6"
    F7 = "F7"
    F8 = "F8"
    F9 = "F9"
    TIMEOUT = "timeout"
    STALE = "stale"
    ERROR_DENSITY = "error_density"
    CROSS_IMU = "cross_imu"
    TEMPERATURE = "temperature"
    GROSS = "gross"
    THRUST_AXIS = "thrust_axis"
    """In flight, the accelerometer's magnitude against GNSS (:mod:`estimators.thrust_gnss`); the
    axis named is the one it sees (z, the thrust axis)."""
    CROSS_IMU_NORM = "cross_imu_norm"
    """Two IMUs' norms moved apart in flight (:mod:`estimators.cross_imu_norm`)."""

    @classmethod
    def parse(cls, value: Any) -> Predicate:
        """Accept a :class:`Predicate`, its string value, an ``int`` j (→ ``Fj``) or any Enum holding one of those."""
        if isinstance(value, Enum) and not isinstance(value, Predicate):
            value = value.value
        if type(value) is int:
            value = f"F{value}"
        try:
            return cls(value)
        except ValueError:
            raise EventError(
                Reason.BAD_VALUE,
                f"unknown predicate {value!r}; expected one of {[p.value for p in cls]}",
            ) from None


class StreamCause(StrEnum):
    """Causes named by F0 and the stream-validity checks (the M1 diagnosis uses :class:`~estimators.conventions.Cause`)."""

    OUT_OF_SHELL = "out_of_shell"
    NO_DATA = "no_data"
    STUCK_VALUE = "stuck_value"
    REJECTED_SAMPLES = "rejected_samples"
    DISAGREEMENT = "disagreement"
    TEMPERATURE_RANGE = "temperature_range"
    RECOVERED = "recovered"
    GRAVITY_MAGNITUDE = "gravity_magnitude"
    """The gross test: ``|a|`` at rest off local gravity beyond the passport's tolerances (a gyro's
    mean off its zero signal is :attr:`Cause.ZERO_SIGNAL`)."""
