"""Checkpoint payloads: a pipeline's state dict as msgpack bytes.

A state dict holds plain dicts, lists, numbers, strings and numpy arrays. It is
encoded as one msgpack value; numpy arrays become an extension type (code 1)
whose data is a msgpack ``[dtype string, shape]`` header followed by the raw
array bytes, so dtype and shape come back exactly. Tuples are written as lists.
Where and under which schema version the payloads are kept is the service's
business (:mod:`service.checkpoint`).
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

_NDARRAY_EXT = 1


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (bytes that are not a state dict, or a stored row of another version)."""


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        # Not ascontiguousarray: it turns a 0-d array into a 1-d one.
        arr = obj if obj.flags.c_contiguous else obj.copy(order="C")
        if arr.dtype.hasobject:
            raise TypeError("object arrays cannot be checkpointed")
        header: bytes = msgpack.packb([arr.dtype.str, list(arr.shape)])
        return msgpack.ExtType(_NDARRAY_EXT, header + arr.tobytes())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, tuple):
        return list(obj)
    raise TypeError(f"cannot checkpoint a value of type {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> Any:
    if code != _NDARRAY_EXT:
        return msgpack.ExtType(code, data)
    unpacker = msgpack.Unpacker(raw=False)
    unpacker.feed(data)
    dtype_str, shape = unpacker.unpack()
    offset = unpacker.tell()
    return np.frombuffer(data[offset:], dtype=np.dtype(dtype_str)).reshape(shape).copy()


def encode_state(state: dict[str, Any]) -> bytes:
    """msgpack bytes of a state dict (numpy arrays kept with dtype and shape).

    Raises ``TypeError`` for a value that has no encoding (an object array, an arbitrary object).
    """
    payload: bytes = msgpack.packb(state, default=_default, use_bin_type=True, strict_types=False)
    return payload


def decode_state(payload: bytes) -> dict[str, Any]:
    """The inverse of :func:`encode_state`; raises :class:`CheckpointError` for any other bytes."""
    try:
        state = msgpack.unpackb(payload, ext_hook=_ext_hook, raw=False, strict_map_key=False)
    except (ValueError, TypeError, KeyError, msgpack.UnpackException) as exc:
        raise CheckpointError(f"not a checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"a checkpoint must decode to a dict, got {type(state).__name__}")
    return state
