"""MAVLink ``.tlog`` IMU messages decoded with numpy, for :class:`protocols.logs.LogReader`.

pymavlink parses a tlog a byte string and a Python message object at a time (52 k samples/s, the
bound of replaying one). A tlog is records of an 8-byte time stamp and one MAVLink packet, so
where each record starts follows from the packet lengths, a block of bytes at a time:

* the candidate records (a MAVLink 1 or 2 start byte 8 bytes on) are found by one vectorized
  scan, each one's length from its header, and the chain of real records among them by
  :func:`protocols.byte_chain.chain`;
* every packet's CRC is checked, vectorized: X.25 (the table from pymavlink's own ``x25crc``) over
  the packets of one length at a time, then the ``crc_extra`` of its message (pymavlink's dialect
  module, ``ardupilotmega`` as :func:`protocols.mavlink_adapter.use_mavlink2` parses);
* the IMU messages of a type are decoded at once with one structured dtype built from the
  dialect's ``unpacker`` format and field names (a MAVLink 2 payload cut of its trailing zeros
  padded back with them, as pymavlink does), converted to SI by
  :func:`protocols.mavlink_adapter.imu_fields_si`, and cut into the blocks of rows
  ``protocols.logs._rows_from_samples`` makes of per-message samples, in the same order.

Where a record is not that (a bad CRC, bytes that start no packet, a signed packet or incompatibility
flags, a message id the dialect does not know, a file cut mid-record), the fast path stops at the
good record before it and pymavlink reads the rest of the file from there: its recovery from damage
(``BAD_DATA``, then a scan for a time stamp near the last good message's) is pymavlink's alone, and
its parser starts that record in the state it has after every good message. Signed packets are
left to it because this checks no signature. pymavlink stays the oracle (tests/test_tlog_numpy.py).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from protocols.byte_chain import STRUCT_TO_NUMPY, chain
from protocols.dataflash_numpy import Blocker
from protocols.mavlink_adapter import FIELD_NAMES, imu_fields_si
from protocols.mavlink_settings import ImuMessage, ImuScale, LinkRejection
from protocols.ulog import ImuRows

BLOCK = 1 << 18
"""Bytes of a block: fewer, larger passes of the CRC over the packets (the 5-minute benchmark log
reads in 1.3 s at 64 KB, 0.85 s at 256 KB, 0.76 s at 1 MB on a loaded machine)."""
_STAMP = 8
_V1, _V2 = mavlink2.PROTOCOL_MARKER_V1, mavlink2.PROTOCOL_MARKER_V2
_HEADER = {_V1: 6, _V2: 10}
_MAX_RECORD = _STAMP + 10 + 255 + 2 + mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN


def _crc_table() -> np.ndarray:
    """X.25 by table: one byte's step from CRC 0 is pymavlink's ``x25crc`` of that byte, and a step
    from any CRC is ``crc >> 8`` xor the table at ``(crc ^ byte) & 0xFF``."""
    table = np.zeros(256, dtype=np.uint16)
    for b in range(256):
        crc = mavlink2.x25crc()
        crc.crc = 0
        crc.accumulate(bytes([b]))
        table[b] = crc.crc
    return table


_CRC_TABLE = _crc_table()


def _crc_pair_table(table: np.ndarray) -> np.ndarray:
    """Two bytes a step: with ``x = crc ^ (b0 | b1 << 8)`` the CRC after both is a function of ``x``
    alone (``(t >> 8) ^ table[((x >> 8) ^ t) & 0xFF]``, ``t = table[x & 0xFF]``): half the steps,
    each one lookup."""
    x = np.arange(1 << 16, dtype=np.uint32)
    t = table[x & 0xFF].astype(np.uint32)
    pairs: np.ndarray = ((t >> 8) ^ table[((x >> 8) ^ t) & 0xFF]).astype(np.uint16)
    return pairs


_CRC_PAIRS = _crc_pair_table(_CRC_TABLE)


def _dtype(cls: Any) -> np.dtype | None:
    """The payload of a dialect message class as a packed structured dtype; None for one with arrays."""
    fmt = cls.unpacker.format.lstrip("<")
    if any(cls.array_lengths) or len(fmt) != len(cls.ordered_fieldnames):
        return None
    return np.dtype(
        [(n, STRUCT_TO_NUMPY[c]) for n, c in zip(cls.ordered_fieldnames, fmt, strict=True)]
    )


class TlogScan:
    """The IMU messages of a tlog's longest clean start (module docstring) as blocks of rows, or
    with ``records`` the messages of those names instead, as structured arrays in :attr:`records`.

    Yields :class:`~protocols.ulog.ImuRows` blocks as ``_rows_from_samples`` would cut them;
    counts every message by type in ``held`` and HIGHRES_IMU messages without their triads
    updated in ``dropped``. After the iteration :attr:`stopped_at` is where pymavlink takes over
    (None: the file ended cleanly) and :meth:`pending_samples` the samples of blocks not complete.
    """

    def __init__(
        self,
        path: Path,
        *,
        held: dict[str, int],
        dropped: dict[str, int],
        flush: int,
        raw_scale: ImuScale,
        imu_index: Mapping[ImuMessage, int],
        records: frozenset[str] = frozenset(),
    ) -> None:
        self.path = path
        self.held = held
        self.dropped = dropped
        self.raw_scale = raw_scale
        self.imu_index = imu_index
        self.offset = 0
        self.stopped_at: int | None = None
        names = [m.value for m in ImuMessage]
        self._blocker = Blocker(flush, names)
        self._imu = {
            mavlink2.mavlink_map[mid].msgname: ImuMessage(mavlink2.mavlink_map[mid].msgname)
            for mid in mavlink2.mavlink_map
            if mavlink2.mavlink_map[mid].msgname in names and not records
        }
        self.records: dict[str, list[np.ndarray]] = {name: [] for name in records}

    def pending_samples(self) -> Iterator[Any]:
        return self._blocker.pending_samples()

    def __iter__(self) -> Iterator[ImuRows]:
        size = os.path.getsize(self.path)
        start: int | None = 0
        with open(self.path, "rb") as fh:
            while start is not None and start < size:
                fh.seek(start)
                data = fh.read(BLOCK + _MAX_RECORD)
                self.offset = start + len(data)
                rows, at, clean = self._block(data, self.offset >= size)
                yield from rows
                if not clean:
                    self.stopped_at = start + at
                    return
                start += at

    def _block(self, data: bytes, eof: bool) -> tuple[list[ImuRows], int, bool]:
        """The rows of the clean records that start in ``data[:BLOCK]``; where the next block starts,
        and whether it is clean there (False: pymavlink reads from there)."""
        d = np.frombuffer(data, dtype=np.uint8)
        end = d.size if eof else min(BLOCK, d.size)
        # Header bytes past the end read as zeros: a record there is cut, found so by its length.
        p = np.concatenate([d, np.zeros(_MAX_RECORD, dtype=np.uint8)])
        magic = p[_STAMP : end + _STAMP]
        cand = np.flatnonzero((magic == _V1) | (magic == _V2))
        if not cand.size or cand[0] != 0:
            return [], 0, False
        v2 = p[cand + _STAMP] == _V2
        length = p[cand + _STAMP + 1].astype(np.int64)
        header = np.where(v2, _HEADER[_V2], _HEADER[_V1])
        flags = np.where(v2, p[cand + _STAMP + 2], 0)
        signed = (flags & mavlink2.MAVLINK_IFLAG_SIGNED) != 0
        signature = np.where(signed, mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN, 0)
        landing = cand + _STAMP + header + length + 2 + signature
        k = np.searchsorted(cand, landing)
        hit = k < cand.size
        hit[hit] = cand[k[hit]] == landing[hit]
        succ = np.where(hit, k, -1)
        path = chain(0, succ)
        r = cand[path]
        id_v2 = p[r + 15] | (p[r + 16].astype(np.int64) << 8) | (p[r + 17].astype(np.int64) << 16)
        msgid = np.where(v2[path], id_v2, p[r + 13])
        ok = (landing[path] <= d.size) & (flags[path] == 0)
        extra = np.full(path.size, -1, dtype=np.int64)
        for mid in np.unique(msgid).tolist():
            cls = mavlink2.mavlink_map.get(mid)
            if cls is not None:
                extra[msgid == mid] = cls.crc_extra
        ok &= extra >= 0
        ok &= self._crc_ok(p, r, header[path], length[path], extra)
        bad = np.flatnonzero(~ok)
        n = int(bad[0]) if bad.size else path.size
        if n == path.size and eof and landing[path[-1]] == d.size:
            nxt, clean = d.size, True
        else:
            # The last good record is left to whoever reads on: the next block, or pymavlink,
            # whose recovery after a bad packet starts from the last good message's time stamp.
            n = max(n - 1, 0)
            nxt = int(r[n])
            clean = n + 1 == path.size and landing[path[-1]] >= end and not eof
        rows = self._decode(p, r[:n], v2[path[:n]], header[path[:n]], length[path[:n]], msgid[:n])
        return rows, nxt, clean

    @staticmethod
    def _crc_ok(
        p: np.ndarray, r: np.ndarray, header: np.ndarray, length: np.ndarray, extra: np.ndarray
    ) -> np.ndarray:
        """Whether each packet's CRC (after header and payload) is the X.25 of them and its crc_extra."""
        span = header - 1 + length  # from after the start byte to the payload's end
        ok = np.zeros(r.size, dtype=bool)
        for n in np.unique(span).tolist():
            sel = np.flatnonzero(span == n)
            first = r[sel] + _STAMP + 1
            rows = np.lib.stride_tricks.sliding_window_view(p, n + 2)[first]
            crc = np.full(sel.size, 0xFFFF, dtype=np.uint16)
            odd = n % 2
            if odd:
                crc = (crc >> 8) ^ _CRC_TABLE.take((crc ^ rows[:, 0]) & 0xFF)
            # A row per pair of byte positions (contiguous), each step one pass over the packets.
            words = rows[:, odd:n].copy().view("<u2").T.copy()
            for word in words:
                crc = _CRC_PAIRS.take(crc ^ word)
            crc = (crc >> 8) ^ _CRC_TABLE.take((crc ^ extra[sel].astype(np.uint16)) & 0xFF)
            sent = rows[:, n].astype(np.uint16) | (rows[:, n + 1].astype(np.uint16) << 8)
            ok[sel] = crc == sent
        return ok

    def _decode(
        self,
        p: np.ndarray,
        r: np.ndarray,
        v2: np.ndarray,
        header: np.ndarray,
        length: np.ndarray,
        msgid: np.ndarray,
    ) -> list[ImuRows]:
        """Count the records' messages; the blocks their IMU messages complete, in file order."""
        parts: list[tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]] = []
        for mid in np.unique(msgid).tolist():
            cls = mavlink2.mavlink_map[mid]
            sel = np.flatnonzero(msgid == mid)
            self.held[cls.msgname] = self.held.get(cls.msgname, 0) + sel.size
            kept = self.records.get(cls.msgname)
            kind = self._imu.get(cls.msgname)
            dtype = _dtype(cls) if kind is not None or kept is not None else None
            if dtype is None:
                continue
            size = cls.unpacker.size
            payload = r[sel] + _STAMP + header[sel]
            body = np.lib.stride_tricks.sliding_window_view(p, size)[payload].copy()
            # pymavlink pads a payload shorter than the message's (MAVLink 2 cuts trailing zeros).
            body[np.arange(size)[None, :] >= length[sel][:, None]] = 0
            rec = body.view(dtype)[:, 0]
            if kept is not None:
                kept.append(rec)
            if kind is None:
                continue
            a = np.column_stack([rec[f].astype(np.float64) for f in FIELD_NAMES[kind]])
            si = imu_fields_si(kind, a, self.raw_scale)
            if si.not_updated:
                reason = LinkRejection.FIELDS_NOT_UPDATED.value
                self.dropped[reason] = self.dropped.get(reason, 0) + si.not_updated
                sel = sel[si.kept]
            base = self.imu_index.get(kind)
            if base is None:
                continue
            imu = base + (si.ids if si.ids is not None else np.zeros(sel.size, dtype=np.int64))
            values = np.column_stack([si.accel_mps2, si.gyro_rps, si.temp_c])
            code = [m.value for m in ImuMessage].index(kind.value)
            parts.append((sel, imu, code, si.t_s, values, si.has_temp))
        if not parts:
            return []
        seq = np.concatenate([x[0] for x in parts])
        order = np.argsort(seq, kind="stable")
        blocks = self._blocker.add(
            seq[order],
            np.concatenate([x[1] for x in parts])[order],
            (
                np.concatenate([np.full(x[0].size, x[2]) for x in parts])[order],
                np.concatenate([x[3] for x in parts])[order],
                np.concatenate([x[4] for x in parts])[order],
                np.concatenate([x[5] for x in parts])[order],
            ),
            np.zeros(0, dtype=np.int64),
        )
        return [b for _, b in blocks]
