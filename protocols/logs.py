"""Logged flights → :class:`~protocols.frames.SampleBatch`: MAVLink ``.tlog``, ArduPilot DataFlash ``.bin`` / ``.log``, PX4 ULog.

Reading (pymavlink parses MAVLink and decodes DataFlash; ULog: :mod:`protocols.ulog`)
-------------------------------------------------------------------------------------
The format is recognised from the content (:func:`detect_format`), never from
the extension. A log with no IMU data raises :class:`NoImuDataError` naming the
message types (topics) it does hold.

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
  Text logs as the firmware writes them: header lines (firmware name, free
  RAM, board) before the first ``FMT`` line, CRLF or LF. The per-sample ``ACC``
  and ``GYR`` messages (instance ``I``, time ``SampleUS``) of an instance are
  paired by time (:class:`protocols.ulog.NearestPairer`) into IMU
  :data:`DATAFLASH_RAW_BASE` + ``I``; so are those of ArduPilot before 4.1,
  ``ACC1``…``ACC3`` and ``GYR1``…``GYR3`` (instance 0…2 by name,
  :data:`DATAFLASH_RAW_NAMES`). ``VIBE``'s clip counters give the
  clipped samples per IMU. DataFlash logs are read as a stream
  (:class:`DataFlashStream`: pymavlink's format and message classes, our own
  sequential loop), so a reader's memory does not grow with the log's length.

Output is deterministic: messages are taken in file order and each IMU's
samples are cut into batches of ``batch_samples``, emitted as they fill (so
the IMUs stay interleaved in time), then the remainders in IMU order. Nothing
is dropped silently: a sample that is not later than the previous one of its
IMU (``time_not_increasing``), a single time stamp far ahead of its
neighbours (``time_glitch``, :data:`JUMP_HOLD_S`), or one that holds NaN/Inf,
is left out and counted in :class:`LogStats`; a run of samples whose time
started again is kept and counted (``clock_restarts``,
:data:`CLOCK_RESTART_SAMPLES`): the batch before it ends there, and the batches from it on carry
the next run id (:attr:`~protocols.frames.SampleBatch.run`: 0 from the log's start, one more at
each restart), so the pipeline starts a new run at once and refuses none of them. With
``join_frames`` > 1 the full batches one IMU fills in a row come joined, up to that many in one
(what replay takes at full speed: the cost is per batch): an IMU's full batches wait until that
many are full, or until another IMU's rows, a restart of its clock or the log's end come, so a
lone IMU's come joined across the blocks the DataFlash and tlog decoders read, and no batch
passes another IMU's; so
is a corrupt message (``corrupt_messages``: a DataFlash one that does not decode, a
tlog packet with a bad CRC), the bytes passed over to the next message
(``skipped_bytes``) and where a file cut mid-message ends (``cut_at_byte``).

Writing (for tests and the demo)
--------------------------------
:func:`write_tlog`, :func:`write_dataflash_bin` and :func:`write_dataflash_text`
write simulated sessions in the same formats; pymavlink has no DataFlash
writer, so the binary one packs ``FMT`` and ``IMU`` messages itself (the format
is in the docstring) and the tests read it back with pymavlink's ``DFReader``.
"""

from __future__ import annotations

import array
import os
import re
import struct
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from estimators._typing import BoolArray
from estimators.session import ImuSession, finite_rows
from protocols.frames import MAX_SAMPLES, SampleBatch, concat_batches
from protocols.mavlink_settings import (
    DEFAULT_IMU_INDEX,
    RAW_IMU_ARDUPILOT,
    ImuMessage,
    ImuScale,
    LinkRejection,
)
from protocols.ulog import ULOG_MAGIC, ImuRows, NearestPairer, UlogImuStream, session_triads

DATAFLASH_IMU_NAMES = ("IMU", "IMU2", "IMU3")
DATAFLASH_RAW_BASE = 3
"""IMU index of ``ACC``/``GYR`` instance 0 (instance ``I`` is ``3 + I``): after IMU, IMU2, IMU3."""
DATAFLASH_RAW_NAMES: dict[str, tuple[bool, int | None]] = {
    "ACC": (True, None),
    "GYR": (False, None),
    **{f"ACC{k + 1}": (True, k) for k in range(3)},
    **{f"GYR{k + 1}": (False, k) for k in range(3)},
}
"""The per-sample messages: name → (accelerometer?, instance the name gives; None: the field ``I``).
ArduPilot 4.1 and later write ``ACC``/``GYR`` with an instance field; earlier versions (its
``IMU_RAW`` logging) wrote ``ACC1``…``ACC3`` and ``GYR1``…``GYR3``, one name per instance."""
_RAW_DTYPE = np.dtype([("timestamp_sample", "<u8"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
_DF_HEAD = b"\xa3\x95"
_DF_FMT_ID = 0x80
_TEXT_HEAD_BYTES = 4096
"""How far into a text DataFlash log its first ``FMT`` line may be (after the firmware's header lines)."""
_FLUSH_MESSAGES = 256
"""DataFlash or MAVLink messages of one IMU gathered before they are handed on as one block of rows."""
_READ_BYTES = 1 << 16
"""Bytes of a binary DataFlash log read at a time (:class:`DataFlashStream`): its memory, whatever the log's length."""
_MAX_TEXT_LINE = 1 << 16
"""Longest text DataFlash line read whole (a real one is under 1 kB); a longer one is counted corrupt."""
_DF_MAX_MESSAGE = 255
"""The longest DataFlash message: ``FMT`` gives a message's length, header included, in one byte."""
_DF_MAX_INSTANCE = 256
"""Instance numbers (``I``, ``VIBE``'s ``IMU``) are a uint8 in ArduPilot's formats; another value is a corrupt message."""
_MESSAGE_NAME = re.compile(r"[A-Za-z0-9_.]+")
"""A message type or topic name a log can hold; another "name" is the first field of a damaged line or record."""
NUMPY_DECODING = True
"""Binary DataFlash and tlog IMU messages decoded with numpy (:mod:`protocols.dataflash_numpy`,
:mod:`protocols.tlog_numpy`); False: pymavlink's decoding of every message (the tests' oracle)."""
_HOLDS_SHOWN = 40
"""Message types listed in :meth:`LogStats.holds`: a damaged text log makes a "type" of every garbled line."""


class LogFormat(StrEnum):
    TLOG = "tlog"
    DATAFLASH_BIN = "bin"
    DATAFLASH_TEXT = "log"
    ULOG = "ulg"


class NoImuDataError(ValueError):
    """A readable log that holds no IMU data; the message names what it holds."""


def detect_format(path: str | os.PathLike[str]) -> LogFormat:
    """The format of a log file, from its content (never from the extension).

    ULog by its magic bytes; binary DataFlash by its message header ``A3 95``; text
    DataFlash by an ``FMT,`` line within the first :data:`_TEXT_HEAD_BYTES` of a text
    file (firmware writes header lines such as its name and free RAM first, CRLF or
    LF); a tlog by a MAVLink 1 or 2 start byte after the first 8-byte time stamp.
    Raises ``ValueError`` for a file that is none of these.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(_TEXT_HEAD_BYTES)
    if head.startswith(ULOG_MAGIC):
        return LogFormat.ULOG
    if head.startswith(_DF_HEAD):
        return LogFormat.DATAFLASH_BIN
    first_fmt = head.find(b"FMT,")
    if first_fmt >= 0 and (first_fmt == 0 or head[first_fmt - 1] in b"\r\n"):
        before = head[:first_fmt]
        if all(32 <= c < 127 or c in b"\r\n\t" for c in before):
            return LogFormat.DATAFLASH_TEXT
    # A tlog record: 8-byte stamp, then a MAVLink 1 (0xFE) or 2 (0xFD) start byte.
    if len(head) > 8 and head[8] in (0xFE, 0xFD):
        return LogFormat.TLOG
    raise ValueError(
        f"{path}: not a MAVLink .tlog, a DataFlash .bin/.log or a PX4 ULog (first bytes {head[:12].hex()})"
    )


@dataclass
class LogStats:
    """What a :class:`LogReader` read and left out.

    ``messages``: IMU messages (or topics) read, by kind; ``samples``: samples kept per IMU;
    ``dropped``: samples left out, by reason; ``sources``: the message or topic of each IMU;
    ``clipped``: clipped samples per IMU (ULog: samples with a clipping flag; DataFlash: the
    growth of ``VIBE``'s clip counters over the log; absent when the log does not say);
    ``held``: every message type (topic instance) of the log with its count; ``skipped``:
    IMU instances not replayed and why; ``skipped_bytes``: bytes that start no message, passed
    over to the next one; ``cut_at_byte``: where the file ends in the middle of a message;
    ``logger_lost``: how often the autopilot's logger said it lost data (ULog dropout messages,
    with their ``logger_lost_ms``; DataFlash: writes its logger refused, the growth of ``DSF.Dp``);
    ``clock_restarts``: how often the log's time started again (:data:`CLOCK_RESTART_SAMPLES`): the
    most of any IMU, as a reboot restarts every IMU's clock once.
    """

    messages: dict[str, int] = field(default_factory=dict)
    samples: dict[int, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    sources: dict[int, str] = field(default_factory=dict)
    clipped: dict[int, int] = field(default_factory=dict)
    held: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    skipped_bytes: int = 0
    cut_at_byte: int | None = None
    logger_lost: int = 0
    logger_lost_ms: int | None = None
    clock_restarts: int = 0

    def _drop(self, reason: str, n: int = 1) -> None:
        if n:
            self.dropped[reason] = self.dropped.get(reason, 0) + n

    def left_out(self) -> str:
        """What reading left out, for a summary line: dropped samples and messages, skipped bytes, or ``none``."""
        parts = [f"{k} {n}" for k, n in sorted(self.dropped.items())]
        if self.skipped_bytes:
            parts.append(f"skipped_bytes {self.skipped_bytes}")
        return ", ".join(parts) or "none"

    def cut(self) -> str:
        """Where the file ends in the middle of a message, for a message; ``""`` for a whole file."""
        return "" if self.cut_at_byte is None else f"cut mid-message at byte {self.cut_at_byte}"

    def logger(self) -> str:
        """What the autopilot's logger said it lost, for a message; ``""`` when it said nothing.

        A gap in an IMU's samples there is the logger's, not the sensor's."""
        if not self.logger_lost:
            return ""
        if self.logger_lost_ms is not None:
            return (
                f"the logger lost data {self.logger_lost} times, {self.logger_lost_ms} ms in all "
                "(ULog dropouts): gaps in the samples there are the logger's"
            )
        return (
            f"the logger refused {self.logger_lost} writes (DSF.Dp): messages of every type, "
            "IMU ones among them, are missing from the log"
        )

    def clock(self) -> str:
        """How often an IMU's time started again, for a message; ``""`` when it never did."""
        if not self.clock_restarts:
            return ""
        return (
            f"the time of the samples started again {self.clock_restarts} time(s) (an autopilot reboot, "
            "or logs joined end to end): what follows is replayed as a stream that restarted"
        )

    def holds(self) -> str:
        """What the log holds, for a message: message types (topics) with their counts."""
        named = sorted((k, n) for k, n in self.held.items() if n and _MESSAGE_NAME.fullmatch(k))
        garbled = sum(n for k, n in self.held.items() if n and not _MESSAGE_NAME.fullmatch(k))
        held = ", ".join(f"{k} {n}" for k, n in named[:_HOLDS_SHOWN]) or "nothing readable"
        if len(named) > _HOLDS_SHOWN:
            held += f" and {len(named) - _HOLDS_SHOWN} more types"
        if garbled:
            held += f"; {garbled} messages with unreadable names"
        left_out = [f"{k} {v}" for k, v in sorted(self.skipped.items())]
        if (read := self.left_out()) != "none":
            left_out.append(read)
        if self.cut_at_byte is not None:
            left_out.append(self.cut())
        return held + (f"; left out: {'; '.join(left_out)}" if left_out else "")


JUMP_HOLD_S = 1.0
"""A sample this much later than the one before it is held until the next one says what it is: a time
stamp gone wrong (the next one goes on from before it: it is left out as ``time_glitch``) or a gap
in the log (the next one is later still: both are kept)."""
CLOCK_RESTART_SAMPLES = 16
"""This many samples in a row earlier than the last one kept, and increasing among themselves, are a
clock that started again (an autopilot reboot, logs joined end to end): they are kept, as a stream
that restarted, which the pipeline detects as the daemon's does (``source_restarts``). Fewer are
late samples, left out as ``time_not_increasing``."""


@dataclass
class _Buffer:
    parts: list[ImuRows] = field(default_factory=list)
    n: int = 0
    seq: int = 0
    last_t_s: float = -np.inf
    held: ImuRows | None = None
    """A sample after a jump of more than :data:`JUMP_HOLD_S`, until the next sample."""
    back: list[ImuRows] = field(default_factory=list)
    """Samples earlier than ``last_t_s``, increasing among themselves: a restarted clock or late samples."""
    run: int = 0
    """How often this IMU's clock started again: the run id of its batches (:data:`CLOCK_RESTART_SAMPLES`)."""

    @property
    def back_n(self) -> int:
        return sum(p.t_s.size for p in self.back)


_Sample = tuple[
    str, int, float, tuple[float, float, float], tuple[float, float, float], float | None
]


def _rows_from_samples(samples: Iterator[_Sample | ImuRows], flush: int) -> Iterator[ImuRows]:
    """Blocks of rows from per-message samples, one IMU's block each time it has ``flush`` messages.

    Rows the source has already built (paired ``ACC``/``GYR``) pass through.
    """
    pending: dict[int, list[_Sample]] = {}
    for s in samples:
        if isinstance(s, ImuRows):
            yield s
            continue
        block = pending.setdefault(s[1], [])
        block.append(s)
        if len(block) >= flush:
            yield _block(block)
            pending[s[1]] = []
    for imu in sorted(pending):
        if pending[imu]:
            yield _block(pending[imu])


def _block(block: list[_Sample]) -> ImuRows:
    kinds = {s[0] for s in block}
    temps = [s[5] for s in block]
    return ImuRows(
        block[0][0] if len(kinds) == 1 else "/".join(sorted(kinds)),
        block[0][1],
        np.array([s[2] for s in block], dtype=float),
        np.array([s[3] for s in block], dtype=float),
        np.array([s[4] for s in block], dtype=float),
        None if any(t is None for t in temps) else np.array(temps, dtype=float),
        np.zeros(len(block), dtype=bool),
    )


class LogReader:
    """Iterate a log as :class:`~protocols.frames.SampleBatch` values (module docstring).

    Parameters
    ----------
    path : the log file.
    vehicle : vehicle id given to the batches.
    batch_samples : samples per batch (the last of each IMU may be shorter).
    join_frames : up to this many full batches of one IMU that come one after the other, joined
        in one, numbered as the last of them (its ``seq`` steps by the batches it joins; a
        shorter batch always comes alone; held until that many, another IMU's rows, a restart or
        the end): ``frames_of`` tells how many a batch joins.
    log_format : override :func:`detect_format`.
    raw_scale, imu_index : MAVLink settings (:mod:`protocols.mavlink_adapter`), tlog only.

    After iterating, :attr:`stats` holds the counts. Iterating again reads the
    file again and gives the same batches. A log with no IMU data raises
    :class:`NoImuDataError` at the end of the iteration, naming what it holds.
    :attr:`fraction_read` follows the reading (0 … 1) for progress lines.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        vehicle: str = "replay",
        batch_samples: int = 1000,
        join_frames: int = 1,
        log_format: LogFormat | None = None,
        raw_scale: ImuScale = RAW_IMU_ARDUPILOT,
        imu_index: Mapping[ImuMessage, int] = DEFAULT_IMU_INDEX,
    ):
        if not 1 <= batch_samples <= MAX_SAMPLES:
            raise ValueError(f"batch_samples must be in 1..{MAX_SAMPLES}, got {batch_samples}")
        if not 1 <= join_frames <= MAX_SAMPLES // batch_samples:
            raise ValueError(
                f"join_frames must be in 1..{MAX_SAMPLES // batch_samples}, got {join_frames}"
            )
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"{self.path}: no such log file")
        self.format = LogFormat(log_format) if log_format is not None else detect_format(self.path)
        self.vehicle = vehicle
        self._batch = int(batch_samples)
        self._join = int(join_frames)
        self._raw_scale = raw_scale
        self._imu_index = imu_index
        self._ulog = UlogImuStream(self.path) if self.format is LogFormat.ULOG else None
        self.stats = LogStats()
        self._fraction: Callable[[], float] = lambda: 0.0

    @property
    def fraction_read(self) -> float:
        return float(self._fraction())

    @property
    def system(self) -> str:
        """The system that wrote the log, where the log says (ULog: ``sys_name ver_hw``), else ``""``."""
        return self._ulog.contents.system if self._ulog is not None else ""

    def __iter__(self) -> Iterator[SampleBatch]:
        self.stats = LogStats()
        buffers: dict[int, _Buffer] = {}
        last: int | None = None  # the IMU of the last rows: the only one holding full batches
        for rows in self._rows():
            stats = self.stats
            n = rows.t_s.size
            stats.messages[rows.kind] = stats.messages.get(rows.kind, 0) + n
            stats.sources.setdefault(rows.imu, rows.kind)
            if last is not None and last != rows.imu:
                # Another IMU's rows: the full batches held for joining go first, as they came.
                yield from self._full(last, buffers[last])
            last = rows.imu
            buf = buffers.setdefault(rows.imu, _Buffer())
            finite = finite_rows(rows.t_s, rows.accel_mps2, rows.gyro_rps, rows.temp_c)
            stats._drop("non_finite", int(n - finite.sum()))
            for piece in _in_order(buf, rows, finite, stats):
                if piece is None:
                    # The clock started again: what came before is the old run's last batch (a batch
                    # going back in time inside was refused past its turn), what follows a new run's.
                    yield from self._full(rows.imu, buf)
                    if buf.n:
                        yield self._emit(rows.imu, buf, buf.n)
                    buf.run += 1
                    # Every IMU restarts at a reboot: one reboot is one restart, however many IMUs.
                    stats.clock_restarts = max(stats.clock_restarts, buf.run)
                    continue
                self._keep(rows.imu, buf, [piece])
                while buf.n >= self._batch * self._join:
                    yield self._emit(rows.imu, buf, self._batch * self._join, frames=self._join)
        if last is not None:
            yield from self._full(last, buffers[last])
        for imu in sorted(buffers):
            buf = buffers[imu]
            # The log ended: a held sample had no next one to tell a glitch (it is kept); a run of
            # earlier samples too short to be a restarted clock is late samples.
            self._keep(imu, buf, [buf.held] if buf.held is not None else [])
            self.stats._drop("time_not_increasing", buf.back_n)
            buf.held, buf.back = None, []
            while buf.n:
                yield self._emit(imu, buf, buf.n)
        if not self.stats.samples:
            what = (
                "topics sensor_combined, sensor_accel+sensor_gyro, vehicle_imu"
                if self.format is LogFormat.ULOG
                else "messages IMU, IMU2, IMU3"
                if self.format is not LogFormat.TLOG
                else "messages " + ", ".join(m.value for m in ImuMessage)
            )
            raise NoImuDataError(
                f"{self.path}: no IMU data ({what}); the log holds {self.stats.holds()}"
            )

    def _keep(self, imu: int, buf: _Buffer, pieces: list[ImuRows]) -> None:
        for kept in pieces:
            buf.parts.append(kept)
            buf.n += kept.t_s.size
            self.stats.samples[imu] = self.stats.samples.get(imu, 0) + kept.t_s.size
            if self.format is LogFormat.ULOG:
                self.stats.clipped[imu] = self.stats.clipped.get(imu, 0) + int(kept.clipped.sum())

    def _rows(self) -> Iterator[ImuRows]:
        if self._ulog is not None:
            ulog = self._ulog
            self._fraction = lambda: ulog.fraction_read
            yield from ulog
            self.stats.held = {k: n for k, n in ulog.contents.topics.items() if n}
            self.stats.skipped = dict(ulog.contents.skipped)
            if ulog.contents.corrupt_messages:
                self.stats._drop("corrupt_messages", ulog.contents.corrupt_messages)
            self.stats._drop("data_without_subscription", ulog.contents.unsubscribed_data)
            self.stats.cut_at_byte = ulog.contents.cut_at_byte
            self.stats.logger_lost = ulog.contents.dropouts
            self.stats.logger_lost_ms = ulog.contents.dropout_ms
            return
        samples = (
            self._tlog_samples() if self.format is LogFormat.TLOG else self._dataflash_samples()
        )
        yield from _rows_from_samples(samples, min(self._batch, _FLUSH_MESSAGES))

    def _full(self, imu: int, buf: _Buffer) -> Iterator[SampleBatch]:
        """The full batches ``buf`` holds, joined up to ``join_frames`` in one."""
        while buf.n >= self._batch:
            k = min(buf.n // self._batch, self._join)
            yield self._emit(imu, buf, k * self._batch, frames=k)

    def frames_of(self, batch: SampleBatch) -> int:
        """How many batches of ``batch_samples`` the reader's ``batch`` joins (``join_frames``)."""
        return -(-batch.n_samples // self._batch)

    def _emit(self, imu: int, buf: _Buffer, n: int, *, frames: int = 1) -> SampleBatch:
        rows = _concat(buf.parts)
        head = _select(rows, slice(0, n))
        rest = _select(rows, slice(n, None))
        buf.parts, buf.n = ([rest] if rest.t_s.size else []), rest.t_s.size
        batch = SampleBatch(
            self.vehicle,
            imu,
            buf.seq + frames - 1,
            head.t_s,
            head.accel_mps2,
            head.gyro_rps,
            head.temp_c,
            buf.run,
        )
        buf.seq += frames
        return batch

    def _tlog_samples(self) -> Iterator[_Sample | ImuRows]:
        from pymavlink import mavutil

        from protocols.mavlink_adapter import (
            decode_imu_message,
            highres_triads_updated,
            use_mavlink2,
        )

        size = max(os.path.getsize(self.path), 1)
        start = 0
        if NUMPY_DECODING:
            # Imported here: the numpy decoder builds on this module's definitions.
            from protocols.tlog_numpy import TlogScan

            scan = TlogScan(
                self.path,
                held=self.stats.held,
                dropped=self.stats.dropped,
                flush=min(self._batch, _FLUSH_MESSAGES),
                raw_scale=self._raw_scale,
                imu_index=self._imu_index,
            )
            self._fraction = lambda: scan.offset / size
            yield from scan
            yield from scan.pending_samples()
            if scan.stopped_at is None:
                return
            start = scan.stopped_at
        # mavlogfile reads sequentially (flat memory) and, unlike mavutil.mavlink_connection's
        # mmap reader, parses nothing before use_mavlink2 has given it its own MAVLink 2 parser.
        conn = use_mavlink2(mavutil.mavlogfile(str(self.path), notimestamps=False))
        conn.f.seek(
            start
        )  # where the numpy decoder stopped: a record's start, as after a good message
        self._fraction = lambda: conn.f.tell() / size
        types = {m.value for m in ImuMessage}
        stats = self.stats
        try:
            while (msg := conn.recv_msg()) is not None:
                kind = msg.get_type()
                stats.held[kind] = stats.held.get(kind, 0) + 1
                # pymavlink's verdict on a packet with a bad CRC, or on bytes that start no packet.
                if kind == "BAD_DATA":
                    stats._drop("corrupt_messages")
                    stats.skipped_bytes += len(msg.data)
                    continue
                if kind not in types:
                    continue
                if not highres_triads_updated(msg):
                    stats._drop(LinkRejection.FIELDS_NOT_UPDATED.value)
                    continue
                s = decode_imu_message(msg, raw_scale=self._raw_scale, imu_index=self._imu_index)
                if s is not None:
                    yield kind, s.imu, s.t_s, s.accel_mps2, s.gyro_rps, s.temp_c
            if pending := conn.mav.buf_len():
                stats.cut_at_byte = os.path.getsize(self.path) - pending
        finally:
            conn.close()

    def _dataflash_samples(self) -> Iterator[_Sample | ImuRows]:
        # Imported here: the numpy decoder builds on this module's definitions (formats, limits).
        from protocols.dataflash_numpy import DataFlashScan
        from protocols.dataflash_text_numpy import DataFlashTextScan

        wanted = frozenset([*DATAFLASH_IMU_NAMES, *DATAFLASH_RAW_NAMES, "VIBE", "DSF"])
        stream: DataFlashStream | DataFlashScan | DataFlashTextScan
        flush = min(self._batch, _FLUSH_MESSAGES)
        if self.format is LogFormat.DATAFLASH_BIN and NUMPY_DECODING:
            stream = DataFlashScan(self.path, wanted=wanted, held=self.stats.held, flush=flush)
        elif NUMPY_DECODING:
            stream = DataFlashTextScan(self.path, wanted=wanted, held=self.stats.held, flush=flush)
        else:
            binary = self.format is LogFormat.DATAFLASH_BIN
            stream = DataFlashStream(self.path, binary=binary, wanted=wanted, held=self.stats.held)
        size = max(os.path.getsize(self.path), 1)
        self._fraction = lambda: stream.offset / size
        clip: dict[int, list[float]] = {}
        refused: list[int] = []  # DSF.Dp: the last value, then the writes refused over the log
        raw: dict[tuple[int, bool], list[tuple[int, float, float, float]]] = {}
        pairs: dict[int, NearestPairer] = {}
        suffix: dict[int, str] = {}  # per instance: "" (ACC/GYR) or its number (ACC1/GYR1 ...)
        corrupt = 0
        for msg in stream:
            if isinstance(msg, ImuRows):  # IMU messages DataFlashScan decoded
                yield msg
                continue
            name = msg.get_type()
            fields = msg.get_fieldnames()
            try:
                if name == "VIBE":
                    _note_clipping(msg, fields, clip)
                    continue
                if name == "DSF":
                    _note_refused_writes(msg, refused)
                    continue
                if name in DATAFLASH_RAW_NAMES:
                    inst = _note_raw(msg, fields, raw)
                    suffix[inst] = name[3:]
                else:
                    sample = _imu_sample(msg, fields)
            except FIELD_ERRORS:
                corrupt += 1
                continue
            if name not in DATAFLASH_RAW_NAMES:
                yield sample
            elif len(raw[(inst, DATAFLASH_RAW_NAMES[name][0])]) >= _FLUSH_MESSAGES:
                yield from _pair_raw(raw, pairs, inst, suffix[inst])
        for inst in sorted({i for i, _ in raw}):
            yield from _pair_raw(raw, pairs, inst, suffix[inst])
        if isinstance(stream, DataFlashScan | DataFlashTextScan):
            yield from stream.pending_samples()
        self.stats._drop("corrupt_messages", corrupt + stream.corrupt)
        self.stats.skipped_bytes += stream.skipped_bytes
        self.stats.cut_at_byte = stream.cut_at_byte
        for inst, pairer in sorted(pairs.items()):
            pairer.finish()
            if pairer.unpaired_accel:
                accel, gyro = pairer.kind.split("+")
                self.stats.skipped[f"{accel}.{inst}"] = (
                    f"{pairer.unpaired_accel} samples without a {gyro} sample near in time"
                )
        for name in ("ISBH", "ISBD"):
            if held := self.stats.held.get(name):
                self.stats.skipped[name] = (
                    f"{held} messages of the batch sampler's raw samples: read into the report's firmware "
                    "section (noise, spectra, clipping), not replayed through the pipeline"
                )
        self.stats.clipped = {imu: int(last - first) for imu, (first, last) in sorted(clip.items())}
        self.stats.logger_lost = refused[1] if refused else 0


FIELD_ERRORS = (ValueError, TypeError, AttributeError, OverflowError)
"""What reading a DataFlash message's fields raises for a corrupt one: a field that is not a number
(text, or a string or array in the format), missing, or a text log's integer too large for a float."""


def _whole(value: Any, limit: int) -> int:
    """A field that must be a whole number in ``0 .. limit - 1``; ``ValueError`` (a corrupt message) otherwise."""
    try:
        number = int(value)
    except OverflowError:  # inf
        raise ValueError(f"{value!r} is not a whole number") from None
    if not 0 <= number < limit:
        raise ValueError(f"{value!r} is outside 0..{limit - 1}")
    return number


def _imu_sample(msg: Any, fields: list[str]) -> _Sample:
    """The sample of an ``IMU``/``IMU2``/``IMU3`` message (module docstring)."""
    name = msg.get_type()
    return (
        name,
        _whole(msg.I, _DF_MAX_INSTANCE) if "I" in fields else DATAFLASH_IMU_NAMES.index(name),
        float(msg.TimeUS) * 1e-6 if "TimeUS" in fields else float(msg.TimeMS) * 1e-3,
        (float(msg.AccX), float(msg.AccY), float(msg.AccZ)),
        (float(msg.GyrX), float(msg.GyrY), float(msg.GyrZ)),
        float(msg.T) if "T" in fields else None,
    )


def _note_raw(
    msg: Any, fields: list[str], raw: dict[tuple[int, bool], list[tuple[int, float, float, float]]]
) -> int:
    """Gather a per-sample message (:data:`DATAFLASH_RAW_NAMES`: one triad, sampled at ``SampleUS``)
    for pairing by time; its instance."""
    is_accel, named = DATAFLASH_RAW_NAMES[msg.get_type()]
    inst = _whole(msg.I, _DF_MAX_INSTANCE) if "I" in fields else (named or 0)
    prefix = "Acc" if is_accel else "Gyr"
    time_us = msg.SampleUS if "SampleUS" in fields else msg.TimeUS
    raw.setdefault((inst, is_accel), []).append(
        (
            _whole(time_us, 1 << 64),  # _RAW_DTYPE's uint64
            float(getattr(msg, prefix + "X")),
            float(getattr(msg, prefix + "Y")),
            float(getattr(msg, prefix + "Z")),
        )
    )
    return inst


def _df_format(type_id: int, name: str, length: int, fmt: str, columns: str) -> Any:
    """pymavlink's ``DFFormat`` of an ``FMT`` definition; ``ValueError`` for one it cannot decode.

    Refused besides: more columns than format characters (``DFMessage`` would index past its
    values when a column is read), and a redefinition of ``FMT`` itself other than the one every
    log assumes (the readers take an ``FMT``'s fields by position).
    """
    from pymavlink import DFReader

    if length < 3 or any(c not in DFReader.FORMAT_TO_STRUCT for c in fmt):
        # Checked here: DFFormat prints to stdout and raises a bare Exception for an unknown character.
        raise ValueError(f"FMT of {name!r}: length {length}, format {fmt!r}")
    if len(columns.split(",")) > len(fmt):
        raise ValueError(f"FMT of {name!r}: columns {columns!r} outnumber format {fmt!r}")
    f = _FMT_OF_FMT
    if (type_id == f.type_id or name == f.name) and (type_id, name, length, fmt) != (
        f.type_id,
        f.name,
        f.length,
        f.fmt,
    ):
        raise ValueError(f"FMT redefines FMT: type {type_id}, length {length}, format {fmt!r}")
    return DFReader.DFFormat(type_id, name, length, fmt, columns)


def _fmt_of_fmt() -> Any:
    """The ``FMT`` message's own format (the writers' :data:`_FMT_OF_FMT`), which every log assumes."""
    from pymavlink import DFReader

    f = _FMT_OF_FMT
    return DFReader.DFFormat(f.type_id, f.name, f.length, f.fmt, ",".join(f.columns))


class _StreamCounts:
    """What a DataFlash reader read so far: :class:`DataFlashStream`'s attributes."""

    def __init__(self, path: Path, wanted: frozenset[str], held: dict[str, int]) -> None:
        self.path = path
        self.wanted = wanted
        self.held = held
        self.offset = 0
        self.corrupt = 0
        self.skipped_bytes = 0
        self.cut_at_byte: int | None = None


class DataFlashStream(_StreamCounts):
    """The messages of a DataFlash log (binary or text) in file order, read as a stream.

    pymavlink's ``DFReader_binary`` and ``DFReader_text`` index a whole log when they open it (an
    offset per message, the file mapped into memory), so their memory grows with the log: a
    one-hour 1 kHz log took 417 MB (``.bin``) and 770 MB (``.log``) to replay. This reads the file
    front to back and holds the message formats, a read buffer and the message at hand, whatever
    the log's length. Decoding is pymavlink's own, as ``DFReader`` does it: ``DFFormat`` turns each
    ``FMT`` definition into the struct format, columns and multipliers of its type, and
    ``DFMessage`` gives the typed, scaled fields (``msg.AccX``, ``get_type()``, ``get_fieldnames()``).

    * Binary: a message is ``A3 95 <type>`` and the body its type's ``FMT`` defines (``FMT`` itself
      is type 128). Bytes that do not start a message of a defined type are skipped to the next
      ``A3 95``, as ``DFReader`` does, and counted in :attr:`skipped_bytes`; a body that does not
      unpack, or an ``FMT`` that defines no usable format, is counted in :attr:`corrupt` and reading
      resumes after its header. A message cut by the end of the file ends the log, and
      :attr:`cut_at_byte` says where it starts.
    * Text: the lines before the first ``FMT`` line (the firmware's name, free RAM, board) are
      skipped; fields are split at ``", "``, or at ``","`` where the ``FMT`` lines use that; CRLF
      or LF. A line of an undefined type, or with fewer fields than its format, is skipped; one
      longer than :data:`_MAX_TEXT_LINE` is read past in pieces and counted in :attr:`corrupt`. A
      last line without a line break (the firmware ends every line with one) is cut: not decoded,
      and :attr:`cut_at_byte` says where it starts.

    Only the messages named in ``wanted`` are decoded and yielded; every message is counted by name
    in ``held`` as the stream goes. :attr:`offset` is the number of bytes read so far.
    """

    def __init__(
        self, path: Path, *, binary: bool, wanted: frozenset[str], held: dict[str, int]
    ) -> None:
        _StreamCounts.__init__(self, path, wanted, held)
        self.binary = binary
        self.formats: dict[str, Any] = {"FMT": _fmt_of_fmt()}
        """Text: the formats defined so far, by name."""
        self.delimiter = ""
        """Text: what separates the fields (``", "`` or ``","``, as the first ``FMT`` line has it)."""

    def __iter__(self) -> Iterator[Any]:
        return self._binary() if self.binary else self._text()

    def _binary(self) -> Iterator[Any]:
        from pymavlink import DFReader

        formats = {_DF_FMT_ID: _fmt_of_fmt()}
        unpack: dict[int, Callable[[bytes], tuple[Any, ...]]] = {}
        held, wanted = self.held, self.wanted
        buf, pos, eof = b"", 0, False
        with open(self.path, "rb") as fh:
            while True:
                avail = len(buf) - pos
                if avail < _DF_MAX_MESSAGE and not eof:
                    chunk = fh.read(_READ_BYTES)
                    eof, self.offset = not chunk, fh.tell()
                    buf, pos = buf[pos:] + chunk, 0
                    continue
                if avail < 3:
                    if avail:
                        self.cut_at_byte = self.offset - avail
                    return
                type_id = buf[pos + 2]
                fmt = formats.get(type_id) if buf[pos] == 0xA3 and buf[pos + 1] == 0x95 else None
                if fmt is None:
                    found = buf.find(_DF_HEAD, pos + 1)
                    # Short of the end, the last byte may be the A3 of a header the next read completes.
                    resume = found if found >= 0 else len(buf) - (0 if eof else 1)
                    self.skipped_bytes += resume - pos
                    pos = resume
                    continue
                n = fmt.len
                if avail < n:
                    self.cut_at_byte = self.offset - avail
                    return
                held[fmt.name] = held.get(fmt.name, 0) + 1
                if type_id == _DF_FMT_ID or fmt.name in wanted:
                    try:
                        if type_id not in unpack:
                            unpack[type_id] = struct.Struct(fmt.msg_struct).unpack
                        elements = list(unpack[type_id](buf[pos + 3 : pos + n]))
                        if type_id == _DF_FMT_ID:
                            null_term = DFReader.null_term
                            defined = _df_format(
                                elements[0],
                                null_term(elements[2]),
                                elements[1],
                                null_term(elements[3]),
                                null_term(elements[4]),
                            )
                            formats[defined.type] = defined
                            unpack.pop(defined.type, None)
                    except (struct.error, ValueError):
                        self.corrupt += 1
                        pos += 3
                        continue
                    if type_id != _DF_FMT_ID:
                        for k in fmt.a_indexes:  # int16[32] fields, as DFReader gives them
                            elements[k] = array.array("h", elements[k])
                        yield DFReader.DFMessage(fmt, elements, True, None)
                pos += n

    def _text(self) -> Iterator[Any]:
        with open(self.path, "rb") as fh:
            for line in _bounded_lines(fh, _MAX_TEXT_LINE):
                start, self.offset = self.offset, fh.tell()
                if line is None:
                    self.corrupt += 1
                    continue
                if not line.endswith(b"\n"):
                    self.cut_at_byte = start
                    return
                if (msg := self._text_line(line)) is not None:
                    yield msg

    def _text_line(self, line: bytes) -> Any | None:
        """Read one whole text line (its line break included): counted, a format defined, or the
        ``DFMessage`` of a wanted message returned."""
        if not self.delimiter:
            if not line.startswith(b"FMT,"):
                return None  # the firmware's header lines
            self.delimiter = ", " if line.startswith(b"FMT, ") else ","
        delimiter = self.delimiter
        fields = line.rstrip().decode("utf-8", "backslashreplace").split(delimiter)
        if len(fields) < 2:
            return None
        name, values = fields[0], fields[1:]
        self.held[name] = self.held.get(name, 0) + 1
        fmt = self.formats.get(name)
        if fmt is None:
            return None
        if len(values) < len(fmt.format):
            # A line cut short (a field lost): counted where it was wanted, as a binary
            # message that does not decode is.
            if name == "FMT" or name in self.wanted:
                self.corrupt += 1
            return None
        if name == "FMT":
            if delimiter == ",":  # the columns, themselves comma-separated, were split too
                values = [*values[:4], ",".join(values[4:])]
            columns = values[4]
            if values[2] == "FMT" and columns == "Type,Length,Name,Format":
                columns += ",Columns"  # some text logs leave the column out
            try:
                defined = _df_format(int(values[0]), values[2], int(values[1]), values[3], columns)
            except ValueError:
                self.corrupt += 1
                return None
            self.formats[defined.name] = defined
        elif name in self.wanted:
            from pymavlink import DFReader

            return DFReader.DFMessage(fmt, values, False, None)
        return None


def _bounded_lines(fh: BinaryIO, limit: int) -> Iterator[bytes | None]:
    """The lines of ``fh``; ``None`` for a line longer than ``limit`` bytes, read past in pieces.

    A file without line breaks (not a text log, or a damaged one) then costs ``limit``
    bytes of memory, not its size.
    """
    while line := fh.readline(limit):
        if len(line) < limit or line.endswith(b"\n"):
            yield line
            continue
        while (rest := fh.readline(limit)) and not rest.endswith(b"\n"):
            pass
        yield None


def _pair_raw(
    raw: dict[tuple[int, bool], list[tuple[int, float, float, float]]],
    pairs: dict[int, NearestPairer],
    inst: int,
    suffix: str,
) -> Iterator[ImuRows]:
    """Hand the per-sample messages gathered for instance ``inst`` to its pairer; the pairs it completes.

    The pairer is named after the messages: ``ACC+GYR``, or ``ACC1+GYR1`` … (``suffix``) in a log
    of ArduPilot before 4.1."""
    if inst not in pairs:
        pairs[inst] = NearestPairer(f"ACC{suffix}+GYR{suffix}", DATAFLASH_RAW_BASE + inst)
    pairer = pairs[inst]
    for is_accel in (True, False):
        block = raw.pop((inst, is_accel), [])
        if block:
            pairer.add(is_accel, np.array(block, dtype=_RAW_DTYPE))
    rows = pairer.paired()
    if rows is not None and rows.t_s.size:
        yield rows


def _note_refused_writes(msg: Any, refused: list[int]) -> None:
    """The growth of ``DSF.Dp``, the writes the logger refused (a full buffer), in ``refused`` as
    [last value, total]. Counted from the first ``DSF``: its value may hold a previous log's (some
    ArduPilot versions clear the counter at a new log, others at boot); a value lower than the
    last is a counter cleared since."""
    value = _whole(msg.Dp, 1 << 32)
    if not refused:
        refused += [value, 0]
        return
    refused[1] += value - refused[0] if value >= refused[0] else value
    refused[0] = value


def _note_clipping(msg: Any, fields: list[str], clip: dict[int, list[float]]) -> None:
    """First and last value of VIBE's cumulative clip counters per IMU (``Clip0..2``, or ``IMU`` + ``Clip``)."""
    if "Clip" in fields:
        counters = {_whole(getattr(msg, "IMU", 0), _DF_MAX_INSTANCE): float(msg.Clip)}
    else:
        counters = {k: float(getattr(msg, f"Clip{k}")) for k in range(3) if f"Clip{k}" in fields}
    if not all(np.isfinite(v) for v in counters.values()):
        raise ValueError(f"VIBE clip counters {counters}")
    for imu, value in counters.items():
        clip.setdefault(imu, [value, value])[1] = value


def _in_order(
    buf: _Buffer, rows: ImuRows, finite: BoolArray, stats: LogStats
) -> list[ImuRows | None]:
    """The finite samples of ``rows`` to keep, in time order, with what ``buf`` held before them
    (:data:`JUMP_HOLD_S`, :data:`CLOCK_RESTART_SAMPLES`); ``buf`` carries what waits to the next rows.
    ``None`` among them: the clock started again there.

    A running maximum of the time stamps made one stamp gone wrong (a bit flipped: 2³² µs ahead) refuse
    every later sample of the log as not increasing, and a log across a reboot lost all after it."""
    t = rows.t_s
    last = buf.last_t_s
    if buf.held is None and not buf.back:
        steps = np.diff(t[finite], prepend=last)
        if np.all(steps > 0.0) and np.all(steps[np.isfinite(steps)] <= JUMP_HOLD_S):
            if finite.any():
                buf.last_t_s = float(t[finite][-1])
                return [_select(rows, finite)]
            return []
    out: list[ImuRows | None] = []
    run: list[int] = []  # indices of this block kept in a row, not yet in ``out``
    back: list[int] = []  # indices of this block in the run of earlier samples
    for k in map(int, np.flatnonzero(finite)):
        tk = float(t[k])
        if buf.held is not None:
            held_t = float(buf.held.t_s[0])
            if tk > held_t:  # a gap in the log: the held sample goes on, after those kept before it
                if run:
                    out.append(_select(rows, np.array(run)))
                    run = []
                out.append(buf.held)
                last = held_t
            else:  # back from before it: the held stamp went wrong
                stats._drop("time_glitch")
            buf.held = None
        if buf.back or back:
            back_last = float(t[back[-1]]) if back else float(buf.back[-1].t_s[-1])
            if tk > last:  # the clock goes on: the run was late samples
                stats._drop("time_not_increasing", buf.back_n + len(back))
                buf.back, back = [], []
            elif tk > back_last:
                back.append(k)
                if buf.back_n + len(back) >= CLOCK_RESTART_SAMPLES:
                    # The clock started again: the run is the new stream's first samples.
                    if run:
                        out.append(_select(rows, np.array(run)))
                    out += [None, *buf.back]
                    run, buf.back, back = back, [], []
                    last = tk
                continue
            else:
                stats._drop("time_not_increasing", buf.back_n + len(back))
                buf.back, back = [], [k]
                continue
        if tk <= last:
            back = [k]
        elif np.isfinite(last) and tk - last > JUMP_HOLD_S:
            buf.held = _select(rows, np.array([k]))
        else:
            run.append(k)
            last = tk
    if run:
        out.append(_select(rows, np.array(run)))
    if back:
        buf.back.append(_select(rows, np.array(back)))
    buf.last_t_s = last
    return out


def _select(rows: ImuRows, index: np.ndarray | slice) -> ImuRows:
    return ImuRows(
        rows.kind,
        rows.imu,
        rows.t_s[index],
        rows.accel_mps2[index],
        rows.gyro_rps[index],
        None if rows.temp_c is None else rows.temp_c[index],
        rows.clipped[index],
    )


def _concat(parts: list[ImuRows]) -> ImuRows:
    if len(parts) == 1:
        return parts[0]
    # Temperature only when every sample has one: a batch is all or nothing.
    temps = [p.temp_c for p in parts if p.temp_c is not None]
    temp_c = np.concatenate(temps) if len(temps) == len(parts) else None
    return ImuRows(
        parts[0].kind,
        parts[0].imu,
        np.concatenate([p.t_s for p in parts]),
        np.concatenate([p.accel_mps2 for p in parts]),
        np.concatenate([p.gyro_rps for p in parts]),
        temp_c,
        np.concatenate([p.clipped for p in parts]),
    )


def read_log_sessions(
    path: str | os.PathLike[str], **options: Any
) -> tuple[dict[int, ImuSession], LogStats]:
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
    path: str | os.PathLike[str],
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
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from protocols.mavlink_adapter import imu_message

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
            acc, gyr = session_triads(s)
            kind = messages[imu]
            base = DEFAULT_IMU_INDEX[kind]
            msg = imu_message(
                kind,
                t_s=t_s,
                accel_mps2=acc[k],
                gyro_rps=gyr[k],
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


def _dataflash_records(
    sessions: Mapping[int, ImuSession], per_imu: Mapping[int, _DfFormat]
) -> Iterator[tuple[_DfFormat, list[float]]]:
    for t_s, imu, k in _merged_rows(sessions):
        s, f = sessions[imu], per_imu[imu]
        acc, gyr = session_triads(s)
        values: list[float] = [round(t_s * 1e6)]
        if "I" in f.columns:
            values.append(imu)
        values += [float(v) for v in gyr[k]] + [float(v) for v in acc[k]]
        if "T" in f.columns and s.temp_c is not None:
            values.append(float(s.temp_c[k]))
        yield f, values


def write_dataflash_bin(
    path: str | os.PathLike[str], sessions: Mapping[int, ImuSession], *, legacy_names: bool = False
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
    path: str | os.PathLike[str], sessions: Mapping[int, ImuSession], *, legacy_names: bool = False
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
