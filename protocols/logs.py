"""Logged flights → :class:`~protocols.frames.SampleBatch`: MAVLink ``.tlog`` and ArduPilot DataFlash ``.bin`` / ``.log``.

Reading (pymavlink does the parsing)
------------------------------------
* ``.tlog`` (a ground station's telemetry log: each record an 8-byte big-endian
  µs wall-clock stamp and one MAVLink packet): the IMU messages of
  :mod:`protocols.mavlink_adapter` (RAW_IMU, SCALED_IMU*, HIGHRES_IMU) with the
  same units, scaling and IMU index mapping. Sample time is the message's own
  boot-clock field, not the record stamp.
* DataFlash binary ``.bin`` and text ``.log``: messages named ``IMU``, ``IMU2``,
  ``IMU3`` with ``GyrX GyrY GyrZ`` (rad/s), ``AccX AccY AccZ`` (m/s²), time
  ``TimeUS`` (µs; ``TimeMS`` in old logs) and temperature ``T`` (°C) when
  present. The IMU index is the instance field ``I`` when the format has one
  (current ArduPilot), otherwise the name (``IMU`` 0, ``IMU2`` 1, ``IMU3`` 2).

Output is deterministic: messages are taken in file order and each IMU's
samples are cut into batches of ``batch_samples``, emitted as they fill (so
the IMUs stay interleaved in time), then the remainders in IMU order. Nothing
is dropped silently: a sample that is not later than the previous one of its
IMU, or that holds NaN/Inf, is left out and counted in :class:`LogStats`.

Writing (for tests and the demo)
--------------------------------
:func:`write_tlog`, :func:`write_dataflash_bin` and :func:`write_dataflash_text`
write simulated sessions in the same formats; pymavlink has no DataFlash
writer, so the binary one packs ``FMT`` and ``IMU`` messages itself (the format
is in the docstring) and the tests read it back with pymavlink's ``DFReader``.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np
from pymavlink import DFReader, mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from estimators.session import ImuSession
from protocols.frames import MAX_SAMPLES, SampleBatch, concat_batches
from protocols.mavlink_adapter import (
    DEFAULT_IMU_INDEX,
    RAW_IMU_ARDUPILOT,
    ImuMessage,
    ImuScale,
    decode_imu_message,
    imu_message,
    use_mavlink2,
)

DATAFLASH_IMU_NAMES = ("IMU", "IMU2", "IMU3")
_DF_HEAD = b"\xa3\x95"
_DF_FMT_ID = 0x80


class LogFormat(StrEnum):
    TLOG = "tlog"
    DATAFLASH_BIN = "bin"
    DATAFLASH_TEXT = "log"


def detect_format(path: str | os.PathLike) -> LogFormat:
    """The format of a log file, from its first bytes (the extension is only a tie-breaker).

    Raises ``ValueError`` for a file that is none of the three.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(64)
    if head.startswith(_DF_HEAD):
        return LogFormat.DATAFLASH_BIN
    if head.lstrip().startswith(b"FMT,"):
        return LogFormat.DATAFLASH_TEXT
    # A tlog record: 8-byte stamp, then a MAVLink 1 (0xFE) or 2 (0xFD) start byte.
    if len(head) > 8 and head[8] in (0xFE, 0xFD):
        return LogFormat.TLOG
    raise ValueError(
        f"{path}: not a MAVLink .tlog or a DataFlash .bin/.log (first bytes {head[:12].hex()})"
    )


@dataclass
class LogStats:
    """What a :class:`LogReader` read and left out."""

    messages: dict[str, int] = field(default_factory=dict)
    samples: dict[int, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)

    def _drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1


@dataclass
class _Buffer:
    t_s: list[float] = field(default_factory=list)
    accel_mps2: list[tuple[float, float, float]] = field(default_factory=list)
    gyro_rps: list[tuple[float, float, float]] = field(default_factory=list)
    temp_c: list[float | None] = field(default_factory=list)
    seq: int = 0
    last_t_s: float = -np.inf


class LogReader:
    """Iterate a log as :class:`~protocols.frames.SampleBatch` values (module docstring).

    Parameters
    ----------
    path : the log file.
    vehicle : vehicle id given to the batches.
    batch_samples : samples per batch (the last of each IMU may be shorter).
    log_format : override :func:`detect_format`.
    raw_scale, imu_index : MAVLink settings (:mod:`protocols.mavlink_adapter`), tlog only.

    After iterating, :attr:`stats` holds the counts. Iterating again reads the
    file again and gives the same batches.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        vehicle: str = "replay",
        batch_samples: int = 1000,
        log_format: LogFormat | None = None,
        raw_scale: ImuScale = RAW_IMU_ARDUPILOT,
        imu_index: Mapping[ImuMessage, int] = DEFAULT_IMU_INDEX,
    ):
        if not 1 <= batch_samples <= MAX_SAMPLES:
            raise ValueError(f"batch_samples must be in 1..{MAX_SAMPLES}, got {batch_samples}")
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"{self.path}: no such log file")
        self.format = LogFormat(log_format) if log_format is not None else detect_format(self.path)
        self.vehicle = vehicle
        self._batch = int(batch_samples)
        self._raw_scale = raw_scale
        self._imu_index = imu_index
        self.stats = LogStats()

    def __iter__(self) -> Iterator[SampleBatch]:
        self.stats = LogStats()
        buffers: dict[int, _Buffer] = {}
        samples = (
            self._tlog_samples() if self.format is LogFormat.TLOG else self._dataflash_samples()
        )
        for kind, imu, t_s, acc, gyr, temp in samples:
            self.stats.messages[kind] = self.stats.messages.get(kind, 0) + 1
            buf = buffers.setdefault(imu, _Buffer())
            if not all(map(math.isfinite, (t_s, *acc, *gyr, 0.0 if temp is None else temp))):
                self.stats._drop("non_finite")
                continue
            if t_s <= buf.last_t_s:
                self.stats._drop("time_not_increasing")
                continue
            buf.last_t_s = t_s
            buf.t_s.append(t_s)
            buf.accel_mps2.append(acc)
            buf.gyro_rps.append(gyr)
            buf.temp_c.append(temp)
            self.stats.samples[imu] = self.stats.samples.get(imu, 0) + 1
            if len(buf.t_s) == self._batch:
                yield from self._emit(imu, buf)
        for imu in sorted(buffers):
            if buffers[imu].t_s:
                yield from self._emit(imu, buffers[imu])

    def _emit(self, imu: int, buf: _Buffer) -> Iterator[SampleBatch]:
        # Temperature only when every sample has one: a batch is all or nothing.
        temps = None if any(t is None for t in buf.temp_c) else np.array(buf.temp_c)
        batch = SampleBatch(
            self.vehicle,
            imu,
            buf.seq,
            np.array(buf.t_s),
            np.array(buf.accel_mps2),
            np.array(buf.gyro_rps),
            temps,
        )
        buf.seq += 1
        buf.t_s, buf.accel_mps2, buf.gyro_rps, buf.temp_c = [], [], [], []
        yield batch

    def _tlog_samples(self):
        # mavlogfile reads sequentially (flat memory) and, unlike mavutil.mavlink_connection's
        # mmap reader, parses nothing before use_mavlink2 has given it its own MAVLink 2 parser.
        conn = use_mavlink2(mavutil.mavlogfile(str(self.path), notimestamps=False))
        try:
            types = [m.value for m in ImuMessage]
            while (msg := conn.recv_match(type=types)) is not None:
                s = decode_imu_message(msg, raw_scale=self._raw_scale, imu_index=self._imu_index)
                if s is not None:
                    yield msg.get_type(), s.imu, s.t_s, s.accel_mps2, s.gyro_rps, s.temp_c
        finally:
            conn.close()

    def _dataflash_samples(self):
        reader_cls = (
            DFReader.DFReader_binary
            if self.format is LogFormat.DATAFLASH_BIN
            else DFReader.DFReader_text
        )
        reader = reader_cls(str(self.path))
        try:
            while (msg := reader.recv_match(type=list(DATAFLASH_IMU_NAMES))) is not None:
                name = msg.get_type()
                fields = msg.get_fieldnames()
                imu = int(msg.I) if "I" in fields else DATAFLASH_IMU_NAMES.index(name)
                t_s = msg.TimeUS * 1e-6 if "TimeUS" in fields else msg.TimeMS * 1e-3
                temp = float(msg.T) if "T" in fields else None
                yield (
                    name,
                    imu,
                    t_s,
                    (msg.AccX, msg.AccY, msg.AccZ),
                    (msg.GyrX, msg.GyrY, msg.GyrZ),
                    temp,
                )
        finally:
            reader.close()


def read_log_sessions(path: str | os.PathLike, **options) -> tuple[dict[int, ImuSession], LogStats]:
    """Every IMU of a log as one :class:`~estimators.session.ImuSession` (IMU index → session), and the stats.

    ``options`` are those of :class:`LogReader`.
    """
    reader = LogReader(path, **options)
    per_imu: dict[int, list[SampleBatch]] = {}
    for batch in reader:
        per_imu.setdefault(batch.imu, []).append(batch)
    return {imu: concat_batches(b) for imu, b in sorted(per_imu.items())}, reader.stats


# --------------------------------------------------------------------------- writers


def _merged_rows(sessions: Mapping[int, ImuSession]) -> list[tuple[float, int, int]]:
    """(t_s, imu, sample index) of every sample, in time order (ties by IMU): the order a logger writes."""
    rows = [(float(t), imu, k) for imu, s in sessions.items() for k, t in enumerate(s.t_s)]
    rows.sort()
    return rows


DEFAULT_TLOG_MESSAGES: Mapping[int, ImuMessage] = {
    0: ImuMessage.RAW_IMU,
    1: ImuMessage.SCALED_IMU2,
    2: ImuMessage.SCALED_IMU3,
}
"""What ArduPilot streams per IMU (RAW_SENSORS): the default of :func:`write_tlog`."""


def write_tlog(
    path: str | os.PathLike,
    sessions: Mapping[int, ImuSession],
    *,
    messages: Mapping[int, ImuMessage] = DEFAULT_TLOG_MESSAGES,
    wall_start_s: float = 1.7e9,
    source_system: int = 1,
    raw_scale: ImuScale = RAW_IMU_ARDUPILOT,
) -> int:
    """Write IMU sessions as a MAVLink 2 telemetry log; returns the number of records.

    ``sessions`` maps IMU index → session; ``messages`` says which message
    carries each IMU (RAW_IMU and HIGHRES_IMU put the index in their ``id``
    field; for SCALED_IMU* the message number is the IMU). Record stamps are
    ``wall_start_s + t_s``. Integer messages quantize to their counts.
    """
    for imu, kind in ((imu, ImuMessage(messages[imu])) for imu in sessions):
        if (
            kind not in (ImuMessage.RAW_IMU, ImuMessage.HIGHRES_IMU)
            and imu != DEFAULT_IMU_INDEX[kind]
        ):
            raise ValueError(
                f"{kind.value} carries IMU {DEFAULT_IMU_INDEX[kind]} only, not IMU {imu}"
            )
    mav = mavlink2.MAVLink(
        None, srcSystem=source_system, srcComponent=mavlink2.MAV_COMP_ID_AUTOPILOT1
    )
    with open(path, "wb") as fh:
        rows = _merged_rows(sessions)
        for t_s, imu, k in rows:
            s = sessions[imu]
            kind = messages[imu]
            base = DEFAULT_IMU_INDEX[kind]
            msg = imu_message(
                kind,
                t_s=t_s,
                accel_mps2=s.accel_mps2[k],
                gyro_rps=s.gyro_rps[k],
                temp_c=None if s.temp_c is None else float(s.temp_c[k]),
                imu_id=imu - base,
                raw_scale=raw_scale,
            )
            fh.write(struct.pack(">Q", round((wall_start_s + t_s) * 1e6)) + msg.pack(mav))
    return len(rows)


@dataclass(frozen=True)
class _DfFormat:
    type_id: int
    name: str
    fmt: str
    columns: tuple[str, ...]

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct(
            "<" + self.fmt.replace("n", "4s").replace("N", "16s").replace("Z", "64s")
        )

    @property
    def length(self) -> int:
        return 3 + self.struct.size


_FMT_OF_FMT = _DfFormat(_DF_FMT_ID, "FMT", "BBnNZ", ("Type", "Length", "Name", "Format", "Columns"))


def _dataflash_plan(
    sessions: Mapping[int, ImuSession], legacy_names: bool
) -> tuple[list[_DfFormat], dict[int, _DfFormat]]:
    """Message formats, and the format of each IMU, for the DataFlash writers.

    Current ArduPilot: one ``IMU`` message with instance ``I`` (``QBffffff[f]``).
    ``legacy_names``: ``IMU``, ``IMU2``, ``IMU3`` without ``I`` (``Qffffff[f]``),
    as older firmware (and the real test log) writes.
    """
    with_temp = all(s.temp_c is not None for s in sessions.values())
    data_cols = ("GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ") + (("T",) if with_temp else ())
    if legacy_names:
        if not set(sessions) <= {0, 1, 2}:
            raise ValueError(
                f"legacy IMU/IMU2/IMU3 names hold IMU indices 0..2 only, got {sorted(sessions)}"
            )
        per_imu = {
            imu: _DfFormat(
                _DF_FMT_ID + 1 + imu,
                DATAFLASH_IMU_NAMES[imu],
                "Q" + "f" * len(data_cols),
                ("TimeUS", *data_cols),
            )
            for imu in sorted(sessions)
        }
        return [_FMT_OF_FMT, *per_imu.values()], per_imu
    imu_fmt = _DfFormat(
        _DF_FMT_ID + 1, "IMU", "QB" + "f" * len(data_cols), ("TimeUS", "I", *data_cols)
    )
    return [_FMT_OF_FMT, imu_fmt], {imu: imu_fmt for imu in sessions}


def _dataflash_records(sessions: Mapping[int, ImuSession], per_imu: Mapping[int, _DfFormat]):
    for t_s, imu, k in _merged_rows(sessions):
        s, f = sessions[imu], per_imu[imu]
        values: list = [round(t_s * 1e6)]
        if "I" in f.columns:
            values.append(imu)
        values += [float(v) for v in s.gyro_rps[k]] + [float(v) for v in s.accel_mps2[k]]
        if "T" in f.columns:
            values.append(float(s.temp_c[k]))
        yield f, values


def write_dataflash_bin(
    path: str | os.PathLike, sessions: Mapping[int, ImuSession], *, legacy_names: bool = False
) -> int:
    """Write IMU sessions as a binary DataFlash log; returns the number of IMU messages.

    Layout: every message is ``A3 95 <type id>`` and its packed fields
    (little-endian; ``Q`` uint64, ``B`` uint8, ``f`` float32, ``n`` char[4],
    ``N`` char[16], ``Z`` char[64]). First the ``FMT`` messages (type 128,
    fields ``Type B, Length B, Name n, Format N, Columns Z``; ``Length`` counts
    the 3 header bytes), one for ``FMT`` itself and one per IMU message
    format (:func:`_dataflash_plan`), then the IMU messages in time order.
    Values are stored as float32, as ArduPilot does.
    """
    formats, per_imu = _dataflash_plan(sessions, legacy_names)
    n = 0
    with open(path, "wb") as fh:
        for f in formats:
            payload = _FMT_OF_FMT.struct.pack(
                f.type_id, f.length, f.name.encode(), f.fmt.encode(), ",".join(f.columns).encode()
            )
            fh.write(_DF_HEAD + bytes([_DF_FMT_ID]) + payload)
        for f, values in _dataflash_records(sessions, per_imu):
            fh.write(_DF_HEAD + bytes([f.type_id]) + f.struct.pack(*values))
            n += 1
    return n


def write_dataflash_text(
    path: str | os.PathLike, sessions: Mapping[int, ImuSession], *, legacy_names: bool = False
) -> int:
    """Write IMU sessions as a text DataFlash log (``FMT`` lines, then one line per message); returns IMU messages.

    Same formats as :func:`write_dataflash_bin`; values are written with
    ``repr`` precision (float64), so a text log round-trips exactly.
    """
    formats, per_imu = _dataflash_plan(sessions, legacy_names)
    n = 0
    with open(path, "w", encoding="ascii") as fh:
        for f in formats:
            fh.write(f"FMT, {f.type_id}, {f.length}, {f.name}, {f.fmt}, {','.join(f.columns)}\n")
        for f, values in _dataflash_records(sessions, per_imu):
            fh.write(", ".join([f.name, *(repr(v) for v in values)]) + "\n")
            n += 1
    return n
