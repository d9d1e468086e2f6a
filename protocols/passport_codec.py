"""Passports as JSON files on disk and msgpack bytes on the wire.

Both carry :meth:`estimators.passport.Passport.to_dict` unchanged (its type tag
``"ins.health.passport"`` and ``schema_version`` included) and decode through
:meth:`~estimators.passport.Passport.from_dict`, so one validation applies to
both. JSON is strict (no NaN/Infinity) and written atomically: a temporary file
in the target directory, flushed and fsynced, then ``os.replace``
(:mod:`protocols.atomic_file`) — a reader sees the old passport or the new
one, never a torn file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from estimators.passport import Passport, PassportError
from protocols._schema import MAX_MESSAGE_BYTES, SchemaError, pack, unpack_map
from protocols.atomic_file import atomic_write_bytes

MAX_PASSPORT_BYTES = MAX_MESSAGE_BYTES
"""Largest passport accepted as msgpack bytes or as a JSON file (1 MiB; a passport is ~5 kB)."""


class PassportCodecError(SchemaError):
    """Passport bytes that are not a msgpack map (``reason`` says why)."""


class JsonNestingError(ValueError):
    """JSON nested deeper than the parser can follow (Python's recursion limit)."""


def parse_json(text: str) -> Any:
    """Strict JSON of a passport or a store entry: ``ValueError`` for non-finite constants (NaN,
    Infinity) and invalid JSON (``json.JSONDecodeError``), :class:`JsonNestingError` for nesting
    beyond the parser's recursion limit (``[[[…]]]`` a few thousand deep: a ``RecursionError``
    traceback in every command that read it)."""
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except RecursionError:
        raise JsonNestingError("JSON nested too deeply to parse") from None


def write_passport_json(passport: Passport, path: str | os.PathLike[str]) -> None:
    """Write ``passport`` as indented JSON to ``path`` atomically (temp file + ``os.replace``)."""
    atomic_write_bytes(
        path, (json.dumps(passport.to_dict(), indent=2, allow_nan=False) + "\n").encode("utf-8")
    )


def read_passport_json(path: str | os.PathLike[str]) -> Passport:
    """Read and validate a JSON passport; unusable content raises :class:`PassportError` naming the file."""
    source = Path(path)
    # Read at most one byte past the limit: a device or a pipe (st_size 0) may never end.
    with open(source, "rb") as f:
        raw = f.read(MAX_PASSPORT_BYTES + 1)
    if len(raw) > MAX_PASSPORT_BYTES:
        raise PassportError(f"{source}: more than the passport limit of {MAX_PASSPORT_BYTES} bytes")
    try:
        text = raw.decode("utf-8-sig")  # a byte-order mark (a Windows editor's) is not JSON
    except UnicodeDecodeError as exc:
        raise PassportError(
            f"{source}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); "
            "a passport is the JSON file `ins-health calibrate` writes"
        ) from None
    try:
        obj = parse_json(text)
    except json.JSONDecodeError as exc:
        raise PassportError(
            f"{source}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from None
    except ValueError as exc:
        raise PassportError(f"{source}: {exc}") from None
    try:
        return Passport.from_dict(obj)
    except PassportError as exc:
        raise type(exc)(f"{source}: {exc}") from None


def encode_passport(passport: Passport) -> bytes:
    """msgpack bytes of :meth:`Passport.to_dict`."""
    return pack(passport.to_dict())


def decode_passport(data: bytes, *, max_bytes: int = MAX_PASSPORT_BYTES) -> Passport:
    """Validate msgpack bytes into a :class:`Passport`.

    Raises :class:`PassportCodecError` for bytes that are not a msgpack map and
    :class:`PassportError` (or its version subclass) for an invalid passport.
    """
    return Passport.from_dict(unpack_map(data, error=PassportCodecError, max_bytes=max_bytes))


def _reject_constant(name: str) -> None:
    raise ValueError(f"non-finite number {name} is not allowed")
