"""Shared pieces of the versioned msgpack schemas (frames, events, status).

Every message on the wire is a msgpack *map* with string keys that carries a
type tag ``"type"`` and an integer schema version ``"v"``. Decoders never trust
the bytes: each field is checked for presence, type and range, and any problem
raises :class:`SchemaError` with a machine-readable :class:`Reason` (the
pipeline counts rejections by reason) and a one-line message naming the field
and the value received.
"""

from __future__ import annotations

import math
import re
from enum import Enum, StrEnum
from functools import lru_cache
from typing import Any, Literal, TypeVar, overload

import msgpack

MAX_MESSAGE_BYTES = 1 << 20
"""Default size limit of one encoded message, bytes (1 MiB): larger ones are rejected unread."""

VEHICLE_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
"""A vehicle id is one Zenoh key-expression chunk: no ``/``, wildcards, ``$``, ``?`` or ``#``; 1..64 characters."""

MAX_IMU_INDEX = 255

E = TypeVar("E", bound=Enum)
F = TypeVar("F", bound=Enum)


class Reason(StrEnum):
    """Why a message was rejected (stable names: they are status counters)."""

    TOO_LARGE = "too_large"
    MALFORMED = "malformed"
    NOT_A_MAP = "not_a_map"
    UNKNOWN_TYPE = "unknown_type"
    UNKNOWN_VERSION = "unknown_version"
    MISSING_FIELD = "missing_field"
    WRONG_TYPE = "wrong_type"
    WRONG_LENGTH = "wrong_length"
    BAD_VALUE = "bad_value"
    NON_FINITE = "non_finite"
    TIME_NOT_INCREASING = "time_not_increasing"
    KEY_MISMATCH = "key_mismatch"
    OTHER_SOURCE = "other_source"
    """A frame of a vehicle another input (MAVLink) feeds: one owner per vehicle stream."""


class SchemaError(ValueError):
    """A message that cannot be decoded; ``reason`` says why in one stable word."""

    def __init__(self, reason: Reason, message: str):
        super().__init__(f"{reason.value}: {message}")
        self.reason = Reason(reason)


def pack(obj: object) -> bytes:
    """msgpack bytes of ``obj`` (strings as str, bytes as bin: what :func:`unpack_map` reads back)."""
    data: bytes = msgpack.packb(obj, use_bin_type=True)
    return data


def unpack_map(data: bytes, *, error: type[SchemaError], max_bytes: int) -> dict[str, Any]:
    """Unpack ``data`` into a string-keyed map, or raise ``error`` with a reason.

    The size limit is checked before unpacking so an oversized message costs
    nothing; msgpack's own container limits are tied to it for the same reason.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise error(Reason.WRONG_TYPE, f"expected bytes, got {type(data).__name__}")
    size = len(data)
    if size > max_bytes:
        raise error(Reason.TOO_LARGE, f"{size} bytes exceeds the limit of {max_bytes}")
    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            max_bin_len=max_bytes,
            max_str_len=max_bytes,
            max_array_len=max_bytes,
            max_map_len=max_bytes,
            max_ext_len=0,
        )
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise error(Reason.MALFORMED, f"not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise error(Reason.NOT_A_MAP, f"top level must be a map, got {type(obj).__name__}")
    return obj


def check_header(
    obj: dict[str, Any], *, type_tag: str, versions: tuple[int, ...], error: type[SchemaError]
) -> int:
    """Check the type tag and schema version; return the version."""
    tag = obj.get("type")
    if tag != type_tag:
        raise error(Reason.UNKNOWN_TYPE, f"type tag {tag!r} is not {type_tag!r}")
    version = obj.get("v")
    if type(version) is not int or version not in versions:
        raise error(
            Reason.UNKNOWN_VERSION,
            f"{type_tag} schema version {version!r} is not supported (this build reads {list(versions)}); "
            "upgrade the reader or make the writer emit a supported version",
        )
    return version


def field(
    obj: dict[str, Any],
    name: str,
    kinds: type | tuple[type, ...],
    *,
    error: type[SchemaError],
    optional: bool = False,
) -> Any:
    """Field ``name`` of ``obj`` checked against ``kinds``; ``None`` allowed iff ``optional``.

    ``bool`` is never accepted where an ``int`` or ``float`` is expected (msgpack
    keeps them apart; Python's ``isinstance`` would not).
    """
    if name not in obj:
        if optional:
            return None
        raise error(Reason.MISSING_FIELD, f"field {name!r} is missing")
    value = obj[name]
    if value is None and optional:
        return None
    if isinstance(value, bool) and bool not in (kinds if isinstance(kinds, tuple) else (kinds,)):
        raise error(
            Reason.WRONG_TYPE, f"field {name!r} must be {_kind_names(kinds)}, got bool {value!r}"
        )
    if not isinstance(value, kinds):
        raise error(
            Reason.WRONG_TYPE,
            f"field {name!r} must be {_kind_names(kinds)}, got {type(value).__name__} {_short(value)}",
        )
    return value


@overload
def float_field(
    obj: dict[str, Any], name: str, *, error: type[SchemaError], optional: Literal[False] = False
) -> float: ...


@overload
def float_field(
    obj: dict[str, Any], name: str, *, error: type[SchemaError], optional: bool
) -> float | None: ...


def float_field(
    obj: dict[str, Any], name: str, *, error: type[SchemaError], optional: bool = False
) -> float | None:
    """A finite number (int or float on the wire) as ``float``."""
    value = field(obj, name, (int, float), error=error, optional=optional)
    if value is None:
        return None
    value = float(value)
    if not math.isfinite(value):
        raise error(Reason.NON_FINITE, f"field {name!r} must be finite, got {value!r}")
    return value


@lru_cache(maxsize=4096)
def _valid_vehicle(vehicle: str) -> bool:
    return VEHICLE_ID_PATTERN.match(vehicle) is not None


def check_vehicle(vehicle: str, *, error: type[SchemaError]) -> str:
    """A vehicle id usable as one key-expression chunk (:data:`VEHICLE_ID_PATTERN`)."""
    if not isinstance(vehicle, str):
        raise error(Reason.WRONG_TYPE, f"vehicle must be str, got {type(vehicle).__name__}")
    if not _valid_vehicle(vehicle):
        raise error(
            Reason.BAD_VALUE,
            f"vehicle id {_short(vehicle)} must match {VEHICLE_ID_PATTERN.pattern}",
        )
    return vehicle


def check_imu(imu: int, *, error: type[SchemaError]) -> int:
    """An IMU index in ``0..MAX_IMU_INDEX``."""
    if type(imu) is not int:
        raise error(Reason.WRONG_TYPE, f"imu must be int, got {type(imu).__name__}")
    if not 0 <= imu <= MAX_IMU_INDEX:
        raise error(Reason.BAD_VALUE, f"imu index {imu} outside 0..{MAX_IMU_INDEX}")
    return imu


@overload
def enum_field(
    obj: dict[str, Any],
    name: str,
    enums: tuple[type[E]],
    *,
    error: type[SchemaError],
    optional: Literal[False] = False,
) -> E: ...


@overload
def enum_field(
    obj: dict[str, Any],
    name: str,
    enums: tuple[type[E]],
    *,
    error: type[SchemaError],
    optional: bool,
) -> E | None: ...


@overload
def enum_field(
    obj: dict[str, Any],
    name: str,
    enums: tuple[type[E], type[F]],
    *,
    error: type[SchemaError],
    optional: Literal[False] = False,
) -> E | F: ...


def enum_field(
    obj: dict[str, Any],
    name: str,
    enums: tuple[type[Enum], ...],
    *,
    error: type[SchemaError],
    optional: bool = False,
) -> Enum | None:
    """A string field parsed as the first of ``enums`` that has that value."""
    value = field(obj, name, str, error=error, optional=optional)
    if value is None:
        return None
    member = first_enum(value, enums)
    if member is None:
        allowed = sorted(m.value for kind in enums for m in kind)
        raise error(
            Reason.BAD_VALUE, f"field {name!r} is {_short(value)}, expected one of {allowed}"
        )
    return member


@overload
def first_enum(value: Any, enums: tuple[type[E]]) -> E | None: ...


@overload
def first_enum(value: Any, enums: tuple[type[E], type[F]]) -> E | F | None: ...


@overload
def first_enum(value: Any, enums: tuple[type[Enum], ...]) -> Enum | None: ...


def first_enum(value: Any, enums: tuple[type[Enum], ...]) -> Enum | None:
    """``value`` as a member of the first of ``enums`` that has it (a member passes as it is), else None."""
    for kind in enums:
        if isinstance(value, kind):
            return value
        try:
            return kind(value)
        except ValueError:
            continue
    return None


def _kind_names(kinds: type | tuple[type, ...]) -> str:
    kinds = kinds if isinstance(kinds, tuple) else (kinds,)
    return " or ".join(k.__name__ for k in kinds)


def _short(value: Any, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
