"""IMU frames: :class:`SampleBatch` and its versioned msgpack schema.

A *frame* carries a batch of consecutive samples of one IMU of one vehicle, in
SI units (:mod:`estimators.conventions`). Every source (Zenoh, MAVLink, log
replay) produces :class:`SampleBatch` values; only this module knows the bytes.

Wire schema, version 2
----------------------
One msgpack map with string keys:

=============  ===========  ==========================================================
key            msgpack      meaning
=============  ===========  ==========================================================
``type``       str          ``"ins.imu.frame"`` (type tag)
``v``          int          schema version, ``1`` or ``2``
``vehicle``    str          vehicle id, one key-expression chunk (``[A-Za-z0-9][A-Za-z0-9_.-]{0,63}``)
``imu``        int          IMU index on the vehicle, 0..255
``seq``        int          frame sequence number per (vehicle, imu), 0..2⁶⁴−1, +1 per frame
``n``          int          number of samples N, 1..:data:`MAX_SAMPLES`
``dtype``      str          element type of accel/gyro/temp: ``"<f8"`` or ``"<f4"``
``t_s``        bin          N little-endian float64: sample times, s, strictly increasing
``accel_mps2`` bin          N×3 values of ``dtype``, row-major (sample, axis x y z), m/s²
``gyro_rps``   bin          N×3 values of ``dtype``, row-major, rad/s
``temp_c``     bin or nil   N values of ``dtype``, °C; nil when the IMU gives no temperature
``run``        int          version 2 only: the publisher's run id, 0..2⁶⁴−1, drawn anew each
                            time it starts; a new id tells the daemon a new run begins there
                            (its positions and diagnosis start afresh) without waiting for the
                            ``seq`` and clock going back to show it
=============  ===========  ==========================================================

A frame is written at the lowest version that holds it: version 1 without a
run id, version 2 with one. Both are read.

Time stays float64 whatever ``dtype`` says: a float32 time stamp loses
milliseconds after a few hours. ``"<f4"`` halves the frame for high-rate links;
its 2⁻²⁴ relative resolution is far below any MEMS or tactical-grade noise.

Validation policy of :func:`decode_frame`
----------------------------------------
Everything is checked and any problem raises :class:`FrameError` with a
:class:`~protocols._schema.Reason`: size over the limit (before unpacking),
malformed msgpack, unknown type tag or version, missing fields, wrong types,
byte lengths that do not match ``n`` and ``dtype``, and **non-finite values**
(NaN or ±Inf in any array: the whole frame is rejected with ``non_finite``;
a frame is one atomic sensor read-out, so a NaN taints its neighbours'
trustworthiness too, and the pipeline counts it rather than guessing), and
time stamps that do not strictly increase inside the frame. Ordering *across*
frames (duplicated or out-of-order ``seq``, time jumps) is the pipeline's job.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Literal, Self, overload

import numpy as np

from estimators.session import ImuSession
from protocols._schema import (
    MAX_MESSAGE_BYTES,
    Reason,
    SchemaError,
    check_header,
    check_imu,
    check_vehicle,
    field,
    pack,
    unpack_map,
)

FRAME_TYPE = "ins.imu.frame"
FRAME_VERSION = 2
SUPPORTED_FRAME_VERSIONS = (1, 2)
MAX_FRAME_BYTES = MAX_MESSAGE_BYTES
"""Default size limit of one encoded frame, bytes."""
MAX_SAMPLES = 65_536
"""Largest number of samples one frame may carry."""
MAX_SEQ = (1 << 64) - 1


class FrameError(SchemaError):
    """A frame that cannot be used; ``reason`` (:class:`~protocols._schema.Reason`) says why."""


class SampleDtype(StrEnum):
    """Element type of the accel/gyro/temp arrays on the wire."""

    F64 = "<f8"
    F32 = "<f4"


@dataclass(frozen=True, eq=False)
class SampleBatch:
    """Consecutive samples of one IMU of one vehicle, SI units.

    Attributes
    ----------
    vehicle : vehicle id (one key-expression chunk, see :data:`protocols._schema.VEHICLE_ID_PATTERN`).
    imu : IMU index on the vehicle, 0..255.
    seq : frame sequence number per (vehicle, imu), +1 per frame.
    t_s : (N,) sample times, s, strictly increasing (checked by :func:`decode_frame`).
    accel_mps2 : (N, 3) specific force, m/s², sensor axes.
    gyro_rps : (N, 3) angular rate, rad/s, sensor axes.
    temp_c : (N,) temperature, °C, or None.
    run : the publisher's run id (schema version 2), or None when the source gives none.

    The arrays are float64 and read-only (a batch is a value that travels;
    nobody converts it in place). Construction checks types and shapes and
    raises :class:`FrameError`; finiteness and time order are the decoder's
    checks, so a source can still hand a faithful bad read-out to the pipeline.
    """

    vehicle: str
    imu: int
    seq: int
    t_s: np.ndarray
    accel_mps2: np.ndarray
    gyro_rps: np.ndarray
    temp_c: np.ndarray | None = None
    run: int | None = None

    def __post_init__(self) -> None:
        check_vehicle(self.vehicle, error=FrameError)
        check_imu(self.imu, error=FrameError)
        if type(self.seq) is not int or not 0 <= self.seq <= MAX_SEQ:
            raise FrameError(Reason.BAD_VALUE, f"seq must be an int in 0..2^64-1, got {self.seq!r}")
        if self.run is not None and (type(self.run) is not int or not 0 <= self.run <= MAX_SEQ):
            raise FrameError(Reason.BAD_VALUE, f"run must be an int in 0..2^64-1, got {self.run!r}")
        t = _frozen_f64(self.t_s, "t_s")
        n = t.shape[0]
        if t.ndim != 1 or not 1 <= n <= MAX_SAMPLES:
            raise FrameError(
                Reason.WRONG_LENGTH,
                f"t_s must have shape (N,) with 1 <= N <= {MAX_SAMPLES}, got {t.shape}",
            )
        object.__setattr__(self, "t_s", t)
        for name, shape in (("accel_mps2", (n, 3)), ("gyro_rps", (n, 3)), ("temp_c", (n,))):
            value = getattr(self, name)
            if value is None and name == "temp_c":
                continue
            arr = _frozen_f64(value, name)
            if arr.shape != shape:
                raise FrameError(
                    Reason.WRONG_LENGTH, f"{name} must have shape {shape}, got {arr.shape}"
                )
            object.__setattr__(self, name, arr)

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])

    def to_session(self) -> ImuSession:
        """The samples as an :class:`~estimators.session.ImuSession` (arrays shared, read-only)."""
        return ImuSession(self.t_s, self.accel_mps2, self.gyro_rps, self.temp_c)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SampleBatch):
            return NotImplemented
        if self.temp_c is None or other.temp_c is None:
            same_temp = self.temp_c is None and other.temp_c is None
        else:
            same_temp = np.array_equal(self.temp_c, other.temp_c)
        return (
            (self.vehicle, self.imu, self.seq, self.run)
            == (other.vehicle, other.imu, other.seq, other.run)
            and np.array_equal(self.t_s, other.t_s)
            and np.array_equal(self.accel_mps2, other.accel_mps2)
            and np.array_equal(self.gyro_rps, other.gyro_rps)
            and same_temp
        )

    __hash__ = None  # type: ignore[assignment]  # equal by value, mutable-looking arrays: not hashable


class BatchSource(ABC):
    """A live source of :class:`SampleBatch` values for asyncio (Zenoh, MAVLink).

    ``await source.get()`` or ``async for batch in source``; ``with source:``
    closes it. Iteration ends when :meth:`get` raises ``EOFError``.
    """

    @abstractmethod
    async def get(self) -> SampleBatch:
        """The next batch (waits); ``EOFError`` once the source is closed and drained."""

    @abstractmethod
    def close(self) -> None:
        """Stop receiving; a waiting consumer finishes what is queued, then stops."""

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> SampleBatch:
        try:
            return await self.get()
        except EOFError:
            raise StopAsyncIteration from None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _frozen_f64(value: object, name: str) -> np.ndarray:
    if isinstance(value, (str, bytes)) or value is None:
        raise FrameError(
            Reason.WRONG_TYPE, f"{name} must be a numeric array, got {type(value).__name__}"
        )
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise FrameError(Reason.WRONG_TYPE, f"{name} must be a numeric array ({exc})") from None
    if arr.flags.writeable:
        # A copy, so freezing never reaches back into the caller's array.
        arr = np.array(arr, dtype=np.float64, order="C")
        arr.flags.writeable = False
    return arr


def concat_batches(batches: Iterable[SampleBatch]) -> ImuSession:
    """Join consecutive batches of one IMU into one :class:`~estimators.session.ImuSession`.

    Temperature is kept only if every batch carries it. Raises ``ValueError``
    for an empty input or batches of different (vehicle, imu).
    """
    batches = list(batches)
    if not batches:
        raise ValueError("no batches to join")
    ids = {(b.vehicle, b.imu) for b in batches}
    if len(ids) != 1:
        raise ValueError(
            f"batches of several IMUs cannot be joined into one session: {sorted(ids)}"
        )
    with_temp = all(b.temp_c is not None for b in batches)
    return ImuSession(
        np.concatenate([b.t_s for b in batches]),
        np.concatenate([b.accel_mps2 for b in batches]),
        np.concatenate([b.gyro_rps for b in batches]),
        np.concatenate([b.temp_c for b in batches]) if with_temp else None,
    )


def split_session(
    session: ImuSession,
    *,
    vehicle: str,
    imu: int,
    batch_samples: int,
    first_seq: int = 0,
    run: int | None = None,
) -> Iterator[SampleBatch]:
    """The samples of one IMU's session as consecutive batches of ``batch_samples`` (the last may be shorter).

    The inverse of :func:`concat_batches`; ``seq`` counts from ``first_seq``; every batch
    carries the run id ``run``. Raises
    ``ValueError`` for a session without accelerometer or gyro samples.
    """
    accel, gyro, temp = session.accel_mps2, session.gyro_rps, session.temp_c
    if accel is None or gyro is None:
        raise ValueError("a frame needs accelerometer and gyro samples")
    if batch_samples < 1:
        raise ValueError(f"batch_samples must be >= 1, got {batch_samples}")
    cuts = (slice(i, i + batch_samples) for i in range(0, session.n_samples, batch_samples))
    return (
        SampleBatch(
            vehicle,
            imu,
            first_seq + k,
            session.t_s[cut],
            accel[cut],
            gyro[cut],
            None if temp is None else temp[cut],
            run,
        )
        for k, cut in enumerate(cuts)
    )


def encode_frame(batch: SampleBatch, *, dtype: SampleDtype = SampleDtype.F64) -> bytes:
    """Encode a batch at the lowest schema version that holds it (see the module docstring).

    Encoding is faithful: non-finite values are written as they are, and it is
    :func:`decode_frame` that rejects them (so tests and fault injectors can
    produce such frames through the ordinary path).
    """
    dt = SampleDtype(dtype)
    run = {} if batch.run is None else {"run": batch.run}
    return pack(
        {
            "type": FRAME_TYPE,
            "v": 1 if batch.run is None else FRAME_VERSION,
            **run,
            "vehicle": batch.vehicle,
            "imu": batch.imu,
            "seq": batch.seq,
            "n": batch.n_samples,
            "dtype": dt.value,
            "t_s": batch.t_s.astype("<f8", copy=False).tobytes(),
            "accel_mps2": batch.accel_mps2.astype(dt.value, copy=False).tobytes(),
            "gyro_rps": batch.gyro_rps.astype(dt.value, copy=False).tobytes(),
            "temp_c": None
            if batch.temp_c is None
            else batch.temp_c.astype(dt.value, copy=False).tobytes(),
        }
    )


def decode_frame(data: bytes, *, max_bytes: int = MAX_FRAME_BYTES) -> SampleBatch:
    """Decode and validate one frame; raise :class:`FrameError` with a reason on any problem.

    See the module docstring for the schema and the validation policy.

    Parameters
    ----------
    data : the encoded frame.
    max_bytes : size limit; a larger frame is rejected (``too_large``) before unpacking.
    """
    obj = unpack_map(data, error=FrameError, max_bytes=max_bytes)
    version = check_header(
        obj, type_tag=FRAME_TYPE, versions=SUPPORTED_FRAME_VERSIONS, error=FrameError
    )
    vehicle = check_vehicle(field(obj, "vehicle", str, error=FrameError), error=FrameError)
    imu = check_imu(field(obj, "imu", int, error=FrameError), error=FrameError)
    seq = field(obj, "seq", int, error=FrameError)
    if not 0 <= seq <= MAX_SEQ:
        raise FrameError(Reason.BAD_VALUE, f"seq {seq} outside 0..2^64-1")
    run = field(obj, "run", int, error=FrameError, optional=True) if version >= 2 else None
    if run is not None and not 0 <= run <= MAX_SEQ:
        raise FrameError(Reason.BAD_VALUE, f"run {run} outside 0..2^64-1")
    n = field(obj, "n", int, error=FrameError)
    if not 1 <= n <= MAX_SAMPLES:
        raise FrameError(Reason.BAD_VALUE, f"sample count n={n} outside 1..{MAX_SAMPLES}")
    dtype_text = field(obj, "dtype", str, error=FrameError)
    try:
        dtype = SampleDtype(dtype_text)
    except ValueError:
        raise FrameError(
            Reason.BAD_VALUE, f"dtype {dtype_text!r} is not one of {[d.value for d in SampleDtype]}"
        ) from None

    t_s = _array(obj, "t_s", SampleDtype.F64, (n,))
    accel = _array(obj, "accel_mps2", dtype, (n, 3))
    gyro = _array(obj, "gyro_rps", dtype, (n, 3))
    temp = _array(obj, "temp_c", dtype, (n,), optional=True)
    for name, arr in (("t_s", t_s), ("accel_mps2", accel), ("gyro_rps", gyro), ("temp_c", temp)):
        if arr is not None and not np.isfinite(arr).all():
            raise FrameError(
                Reason.NON_FINITE, f"{name} holds {int((~np.isfinite(arr)).sum())} NaN/Inf value(s)"
            )
    if n > 1 and not np.all(np.diff(t_s) > 0):
        raise FrameError(Reason.TIME_NOT_INCREASING, "t_s must strictly increase within a frame")
    return SampleBatch(vehicle, imu, seq, t_s, accel, gyro, temp, run)


@overload
def _array(
    obj: dict[str, Any],
    name: str,
    dtype: SampleDtype,
    shape: tuple[int, ...],
    *,
    optional: Literal[False] = False,
) -> np.ndarray: ...


@overload
def _array(
    obj: dict[str, Any], name: str, dtype: SampleDtype, shape: tuple[int, ...], *, optional: bool
) -> np.ndarray | None: ...


def _array(
    obj: dict[str, Any],
    name: str,
    dtype: SampleDtype,
    shape: tuple[int, ...],
    *,
    optional: bool = False,
) -> np.ndarray | None:
    raw = field(obj, name, bytes, error=FrameError, optional=optional)
    if raw is None:
        return None
    item = np.dtype(dtype.value).itemsize
    expected = item * int(np.prod(shape))
    if len(raw) != expected:
        raise FrameError(
            Reason.WRONG_LENGTH,
            f"{name} has {len(raw)} bytes, expected {expected} for shape {shape} of {dtype.value}",
        )
    arr = np.frombuffer(raw, dtype=dtype.value).reshape(shape)
    # frombuffer on bytes is already read-only; float32 (or a big-endian host) needs a new array.
    if arr.dtype != np.float64:
        arr = arr.astype(np.float64)
        arr.flags.writeable = False
    return arr
