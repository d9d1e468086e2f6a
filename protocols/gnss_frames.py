"""The GNSS frame: a receiver's velocity epochs for the thrust-axis check, beside the IMU frames.

Published on ``ins/<vehicle>/gnss`` (:func:`protocols.zenoh_adapter.gnss_key`). Wire schema,
version 1 (a msgpack map, as every message of :mod:`protocols._schema`):

=============  =========  =====================================================================
key            type       meaning
=============  =========  =====================================================================
``type``       str        ``"ins.gnss.frame"``
``v``          int        1
``vehicle``    str        vehicle id
``seq``        int        frame number, +1 per frame, 0..2⁶⁴−1
``rate_hz``    float      the receiver's solution rate, Hz (> 0): the check's threshold uses it
``n``          int        epochs, 1..:data:`MAX_EPOCHS`
``t_s``        bytes      n little-endian float64, s, on the vehicle's IMU clock, increasing
``vel_enu``    bytes      n×3 little-endian float64, m/s, East-North-Up, the receiver's own
=============  =========  =====================================================================

Decoding checks every field; non-finite values or times not increasing are refused
(:class:`~protocols.frames.FrameError` with its reason), as IMU frames are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocols._schema import (
    MAX_MESSAGE_BYTES,
    Reason,
    check_header,
    check_vehicle,
    field,
    float_field,
    pack,
    unpack_map,
)
from protocols.frames import MAX_SEQ, FrameError

GNSS_FRAME_TYPE = "ins.gnss.frame"
GNSS_FRAME_VERSION = 1
MAX_EPOCHS = 4096


@dataclass(frozen=True, eq=False)
class GnssFrame:
    """Velocity epochs of one vehicle's receiver (SI, ENU; arrays float64, read-only)."""

    vehicle: str
    seq: int
    rate_hz: float
    t_s: np.ndarray
    vel_enu_mps: np.ndarray

    def __post_init__(self) -> None:
        check_vehicle(self.vehicle, error=FrameError)
        if type(self.seq) is not int or not 0 <= self.seq <= MAX_SEQ:
            raise FrameError(Reason.BAD_VALUE, f"seq must be an int in 0..2^64-1, got {self.seq!r}")
        if not (
            isinstance(self.rate_hz, (int, float))
            and np.isfinite(self.rate_hz)
            and self.rate_hz > 0
        ):
            raise FrameError(Reason.BAD_VALUE, f"rate_hz must be positive, got {self.rate_hz!r}")
        t = np.array(self.t_s, dtype=np.float64)
        v = np.array(self.vel_enu_mps, dtype=np.float64)
        if t.ndim != 1 or not 1 <= t.size <= MAX_EPOCHS or v.shape != (t.size, 3):
            raise FrameError(
                Reason.WRONG_LENGTH,
                f"t_s (n,) with 1 <= n <= {MAX_EPOCHS} and vel_enu_mps (n, 3) expected, got {t.shape}, {v.shape}",
            )
        t.flags.writeable = False
        v.flags.writeable = False
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "vel_enu_mps", v)
        object.__setattr__(self, "rate_hz", float(self.rate_hz))


def encode_gnss_frame(frame: GnssFrame) -> bytes:
    return pack(
        {
            "type": GNSS_FRAME_TYPE,
            "v": GNSS_FRAME_VERSION,
            "vehicle": frame.vehicle,
            "seq": frame.seq,
            "rate_hz": frame.rate_hz,
            "n": int(frame.t_s.size),
            "t_s": frame.t_s.astype("<f8").tobytes(),
            "vel_enu": frame.vel_enu_mps.astype("<f8").tobytes(),
        }
    )


def decode_gnss_frame(data: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> GnssFrame:
    """Decode and validate one GNSS frame; :class:`~protocols.frames.FrameError` with a reason."""
    obj = unpack_map(data, error=FrameError, max_bytes=max_bytes)
    check_header(obj, type_tag=GNSS_FRAME_TYPE, versions=(GNSS_FRAME_VERSION,), error=FrameError)
    vehicle = check_vehicle(field(obj, "vehicle", str, error=FrameError), error=FrameError)
    seq = field(obj, "seq", int, error=FrameError)
    if not 0 <= seq <= MAX_SEQ:
        raise FrameError(Reason.BAD_VALUE, f"seq {seq} outside 0..2^64-1")
    rate = float_field(obj, "rate_hz", error=FrameError)
    n = field(obj, "n", int, error=FrameError)
    if not 1 <= n <= MAX_EPOCHS:
        raise FrameError(Reason.BAD_VALUE, f"epoch count n={n} outside 1..{MAX_EPOCHS}")
    arrays = []
    for name, shape in (("t_s", (n,)), ("vel_enu", (n, 3))):
        raw = field(obj, name, bytes, error=FrameError)
        if len(raw) != 8 * int(np.prod(shape)):
            raise FrameError(
                Reason.WRONG_LENGTH,
                f"{name} has {len(raw)} bytes, expected {8 * int(np.prod(shape))}",
            )
        arr = np.frombuffer(raw, dtype="<f8").reshape(shape)
        if not np.isfinite(arr).all():
            raise FrameError(Reason.NON_FINITE, f"{name} holds NaN/Inf value(s)")
        arrays.append(arr)
    if n > 1 and not np.all(np.diff(arrays[0]) > 0):
        raise FrameError(Reason.TIME_NOT_INCREASING, "t_s must strictly increase within a frame")
    if not rate > 0:
        raise FrameError(Reason.BAD_VALUE, f"rate_hz must be positive, got {rate!r}")
    return GnssFrame(vehicle, seq, rate, arrays[0], arrays[1])
