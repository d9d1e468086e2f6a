"""PX4 ULog files → IMU sample rows, streamed in bounded memory; and a ULog writer.

Format (PX4's "ULog File Format" specification, the one pyulog implements)
---------------------------------------------------------------------------
A 16-byte header (``55 4C 6F 67 01 12 35``, a version byte, the uint64 start
time in µs), then messages ``uint16 msg_size, uint8 msg_type, payload``
(little-endian). The definitions section holds ``B`` (flag bits), ``F``
(formats: ``"name:type field;type field;..."``), ``I``/``M`` (information) and
``P``/``Q`` (parameters); the data section ``A`` (subscribe: ``uint8
multi_id, uint16 msg_id, name``), ``D`` (data: ``uint16 msg_id`` and the
packed fields of the format, nested formats inlined, a uint64 ``timestamp``
in µs), ``L``/``C`` (log text), ``S`` (sync bytes), ``O`` (dropout: ``uint16
duration`` in ms the logger lost, counted in :class:`UlogContents`) and ``R``
(unsubscribe).

Reading
-------
pyulog (PX4's own parser) reads the definitions (``parse_header_only``): the
formats, the information and the parameters, and it rejects a file it cannot
read. Its full parse keeps every data message of the whole log in memory, so
the data section is streamed here instead: the payloads of the wanted topics
are collected and decoded every :data:`FLUSH_MESSAGES` messages with a numpy
structured dtype built from pyulog's format definitions (the tests check the
values against pyulog's own parse of a real log). Messages of every topic are
counted, so a log without IMU topics can say what it holds.

IMU topics, in SI, and the IMU index each becomes:

* ``sensor_combined`` → IMU 0, the primary IMU (gyro ``gyro_rad`` rad/s at
  ``timestamp``, ``accelerometer_m_s2`` m/s²); clipping from
  ``accelerometer_clipping``/``gyro_clipping`` (a bit per axis); temperature
  held from the ``sensor_accel`` instance whose ``device_id`` is the selected
  accelerometer (``sensor_selection.accel_device_id``).
* each ``sensor_accel``/``sensor_gyro`` pair of the same ``multi_id`` m → IMU
  ``1 + m`` (time ``timestamp_sample``; each accelerometer sample is paired with
  the gyro sample nearest in time within half the longer sample period;
  ``temperature`` °C; clipping from ``clip_counter``).
* each ``vehicle_imu`` instance m → IMU ``5 + m`` (``delta_velocity`` /
  ``delta_velocity_dt`` and ``delta_angle`` / ``delta_angle_dt``, dt in µs;
  clipping from ``delta_velocity_clipping``/``delta_angle_clipping``).

An instance other than ``sensor_combined`` is replayed only when it is logged at
:data:`MIN_IMU_RATE_HZ` or more (PX4's default logging profile records them at
1–2 Hz, too slow to find rest or measure noise); its rate is measured on its
first :data:`RATE_PROBE_SAMPLES` samples and the reason it is left out is kept.

Not read: data appended after a crash (``B``'s appended offsets; pyulog reads
it), which the stream meets as a corrupt tail: the rest is skipped to the next
sync sequence and counted (``corrupt_messages``).

Writing
-------
:func:`write_ulog` writes IMU sessions as ``sensor_combined`` (IMU 0) and
``sensor_accel``/``sensor_gyro`` pairs (other IMUs), with temperature and
clipping counters, from the specification above; pyulog reads its files (tests).
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pyulog import ULog

from estimators.session import ImuSession
from protocols.ulog_numpy import DATA, DATA_MIN_SIZE, SUBSCRIBE, message_run

ULOG_MAGIC = b"ULog\x01\x12\x35"
SYNC_BYTES = b"\x2f\x73\x13\x20\x25\x0c\xbb\x12"
FLUSH_MESSAGES = 16384
"""Wanted data messages collected before they are decoded (bounds the memory of a read)."""
RUN_WINDOW_MIN = 1 << 12
RUN_WINDOW_MAX = 1 << 20
"""Bytes searched for a run of messages (:func:`protocols.ulog_numpy.message_run`): from the
smaller after a run that ended short (a subscription, damage), doubled after each that did not."""
MIN_IMU_RATE_HZ = 20.0
"""Slowest logging rate at which a per-instance IMU topic is replayed, Hz."""
RATE_PROBE_SAMPLES = 16
"""Samples of an instance on which its logging rate is measured."""
INTERLEAVE_S = 0.5
"""Slices of log time in which the IMUs of one flush are handed on in turn (:func:`_interleave`)."""
MAX_MESSAGE_BYTES = 10000
"""A larger (or empty) message is taken as corruption, as pyulog does."""
_MIN_SIZE = {DATA: DATA_MIN_SIZE, SUBSCRIBE: 3}
"""Bytes a data and a subscription message need for their fixed fields (``msg_id``; ``multi_id``
and ``msg_id``): one shorter is a corrupt message, not read past its end (into the next message,
or past the file's end: a log cut after such a message raised)."""
MAX_FLAT_FIELDS = 2 * MAX_MESSAGE_BYTES
"""Most fields and nested instances a topic's format may flatten to (:func:`struct_dtype`). A data
message holds at most :data:`MAX_MESSAGE_BYTES`, each field takes a byte or more and each nested
instance holds a field, so a format that flattens to more describes no message a log can hold;
nested arrays (``a[1000]`` of ``b[1000]`` of ...) would otherwise flatten to billions of fields."""

PRIMARY_IMU = 0
SENSOR_IMU_BASE = 1
VEHICLE_IMU_BASE = 5
IMU_TOPICS = ("sensor_combined", "sensor_accel", "sensor_gyro", "vehicle_imu")
IMU_LIKE_PREFIXES = ("sensor_", "vehicle_imu", "vehicle_acceleration", "vehicle_angular")
_WANTED = (*IMU_TOPICS, "sensor_selection")
_NEEDED_FIELDS: Mapping[str, Mapping[str, tuple[int, ...]]] = {
    "sensor_combined": {"timestamp": (), "gyro_rad": (3,), "accelerometer_m_s2": (3,)},
    "sensor_accel": {"timestamp_sample": (), "x": (), "y": (), "z": ()},
    "sensor_gyro": {"timestamp_sample": (), "x": (), "y": (), "z": ()},
    "vehicle_imu": {
        "timestamp_sample": (), "delta_velocity": (3,), "delta_velocity_dt": (),
        "delta_angle": (3,), "delta_angle_dt": (),
    },
    "sensor_selection": {"accel_device_id": ()},
}  # fmt: skip
"""The numeric fields (name → array shape) each wanted topic is read from."""

_NUMPY_TYPES = {
    "int8_t": "<i1", "uint8_t": "<u1", "int16_t": "<i2", "uint16_t": "<u2",
    "int32_t": "<i4", "uint32_t": "<u4", "int64_t": "<i8", "uint64_t": "<u8",
    "float": "<f4", "double": "<f8", "bool": "<u1", "char": "S1",
}  # fmt: skip


class UlogError(ValueError):
    """A file that is not a ULog pyulog can read; the message says why."""


DEFINITIONS_READ_BUDGET_BYTES = 64 << 20
"""Most bytes pyulog may read for a file's definitions. It reads them once on a whole file (a few
MB at most), but past a corrupt header it steps one byte and reads the next header's declared size
(up to 64 KiB) again: on erased flash (0xFF) after the definitions that is quadratic, minutes for
1 MiB. This allows about a thousand such steps."""


class _BudgetedReads(io.RawIOBase):
    """A file pyulog reads through, refusing to read more than ``budget`` bytes in all."""

    def __init__(self, path: Path, budget: int):
        self._f = open(path, "rb")
        self._budget = self._left = budget

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        self._left -= len(data)
        if self._left < 0:
            raise UlogError(
                f"its definitions are corrupt beyond repair: pyulog read {self._budget} "
                f"bytes resynchronizing and was at byte {self._f.tell()}"
            )
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def close(self) -> None:
        self._f.close()
        super().close()


@dataclass(frozen=True)
class ImuRows:
    """Consecutive samples of one IMU as a reader yields them (SI; ``temp_c`` None when not known)."""

    kind: str
    imu: int
    t_s: np.ndarray
    accel_mps2: np.ndarray
    gyro_rps: np.ndarray
    temp_c: np.ndarray | None
    clipped: np.ndarray


@dataclass
class UlogContents:
    """What a ULog holds: messages per topic instance (``"name.multi_id"``), what was left out, the system."""

    topics: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    corrupt_messages: int = 0
    system: str = ""
    cut_at_byte: int | None = None
    dropouts: int = 0
    """Dropout messages: the logger lost data (its buffer full) for ``dropout_ms`` in all."""
    unsubscribed_data: int = 0
    """Data messages whose ``msg_id`` no subscription names (their topic is unknown)."""
    dropout_ms: int = 0


def struct_dtype(formats: Mapping[str, Any], name: str) -> np.dtype[Any]:
    """The packed numpy dtype of topic ``name`` (nested formats flattened to ``outer.inner`` names).

    ``formats`` maps a format name to pyulog's ``MessageFormat`` (``fields``: (type, array size, name)).
    :class:`UlogError` for a format that nests itself or flattens to more than :data:`MAX_FLAT_FIELDS`.
    """
    names: list[str] = []
    types: list[Any] = []
    flat = 0

    def grow() -> None:
        nonlocal flat
        flat += 1
        if flat > MAX_FLAT_FIELDS:
            raise UlogError(
                f"format {name!r} flattens to more than {MAX_FLAT_FIELDS} fields, more than a message holds"
            )

    def add(fmt_name: str, prefix: str, within: tuple[str, ...]) -> None:
        grow()
        for type_name, size, fname in formats[fmt_name].fields:
            full = prefix + fname
            if type_name in _NUMPY_TYPES:
                grow()
                base = _NUMPY_TYPES[type_name]
                names.append(full)
                types.append((base, (size,)) if size else base)
            elif type_name in within:
                raise UlogError(f"format {name!r} nests itself: {' > '.join((*within, type_name))}")
            elif type_name in formats:
                for k in range(max(size, 1)):
                    add(type_name, f"{full}[{k}]." if size else f"{full}.", (*within, type_name))
            else:
                raise UlogError(f"format {fmt_name!r}: unknown field type {type_name!r}")

    add(name, "", (name,))
    # The logger does not write the padding at the end of a message (pyulog's max_data_size).
    while names and names[-1].startswith("_padding"):
        names.pop()
        types.pop()
    return np.dtype({"names": names, "formats": types})


class UlogImuStream:
    """Iterate the IMU rows of a ULog file (module docstring); :attr:`contents` after iterating.

    ``fraction_read`` follows the file position (for progress lines).
    """

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        try:
            # pyulog prints its findings (corruption, unknown messages) to stdout, where --json writes.
            with (
                contextlib.redirect_stdout(io.StringIO()),
                _BudgetedReads(self.path, DEFINITIONS_READ_BUDGET_BYTES) as f,
            ):
                header = ULog(f, parse_header_only=True)
        except Exception as exc:  # pyulog raises its own, struct and index errors on bad files
            raise UlogError(f"{self.path}: not a ULog pyulog can read ({exc})") from None
        self._definitions_corrupt = int(header.file_corruption)
        self._formats = header.message_formats
        info = header.msg_info_dict
        self._system = " ".join(str(info[k]) for k in ("sys_name", "ver_hw") if k in info)
        self.size = os.path.getsize(self.path)
        self.fraction_read = 0.0
        self.contents = UlogContents(system=self._system)

    # ------------------------------------------------------------------ raw stream

    def _records(self) -> Iterator[dict[tuple[str, int], np.ndarray]]:
        """Decoded records of the wanted topics, per (topic, multi_id), a flush at a time."""
        subs: dict[int, tuple[str, int, np.dtype[Any] | None]] = {}
        pending: dict[int, list[np.ndarray]] = {}  # per msg_id, rows of payload bytes
        n_pending = 0
        window = RUN_WINDOW_MIN
        topics = self.contents.topics
        with open(self.path, "rb") as fh:
            fh.seek(16)
            buf, pos, eof = b"", 0, False
            while True:
                if not eof and len(buf) - pos < 3 + MAX_MESSAGE_BYTES:
                    more = fh.read(1 << 20)
                    eof = not more
                    buf, pos = buf[pos:] + more, 0
                    self.fraction_read = (fh.tell() - len(buf)) / max(self.size, 1)
                if len(buf) - pos < 3:
                    if len(buf) > pos:
                        self.contents.cut_at_byte = self.size - (len(buf) - pos)
                    break
                # The messages this loop would read in a row, found at once (ulog_numpy), in a
                # window that grows while the runs fill it (a subscription or damage ends one).
                stop = len(buf) if eof else len(buf) - 2 - MAX_MESSAGE_BYTES
                at, kinds, sizes = message_run(buf, pos, min(stop, pos + window), MAX_MESSAGE_BYTES)
                full = at.size and at[-1] + 3 + sizes[-1] + MAX_MESSAGE_BYTES >= pos + window
                window = min(2 * window, RUN_WINDOW_MAX) if full else RUN_WINDOW_MIN
                if at.size:
                    pos = int(at[-1] + 3 + sizes[-1])
                    d = np.frombuffer(buf, dtype=np.uint8)
                    dropout = at[(kinds == 0x4F) & (sizes >= 2)] + 3
                    self.contents.dropouts += dropout.size
                    self.contents.dropout_ms += int(d[dropout].sum() + 256 * d[dropout + 1].sum())
                    data = at[kinds == 0x44]
                    msg_ids = d[data + 3].astype(np.int64) | (d[data + 4].astype(np.int64) << 8)
                    wanted = np.zeros(data.size, dtype=bool)
                    # The ids (uint16) counted by bincount: a tenth of np.unique's time.
                    counts = np.bincount(msg_ids)
                    for msg_id in np.flatnonzero(counts).tolist():
                        sub = subs.get(msg_id)
                        if sub is None:
                            self.contents.unsubscribed_data += int(counts[msg_id])
                            continue
                        key = f"{sub[0]}.{sub[1]}"
                        topics[key] = topics.get(key, 0) + int(counts[msg_id])
                        if sub[2] is not None:
                            wanted |= msg_ids == msg_id
                    kept = np.flatnonzero(wanted)
                    while kept.size:
                        now, kept = (
                            kept[: FLUSH_MESSAGES - n_pending],
                            kept[FLUSH_MESSAGES - n_pending :],
                        )
                        n_pending += now.size
                        ids_now = msg_ids[now]
                        for msg_id in np.flatnonzero(np.bincount(ids_now)).tolist():
                            rows = now[ids_now == msg_id]
                            self._pend(
                                pending, subs, msg_id, d, data[rows], sizes[kinds == 0x44][rows]
                            )
                        if n_pending >= FLUSH_MESSAGES:
                            yield self._decode(subs, pending)
                            pending, n_pending = {}, 0
                    continue
                size, mtype = struct.unpack_from("<HB", buf, pos)
                if size == 0 or size > MAX_MESSAGE_BYTES or not 0x41 <= mtype <= 0x5A:
                    self.contents.corrupt_messages += 1
                    k = buf.find(SYNC_BYTES, pos + 1)
                    if k >= 0:
                        pos = k + len(SYNC_BYTES)
                    elif eof:
                        break
                    else:
                        # Keep the last bytes: a sync sequence may straddle the read boundary.
                        pos = max(pos + 1, len(buf) - len(SYNC_BYTES) + 1)
                    continue
                end = pos + 3 + size
                # Only at the end of the file: a read keeps a whole message ahead.
                if end > len(buf):
                    self.contents.cut_at_byte = self.size - (len(buf) - pos)
                    break
                if size < _MIN_SIZE.get(mtype, 1):
                    # Too short for its fixed fields: corrupt, but its size still says where the
                    # next message starts.
                    self.contents.corrupt_messages += 1
                    pos = end
                    continue
                if mtype == 0x44:  # 'D'
                    (msg_id,) = struct.unpack_from("<H", buf, pos + 3)
                    sub = subs.get(msg_id)
                    if sub is None:
                        # Its subscription lost (a damaged definitions or data section): of a
                        # topic nobody can name, IMU or not.
                        self.contents.unsubscribed_data += 1
                    else:
                        key = f"{sub[0]}.{sub[1]}"
                        topics[key] = topics.get(key, 0) + 1
                        if sub[2] is not None:
                            d = np.frombuffer(buf, dtype=np.uint8)
                            self._pend(pending, subs, msg_id, d, np.array([pos]), np.array([size]))
                            n_pending += 1
                            if n_pending >= FLUSH_MESSAGES:
                                yield self._decode(subs, pending)
                                pending, n_pending = {}, 0
                elif mtype == 0x4F and size >= 2:  # 'O': uint16 duration in ms
                    self.contents.dropouts += 1
                    self.contents.dropout_ms += struct.unpack_from("<H", buf, pos + 3)[0]
                elif mtype == 0x41:  # 'A'
                    multi_id, msg_id = struct.unpack_from("<BH", buf, pos + 3)
                    name = buf[pos + 6 : end].decode("ascii", "replace")
                    dtype = None
                    if name in _WANTED and name in self._formats:
                        dtype = self._topic_dtype(name, multi_id)
                    subs[msg_id] = (name, multi_id, dtype)
                    topics.setdefault(f"{name}.{multi_id}", 0)
                pos = end
        if pending:
            yield self._decode(subs, pending)
        self.fraction_read = 1.0

    def _topic_dtype(self, name: str, multi_id: int) -> np.dtype[Any] | None:
        """The dtype of a wanted topic; None, the reason kept, when its format lacks a field it is read from."""
        try:
            dtype = struct_dtype(self._formats, name)
        except UlogError as exc:
            raise UlogError(f"{self.path}: topic {name}: {exc}") from None
        names = dtype.names or ()
        for fname, shape in _NEEDED_FIELDS[name].items():
            sub = dtype[fname] if fname in names else None
            if sub is None or sub.shape != shape or sub.base.kind not in "biuf":
                self.contents.skipped[f"{name}.{multi_id}"] = (
                    f"its format has no numeric field {fname}{list(shape) if shape else ''}"
                )
                return None
        return dtype

    def _pend(
        self,
        pending: dict[int, list[np.ndarray]],
        subs: Mapping[int, tuple[str, int, np.dtype[Any] | None]],
        msg_id: int,
        d: np.ndarray,
        at: np.ndarray,
        size: np.ndarray,
    ) -> None:
        """Keep the payloads of the data messages of ``msg_id`` at ``at`` (sizes ``size``) for
        decoding; one shorter than the topic's format is corrupt."""
        dtype = subs[msg_id][2]
        assert dtype is not None
        good = size - 2 >= dtype.itemsize
        self.contents.corrupt_messages += int(good.size - good.sum())
        # A newer logger may pad a message past its format: the format's fields come first.
        rows = np.lib.stride_tricks.sliding_window_view(d, dtype.itemsize)[at[good] + 5]
        pending.setdefault(msg_id, []).append(rows)

    def _decode(
        self,
        subs: Mapping[int, tuple[str, int, np.dtype[Any] | None]],
        pending: Mapping[int, list[np.ndarray]],
    ) -> dict[tuple[str, int], np.ndarray]:
        out: dict[tuple[str, int], np.ndarray] = {}
        for msg_id, rows in pending.items():
            name, multi_id, dtype = subs[msg_id]
            assert dtype is not None
            out[(name, multi_id)] = np.concatenate(rows).view(dtype).reshape(-1)
        return out

    # ------------------------------------------------------------------ IMU rows

    def __iter__(self) -> Iterator[ImuRows]:
        self.contents = UlogContents(
            system=self._system, corrupt_messages=self._definitions_corrupt
        )
        state = _ImuState()
        for records in self._records():
            yield from _interleave(self._flush_rows(state, records))
        rows: list[ImuRows] = []
        for key, probe in sorted(state.probes.items()):
            # An instance whose log ended before the rate probe filled: judge it on what there is.
            rows += state.decide(self.contents, key, probe, final=True)
        for multi_id, pairer in sorted(state.pairs.items()):
            pairer.finish()
            if pairer.unpaired_accel:
                # An instance left out for its rate keeps that reason.
                self.contents.skipped.setdefault(
                    f"sensor_accel.{multi_id}",
                    f"{pairer.unpaired_accel} samples without a sensor_gyro sample near in time",
                )
        yield from _interleave(rows)

    def _flush_rows(
        self, state: _ImuState, records: Mapping[tuple[str, int], np.ndarray]
    ) -> list[ImuRows]:
        """The IMU rows one flush of the stream completes, every IMU's in time order."""
        for sel in _get(records, "sensor_selection", 0):
            state.selected_accel = int(sel["accel_device_id"])
        for (name, _), rec in sorted(records.items()):
            names = set(rec.dtype.names or ())
            if name == "sensor_accel" and {"temperature", "device_id"} <= names:
                state.note_temperature(rec)
        rows: list[ImuRows] = []
        for (name, multi_id), rec in sorted(records.items()):
            if name == "sensor_combined" and multi_id == 0:
                rows += state.combined(rec)
            elif name == "vehicle_imu":
                rows += state.admitted(
                    self.contents, f"vehicle_imu.{multi_id}", _vehicle_imu_rows(rec, multi_id)
                )
            elif name in ("sensor_accel", "sensor_gyro"):
                pairer = NearestPairer("sensor_accel+sensor_gyro", SENSOR_IMU_BASE + multi_id)
                state.pairs.setdefault(multi_id, pairer).add(name == "sensor_accel", rec)
        for multi_id, pairer in sorted(state.pairs.items()):
            paired = pairer.paired()
            if paired is not None:
                rows += state.admitted(self.contents, f"sensor_accel.{multi_id}", paired)
        return rows


def _interleave(rows: list[ImuRows], step_s: float = INTERLEAVE_S) -> Iterator[ImuRows]:
    """The rows of several IMUs cut into slices of ``step_s`` of log time, in time order.

    A flush holds thousands of samples of each IMU; handed on IMU after IMU, one IMU would run ahead
    of the others by the whole flush, too far for the cross-IMU comparison to wait for the others.
    """
    rows = [r for r in rows if r.t_s.size]
    if len(rows) < 2:
        yield from rows
        return
    start = min(float(r.t_s[0]) for r in rows)
    stop = max(float(r.t_s[-1]) for r in rows)
    cursor = [0] * len(rows)
    for edge in np.arange(start + step_s, stop + step_s, step_s):
        for i, r in enumerate(rows):
            end = int(np.searchsorted(r.t_s, edge, side="left"))
            if end > cursor[i]:
                yield _slice(r, cursor[i], end)
                cursor[i] = end
    for i, r in enumerate(rows):
        if cursor[i] < r.t_s.size:
            yield _slice(r, cursor[i], r.t_s.size)


def _slice(r: ImuRows, lo: int, hi: int) -> ImuRows:
    return ImuRows(
        r.kind,
        r.imu,
        r.t_s[lo:hi],
        r.accel_mps2[lo:hi],
        r.gyro_rps[lo:hi],
        None if r.temp_c is None else r.temp_c[lo:hi],
        r.clipped[lo:hi],
    )


def _get(records: Mapping[tuple[str, int], np.ndarray], name: str, multi_id: int) -> np.ndarray:
    return records.get((name, multi_id), np.zeros(0))


def _vec(rec: np.ndarray, name: str) -> np.ndarray:
    """(N, 3) float64 of a ``name[3]`` field (pyulog's flat names ``name[0]``… are the same bytes)."""
    return np.asarray(rec[name], dtype=float).reshape(-1, 3)


def _flag(rec: np.ndarray, *names: str) -> np.ndarray:
    clipped = np.zeros(rec.shape[0], dtype=bool)
    for name in names:
        if name in (rec.dtype.names or ()):
            values = np.asarray(rec[name]) != 0
            clipped |= values.any(axis=tuple(range(1, values.ndim)))
    return clipped


def _vehicle_imu_rows(rec: np.ndarray, multi_id: int) -> ImuRows:
    dv_dt = np.asarray(rec["delta_velocity_dt"], dtype=float)[:, None] * 1e-6
    da_dt = np.asarray(rec["delta_angle_dt"], dtype=float)[:, None] * 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        accel = _vec(rec, "delta_velocity") / dv_dt
        gyro = _vec(rec, "delta_angle") / da_dt
    return ImuRows(
        "vehicle_imu",
        VEHICLE_IMU_BASE + multi_id,
        np.asarray(rec["timestamp_sample"], dtype=float) * 1e-6,
        accel,
        gyro,
        None,
        _flag(rec, "delta_velocity_clipping", "delta_angle_clipping"),
    )


@dataclass
class NearestPairer:
    """Pairs accelerometer with gyro samples of one IMU logged as two streams (module docstring).

    Records are structured arrays with ``timestamp_sample`` (µs), ``x``, ``y``, ``z`` (SI) and,
    optionally, ``temperature`` (°C, accelerometer) and ``clip_counter``; PX4's ``sensor_accel`` and
    ``sensor_gyro`` are such records, and :mod:`protocols.logs` builds them from DataFlash ``ACC``/``GYR``.
    Each accelerometer sample takes the gyro sample nearest in time within half the longer of
    the two streams' median intervals; the others are counted in ``unpaired_accel``.
    """

    kind: str
    imu: int
    accel: list[np.ndarray] = field(default_factory=list)
    gyro: list[np.ndarray] = field(default_factory=list)
    tol_s: float | None = None
    unpaired_accel: int = 0

    def add(self, is_accel: bool, rec: np.ndarray) -> None:
        (self.accel if is_accel else self.gyro).append(rec)

    def finish(self) -> None:
        """At the end of the log: the accelerometer samples still waiting for a gyro sample (later
        than the last one, or all of them when too few came to pair any) are unpaired. An instance
        that never had a gyro sample is no IMU of two streams (PX4 logs a temperature that way)."""
        if self.gyro:
            self.unpaired_accel += sum(len(a) for a in self.accel)
        self.accel = []

    def paired(self) -> ImuRows | None:
        """The pairs complete so far (accelerometer samples later than the last gyro wait), or None."""
        if not self.accel or not self.gyro:
            return None
        acc, gyr = np.concatenate(self.accel), np.concatenate(self.gyro)
        ta = np.asarray(acc["timestamp_sample"], dtype=float) * 1e-6
        tg = np.asarray(gyr["timestamp_sample"], dtype=float) * 1e-6
        if self.tol_s is None:
            if ta.size < 2 or tg.size < 2:
                return None
            self.tol_s = 0.5 * max(float(np.median(np.diff(ta))), float(np.median(np.diff(tg))))
        ready = ta <= tg[-1] + self.tol_s
        j = np.clip(np.searchsorted(tg, ta[ready]), 1, tg.size - 1)
        j -= (ta[ready] - tg[j - 1]) < (tg[j] - ta[ready])
        ok = np.abs(tg[j] - ta[ready]) <= self.tol_s
        self.unpaired_accel += int((~ok).sum())
        a, g = acc[ready][ok], gyr[j[ok]]
        self.accel = [acc[~ready]]
        self.gyro = [gyr[int(j.max()) :]] if j.size else [gyr]
        temp = (
            np.asarray(a["temperature"], dtype=float)
            if "temperature" in (acc.dtype.names or ())
            else None
        )
        if temp is not None and not (np.isfinite(temp) & (temp != 0.0)).all():
            temp = None  # NaN (no reading) or SITL's 0 °C in the block: no temperature for it
        clipped = _flag(a, "clip_counter") | _flag(g, "clip_counter")
        return ImuRows(
            self.kind,
            self.imu,
            ta[ready][ok],
            np.column_stack([a["x"], a["y"], a["z"]]).astype(float),
            np.column_stack([g["x"], g["y"], g["z"]]).astype(float),
            temp,
            clipped,
        )


@dataclass
class _ImuState:
    selected_accel: int | None = None
    temp_by_device: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    last_temp: dict[int, tuple[float, float]] = field(default_factory=dict)
    pairs: dict[int, NearestPairer] = field(default_factory=dict)
    probes: dict[str, list[ImuRows]] = field(default_factory=dict)
    decided: dict[str, bool] = field(default_factory=dict)

    def note_temperature(self, rec: np.ndarray) -> None:
        t = np.asarray(rec["timestamp_sample"], dtype=float) * 1e-6
        temp = np.asarray(rec["temperature"], dtype=float)
        dev = np.asarray(rec["device_id"])
        for d in np.unique(dev):
            # 0 °C exactly is what a simulator (PX4 SITL) logs for "no sensor temperature".
            sel = (dev == d) & np.isfinite(temp) & (temp != 0.0)
            prev = self.last_temp.get(int(d))
            ts, vs = t[sel], temp[sel]
            if prev is not None:
                ts, vs = np.concatenate([[prev[0]], ts]), np.concatenate([[prev[1]], vs])
            self.temp_by_device[int(d)] = (ts, vs)
            if ts.size:
                self.last_temp[int(d)] = (float(ts[-1]), float(vs[-1]))

    def combined(self, rec: np.ndarray) -> Iterator[ImuRows]:
        t = np.asarray(rec["timestamp"], dtype=float) * 1e-6
        accel, gyro = _vec(rec, "accelerometer_m_s2"), _vec(rec, "gyro_rad")
        clipped = _flag(rec, "accelerometer_clipping", "gyro_clipping")
        ts, vs = self.temp_by_device.get(self.selected_accel or -1, (np.zeros(0), np.zeros(0)))
        k = np.searchsorted(ts, t, side="right") - 1 if ts.size else np.full(t.size, -1)
        first = int(
            np.searchsorted(k, 0)
        )  # k ascends with t: rows before `first` have no temperature yet
        kind = "sensor_combined"
        if first:
            yield ImuRows(
                kind, PRIMARY_IMU, t[:first], accel[:first], gyro[:first], None, clipped[:first]
            )
        if first < t.size:
            yield ImuRows(kind, PRIMARY_IMU, t[first:], accel[first:], gyro[first:], vs[k[first:]], clipped[first:])  # fmt: skip

    def admitted(self, contents: UlogContents, key: str, rows: ImuRows) -> Iterator[ImuRows]:
        """Rows of an instance once its rate is known to be useful (module docstring); probed first."""
        verdict = self.decided.get(key)
        if verdict is True:
            yield rows
            return
        if verdict is False:
            return
        probe = self.probes.setdefault(key, [])
        probe.append(rows)
        if sum(r.t_s.size for r in probe) >= RATE_PROBE_SAMPLES:
            yield from self.decide(contents, key, probe, final=False)

    def decide(
        self, contents: UlogContents, key: str, probe: list[ImuRows], *, final: bool
    ) -> Iterator[ImuRows]:
        del self.probes[key]
        t = np.concatenate([r.t_s for r in probe])
        rate = 1.0 / float(np.median(np.diff(t))) if t.size > 1 else 0.0
        self.decided[key] = rate >= MIN_IMU_RATE_HZ
        if self.decided[key]:
            yield from probe
        else:
            contents.skipped[key] = f"logged at {rate:.3g} Hz, below {MIN_IMU_RATE_HZ:g} Hz"


def describe_contents(contents: UlogContents) -> str:
    """One line: the IMU-like topics, then every topic with its message count."""
    held = {k: n for k, n in contents.topics.items() if n}
    imu_like = sorted(k for k in held if k.startswith(IMU_LIKE_PREFIXES))
    text = f"IMU-like topics: {', '.join(imu_like) or 'none'}"
    if contents.skipped:
        text += "; left out: " + "; ".join(f"{k} {v}" for k, v in sorted(contents.skipped.items()))
    return text + "; topics: " + ", ".join(f"{k} {n}" for k, n in sorted(held.items()))


# --------------------------------------------------------------------------- writer

_FORMATS = {
    "sensor_combined": (
        "uint64_t timestamp;float[3] gyro_rad;uint32_t gyro_integral_dt;"
        "int32_t accelerometer_timestamp_relative;float[3] accelerometer_m_s2;"
        "uint32_t accelerometer_integral_dt;uint8_t accelerometer_clipping;uint8_t gyro_clipping;"
        "uint8_t accel_calibration_count;uint8_t gyro_calibration_count;"
    ),
    "sensor_accel": (
        "uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float x;float y;float z;"
        "float temperature;uint32_t error_count;uint8_t[3] clip_counter;uint8_t samples;"
    ),
    "sensor_gyro": (
        "uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float x;float y;float z;"
        "float temperature;uint32_t error_count;uint8_t[3] clip_counter;uint8_t samples;"
    ),
    "sensor_selection": "uint64_t timestamp;uint32_t accel_device_id;uint32_t gyro_device_id;",
    "vehicle_status": "uint64_t timestamp;uint8_t arming_state;uint8_t nav_state;",
    **dict.fromkeys(
        ("sensor_gps", "vehicle_gps_position"),
        "uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float vel_n_m_s;"
        "float vel_e_m_s;float vel_d_m_s;uint8_t fix_type;bool vel_ned_valid;",
    ),
}
_PACK = {
    "sensor_combined": struct.Struct("<Q3fIi3fIBBBB"),
    "sensor_accel": struct.Struct("<QQI4fI3BB"),
    "sensor_gyro": struct.Struct("<QQI4fI3BB"),
    "sensor_selection": struct.Struct("<QII"),
    "sensor_gps": struct.Struct("<QQI3fB?"),
    "vehicle_gps_position": struct.Struct("<QQI3fB?"),
}
DEVICE_ID_BASE = 0x240000
"""Device ids the writer gives the IMUs' sensors (``DEVICE_ID_BASE + imu``)."""


def session_triads(session: ImuSession) -> tuple[np.ndarray, np.ndarray]:
    """(accel_mps2, gyro_rps) of a session a log writer can write: both triads are needed."""
    if session.accel_mps2 is None or session.gyro_rps is None:
        raise ValueError("a log holds IMUs with both triads; this session lacks one")
    return session.accel_mps2, session.gyro_rps


@dataclass(frozen=True)
class UlogGnss:
    """A receiver's epochs for :func:`write_ulog`: ``topic`` ``sensor_gps`` or
    ``vehicle_gps_position`` (the fields :mod:`protocols.gnss_logs` reads), instance ``multi_id``,
    ``t_s`` (M,) s, ``vel_ned_mps`` (M, 3) North-East-Down, per epoch (or one for all)
    ``fix_type`` and ``vel_ned_valid``."""

    topic: str
    t_s: np.ndarray
    vel_ned_mps: np.ndarray
    multi_id: int = 0
    fix_type: int | np.ndarray = 3
    vel_ned_valid: bool | np.ndarray = True


def _message(mtype: bytes, payload: bytes) -> bytes:
    return struct.pack("<H", len(payload)) + mtype + payload


def write_ulog(
    path: str | os.PathLike[str],
    sessions: Mapping[int, ImuSession],
    *,
    clipped: Mapping[int, np.ndarray] | None = None,
    topics: Sequence[str] | None = None,
    gnss: Sequence[UlogGnss] = (),
    system: str = "ins-health",
) -> int:
    """Write IMU sessions as a ULog file (module docstring); returns the number of data messages.

    IMU 0 → ``sensor_combined`` (its temperature as a ``sensor_accel`` instance of its own at 1 Hz, the
    selected accelerometer); IMU k ≥ 1 → ``sensor_accel``/``sensor_gyro`` instance k − 1 at the session's rate,
    with ``temperature``. ``clipped`` (per IMU, (N,) bool) sets the clipping bits/counters of those
    samples. ``topics`` restricts what is written (e.g. ``["vehicle_status"]`` for a log without IMU
    topics, which then holds one ``vehicle_status`` message per second of the first session).
    ``gnss``: receivers' epochs written beside them (:class:`UlogGnss`).
    """
    wanted = set(topics) if topics is not None else set(_PACK)
    clipped = clipped or {}
    rows: list[tuple[int, int, bytes]] = []  # (t_us, order, message)
    subs: list[tuple[str, int]] = []

    def sub_id(name: str, multi_id: int) -> int:
        if (name, multi_id) not in subs:
            subs.append((name, multi_id))
        return subs.index((name, multi_id))

    def data(t_us: int, name: str, multi_id: int, *values: Any) -> None:
        msg_id = sub_id(name, multi_id)
        rows.append((t_us, len(rows), _message(b"D", struct.pack("<H", msg_id) + _PACK[name].pack(*values))))  # fmt: skip

    first = sessions[min(sessions)]
    temp_instance = max(sessions)  # IMU 0's slow temperature topic: an instance no other IMU uses
    if "vehicle_status" in wanted:
        for t in np.arange(first.t_s[0], first.t_s[-1], 1.0):
            msg_id = sub_id("vehicle_status", 0)
            rows.append((round(t * 1e6), len(rows), _message(b"D", struct.pack("<HQBB", msg_id, round(t * 1e6), 1, 0))))  # fmt: skip
    for imu, s in sorted(sessions.items()):
        acc, gyr = session_triads(s)
        t_us = np.round(s.t_s * 1e6).astype(np.int64)
        clip = np.asarray(clipped.get(imu, np.zeros(s.n_samples, bool)), dtype=bool)
        dev = DEVICE_ID_BASE + imu
        if imu == 0 and "sensor_combined" in wanted:
            data(int(t_us[0]), "sensor_selection", 0, int(t_us[0]), dev, dev)
            for k in range(s.n_samples):
                c = 7 if clip[k] else 0
                data(int(t_us[k]), "sensor_combined", 0, int(t_us[k]), *map(float, gyr[k]), 4000, 0,
                     *map(float, acc[k]), 4000, c, c, 0, 0)  # fmt: skip
            if s.temp_c is not None:
                for j in np.flatnonzero(np.diff(np.floor(s.t_s), prepend=-1.0) > 0):
                    data(int(t_us[j]), "sensor_accel", temp_instance, int(t_us[j]), int(t_us[j]), dev,
                         *map(float, acc[j]), float(s.temp_c[j]), 0, 0, 0, 0, 1)  # fmt: skip
        elif imu > 0 and "sensor_accel" in wanted:
            temp = s.temp_c if s.temp_c is not None else np.full(s.n_samples, np.nan)
            for k in range(s.n_samples):
                c = 1 if clip[k] else 0
                tk = int(t_us[k])
                data(tk, "sensor_accel", imu - 1, tk, tk, dev, *map(float, acc[k]), float(temp[k]), 0, c, c, c, 1)  # fmt: skip
                data(tk, "sensor_gyro", imu - 1, tk, tk, dev, *map(float, gyr[k]), float(temp[k]), 0, c, c, c, 1)  # fmt: skip
    for receiver in gnss:
        n = len(receiver.t_s)
        fix = np.broadcast_to(receiver.fix_type, n)
        valid = np.broadcast_to(receiver.vel_ned_valid, n)
        for k, t in enumerate(np.round(np.asarray(receiver.t_s) * 1e6).astype(np.int64)):
            data(int(t), receiver.topic, receiver.multi_id, int(t), int(t), 0,
                 *map(float, receiver.vel_ned_mps[k]), int(fix[k]), bool(valid[k]))  # fmt: skip
    rows.sort()
    start_us = rows[0][0] if rows else 0
    with open(path, "wb") as fh:
        fh.write(ULOG_MAGIC + b"\x01" + struct.pack("<Q", start_us))
        fh.write(_message(b"B", bytes(16) + bytes(24)))
        fh.write(_message(b"I", _info(f"char[{len(system)}] sys_name", system.encode())))
        for name in sorted({n for n, _ in subs}):
            fh.write(_message(b"F", f"{name}:{_FORMATS[name]}".encode()))
        for msg_id, (name, multi_id) in enumerate(subs):
            fh.write(_message(b"A", struct.pack("<BH", multi_id, msg_id) + name.encode()))
        for k, (_, _, msg) in enumerate(rows):
            if k % 1000 == 0:
                fh.write(_message(b"S", SYNC_BYTES))
            fh.write(msg)
    return len(rows)


def _info(key: str, value: bytes) -> bytes:
    return struct.pack("<B", len(key)) + key.encode() + value
