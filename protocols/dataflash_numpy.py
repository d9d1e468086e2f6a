"""Binary DataFlash IMU messages decoded with numpy, for :class:`protocols.logs.LogReader`.

:class:`protocols.logs.DataFlashStream` builds a pymavlink ``DFMessage`` per message and reads its
fields one attribute at a time: 84 k samples/s, the bound of replaying a ``.bin``. This reads the
same bytes with the same rules (the stream's docstring: a message is ``A3 95 <type>`` and the
body its ``FMT`` defines; bytes that start no message of a known type are skipped to the next
``A3 95``; a wanted body of the wrong size is corrupt and reading resumes after its header; a
message cut by the end of the file ends the log) and pymavlink's definitions (``DFFormat`` of
every ``FMT``: struct codes, columns, multipliers, value types), a block of bytes at a time:

* the headers are found by one vectorized scan, each one's message length from its type's format,
  and the chain of real messages among them by :func:`protocols.byte_chain.chain`;
* the ``IMU``/``IMU2``/``IMU3`` messages of a type are decoded at once with one structured dtype
  built from their ``FMT`` (the fields as ``DFMessage`` gives them: pymavlink's value type, then
  its multiplier), and cut into the blocks of rows :func:`protocols.logs._rows_from_samples`
  makes of the per-message samples, in the same order;
* every other wanted message (``VIBE``, ``DSF``, ``ACC``/``GYR``; an IMU format whose instance or
  data fields are not plain numbers) is still a pymavlink ``DFMessage``, decoded as the stream does.

An ``FMT`` ends a block (the formats after it are new). The reader's memory is a block's, whatever
the log's length. The stream stays the oracle (tests/test_dataflash_numpy.py: the same batches and
counts on every log).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import DFReader

from protocols.byte_chain import STRUCT_TO_NUMPY, chain
from protocols.logs import (
    _DF_FMT_ID,
    _DF_MAX_INSTANCE,
    _DF_MAX_MESSAGE,
    DATAFLASH_IMU_NAMES,
    _df_format,
    _fmt_of_fmt,
    _Sample,
    _StreamCounts,
)
from protocols.ulog import ImuRows

MIN_BLOCK = 1 << 12
"""Bytes of the first block and of the one after an ``FMT`` (formats come in bursts early in a log)."""
MAX_BLOCK = 1 << 16
"""Bytes of a block once no ``FMT`` came for a while (each block without one doubles the next): no
faster above (the 5-minute benchmark log reads in 0.16 s at 64 KB, 0.30 s at 4 MB), and the
reader's memory stays that of a block."""

# What reading does at a header: the type is undefined (skip), the message is read (MSG), its
# body does not unpack (BAD: corrupt, resume after the header), an FMT, or the file ends in it.
_SKIP, _MSG, _BAD, _FMT, _CUT = range(5)

_INTEGER_CODES = frozenset("bBhHiIqQM")
"""Format characters whose ``DFMessage`` value is an int (the instance field must be one)."""
_NUMERIC_CODES = _INTEGER_CODES | frozenset("fdgcCeEL")


@dataclass(frozen=True)
class _ImuLayout:
    """How the numpy path decodes one IMU message type, from its pymavlink ``DFFormat``."""

    fmt: Any
    dtype: np.dtype
    time_field: str
    time_scale: float
    has_instance: bool
    has_temp: bool

    @classmethod
    def of(cls, fmt: Any) -> _ImuLayout | None:
        """The layout, or None where the numpy path does not apply (the stream decodes those):
        a needed field missing (every message corrupt) or not a plain number (``_imu_sample``'s
        conversions of text or arrays). (A type whose body size the struct does not have has
        only corrupt messages, :meth:`DataFlashScan._tables`: none to decode.)"""
        cols: dict[str, int] = fmt.colhash
        time_field = "TimeUS" if "TimeUS" in cols else "TimeMS"
        needed = [time_field] + [f"{p}{a}" for p in ("Acc", "Gyr") for a in "XYZ"]
        needed += [c for c in ("I", "T") if c in cols]
        if any(c not in cols or fmt.msg_fmts[cols[c]] not in _NUMERIC_CODES for c in needed):
            return None
        if "I" in cols and fmt.msg_fmts[cols["I"]] not in _INTEGER_CODES:
            return None
        names, formats, offsets, at = [], [], [], 0
        for i, code in enumerate(fmt.msg_fmts):
            s = DFReader.FORMAT_TO_STRUCT[code][0]
            col = [c for c, k in cols.items() if k == i]
            if col:
                names.append(col[0])
                formats.append(STRUCT_TO_NUMPY.get(s, f"S{struct.calcsize(s)}"))
                offsets.append(at)
            at += struct.calcsize(s)
        dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": at})
        scale = 1e-6 if time_field == "TimeUS" else 1e-3
        return cls(fmt, dtype, time_field, scale, "I" in cols, "T" in cols)

    def value(self, rec: np.ndarray, column: str) -> np.ndarray:
        """A column as ``float(DFMessage.<column>)``: pymavlink's value type, its multiplier, float."""
        i = self.fmt.colhash[column]
        # float(int) and float(float) alike: exact, or rounded once to nearest
        v = rec[column].astype(np.float64)
        mult = self.fmt.msg_mults[i]
        if mult is not None:
            # pymavlink divides by 1/mult below 1 (a more accurate result than multiplying)
            v = v / (1 / mult) if 0.0 < mult < 1.0 else v * mult
        return v

    def decode(self, body: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(valid, imu, t_s, accel and gyro as an (n, 6) array, then temperature) of the bodies
        (rows of bytes): ``protocols.logs._imu_sample`` on every message; an instance outside
        ``0 .. 255`` is not valid (a corrupt message there)."""
        rec = body.view(self.dtype)[:, 0]
        n = rec.size
        if self.has_instance:
            inst = rec["I"]  # an integer format (of): its own values, compared without conversion
            valid = (inst >= 0) & (inst < _DF_MAX_INSTANCE)
            imu = np.where(valid, inst, 0).astype(np.int64)
        else:
            valid = np.ones(n, dtype=bool)
            imu = np.full(n, DATAFLASH_IMU_NAMES.index(self.fmt.name), dtype=np.int64)
        t_s = self.value(rec, self.time_field) * self.time_scale
        cols = [f"{p}{a}" for p in ("Acc", "Gyr") for a in "XYZ"] + (["T"] if self.has_temp else [])
        values = np.column_stack([self.value(rec, c) for c in cols])
        return valid, imu, t_s, values


_Part = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""Consecutive samples of one IMU: message type codes, t_s, values (accel, gyro, temperature), and
whether their type has a temperature."""


def _take(part: _Part, index: np.ndarray | slice) -> _Part:
    kind, t_s, values, with_temp = part
    return kind[index], t_s[index], values[index], with_temp[index]


class Blocker:
    """Cuts each IMU's samples into blocks of ``flush`` as ``_rows_from_samples`` does with the
    stream's per-message samples: a block when an IMU's ``flush``-th sample comes, named after the
    message types in it, its temperature only when every message of it has one."""

    def __init__(self, flush: int, names: list[str]) -> None:
        self.flush = flush
        self.names = names
        self.pending: dict[int, list[_Part]] = {}

    def add(
        self, seq: np.ndarray, imu: np.ndarray, part: _Part, barriers: np.ndarray
    ) -> list[tuple[int, ImuRows]]:
        """Samples in file order (``seq`` their place among the block's messages); the blocks they
        complete, each with the ``seq`` of the sample that completed it. Blocks of an IMU that
        follow each other with no other block, nor a message at ``barriers`` (seqs, sorted),
        between them come as one: the reader cuts the same batches from them in the same order (a
        batch is all or nothing in temperature, so only blocks alike in it and in name join)."""
        blocks: list[tuple[int, int, str, bool, list[_Part]]] = []
        for u in np.unique(imu).tolist():
            sel = np.flatnonzero(imu == u)
            mine = _take(part, sel)
            waiting = self.pending.setdefault(u, [])
            # One type, and temperature all or nothing, here (the usual case): every block of
            # these samples alone has the same name and temperature, found once.
            alike = mine[0].min() == mine[0].max() and mine[3].min() == mine[3].max()
            alike_name, alike_temp = self._name(mine[0][:1]), bool(mine[3][0])
            start = 0
            for end in range(
                self.flush - sum(w[1].size for w in waiting), sel.size + 1, self.flush
            ):
                parts = [*waiting, _take(mine, slice(start, end))]
                if alike and len(parts) == 1:
                    name, temp = alike_name, alike_temp
                else:
                    kind = np.concatenate([q[0] for q in parts])
                    name, temp = self._name(kind), all(bool(q[3].all()) for q in parts)
                blocks.append((int(seq[sel[end - 1]]), u, name, temp, parts))
                waiting.clear()
                start = end
            if start < sel.size:
                waiting.append(_take(mine, slice(start, None)))
        blocks.sort(key=lambda b: b[0])
        out: list[tuple[int, ImuRows]] = []
        run: list[_Part] = []
        for i, (end_seq, u, name, temp, parts) in enumerate(blocks):
            run += parts
            nxt = blocks[i + 1] if i + 1 < len(blocks) else None
            if (
                nxt is not None
                and nxt[1:4] == (u, name, temp)
                and (
                    not barriers.size
                    or np.searchsorted(barriers, end_seq) == np.searchsorted(barriers, nxt[0])
                )
            ):
                continue
            out.append((end_seq, self._rows(u, name, temp, run)))
            run = []
        return out

    def _name(self, kind: np.ndarray) -> str:
        """A block's name: its message type, or the types in it joined by ``/``."""
        codes = np.unique(kind).tolist() if kind.min() != kind.max() else [int(kind[0])]
        return "/".join(sorted(self.names[k] for k in codes))

    def pending_samples(self) -> Iterator[_Sample]:
        """The samples of blocks not complete, as the per-message samples of ``_rows_from_samples``
        (which then cuts them as it would have: at the end of the log, or where the per-message
        path takes over), and none left here."""
        for u in sorted(self.pending):
            for kind, t_s, values, with_temp in self.pending.pop(u):
                for k, t, v, w in zip(
                    kind.tolist(), t_s.tolist(), values.tolist(), with_temp.tolist(), strict=True
                ):
                    yield (
                        self.names[k],
                        u,
                        t,
                        (v[0], v[1], v[2]),
                        (v[3], v[4], v[5]),
                        v[6] if w else None,
                    )

    @staticmethod
    def _rows(imu: int, name: str, temp: bool, parts: list[_Part]) -> ImuRows:
        t_s = parts[0][1] if len(parts) == 1 else np.concatenate([q[1] for q in parts])
        values = parts[0][2] if len(parts) == 1 else np.concatenate([q[2] for q in parts])
        return ImuRows(
            name,
            imu,
            t_s,
            values[:, 0:3],
            values[:, 3:6],
            values[:, 6] if temp else None,
            np.zeros(t_s.size, dtype=bool),
        )


class DataFlashScan(_StreamCounts):
    """The wanted messages of a binary DataFlash log in file order (module docstring).

    Yields pymavlink ``DFMessage`` values, as :class:`protocols.logs.DataFlashStream` does, except
    for the IMU messages it decodes itself: those come as :class:`~protocols.ulog.ImuRows` blocks of
    ``flush`` samples of an IMU where the last sample of the block was; :meth:`pending_samples` gives
    the rest after the iteration. Counts as the stream's: ``held``, :attr:`corrupt`,
    :attr:`skipped_bytes`, :attr:`cut_at_byte`; :attr:`offset` the bytes read so far.
    """

    def __init__(
        self, path: Path, *, wanted: frozenset[str], held: dict[str, int], flush: int
    ) -> None:
        super().__init__(path, wanted, held)
        self._names: list[str] = []
        self._blocker = Blocker(flush, self._names)

    def pending_samples(self) -> Iterator[_Sample]:
        return self._blocker.pending_samples()

    def __iter__(self) -> Iterator[Any]:
        formats = {_DF_FMT_ID: _fmt_of_fmt()}
        size = os.path.getsize(self.path)
        start: int | None = 0
        block = MIN_BLOCK
        with open(self.path, "rb") as fh:
            while start is not None:
                fh.seek(start)
                data = fh.read(block + _DF_MAX_MESSAGE + 3)
                self.offset = start + len(data)
                eof = self.offset >= size
                items, start, new_format = self._block(data, start, eof, block, formats)
                yield from items
                block = MIN_BLOCK if new_format else min(2 * block, MAX_BLOCK)

    def _tables(self, formats: dict[int, Any]) -> tuple[np.ndarray, np.ndarray]:
        """Per type id: what reading does at its header and its message's length."""
        action = np.full(256, _SKIP, dtype=np.int8)
        length = np.zeros(256, dtype=np.int64)
        for type_id, fmt in formats.items():
            length[type_id] = fmt.len
            if type_id == _DF_FMT_ID:
                action[type_id] = _FMT
            elif fmt.name in self.wanted and struct.calcsize(fmt.msg_struct) != fmt.len - 3:
                action[type_id] = _BAD
            else:
                action[type_id] = _MSG
        return action, length

    def _block(
        self, data: bytes, start: int, eof: bool, block: int, formats: dict[int, Any]
    ) -> tuple[list[Any], int | None, bool]:
        """The items of the messages that start in ``data[:block]`` (all of it at the end of the
        file), where the next block starts (None: the log ended) and whether an ``FMT`` ended it."""
        d = np.frombuffer(data, dtype=np.uint8)
        end = d.size if eof else block
        heads = np.flatnonzero((d[:-1] == 0xA3) & (d[1:] == 0x95))
        heads = heads[heads < end]
        typed = heads + 2 < d.size
        type_id = np.zeros(heads.size, dtype=np.int64)
        type_id[typed] = d[heads[typed] + 2]
        action_of, length_of = self._tables(formats)
        action = np.where(typed, action_of[type_id], _CUT)
        nodes = action != _SKIP
        pos, action, type_id = heads[nodes], action[nodes], type_id[nodes]
        length = length_of[type_id]
        action[pos + length > d.size] = _CUT  # the file ends inside it (blocks are read with room)
        landing = pos + np.where(action == _BAD, 3, length)

        def resolve(at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """From where reading goes on: the next node and the bytes skipped to it (-1: none here)."""
            k = np.searchsorted(pos, at)
            found = (k < pos.size) & (at < end)
            if eof:
                found &= at < d.size - 2  # fewer than 3 bytes left: the log ends there
            return np.where(found, k, -1), np.where(found, np.append(pos, end)[k] - at, 0)

        first, skip0 = resolve(np.array([0]))
        succ, skip = resolve(landing)
        succ[(action != _MSG) & (action != _BAD)] = -1
        path = chain(int(first[0]), succ)
        self.skipped_bytes += int(skip0[0]) + int(skip[path[:-1]].sum())
        at = int(landing[path[-1]]) if path.size else 0
        last = int(action[path[-1]]) if path.size else _MSG
        if last == _FMT or last == _CUT:
            path, tail = path[:-1], int(pos[path[-1]])
        items = self._messages(data, pos[path], type_id[path], action[path], formats)
        new_format = False
        if last == _CUT:
            self.cut_at_byte = start + tail
            return items, None, False
        if last == _FMT:
            self.held["FMT"] = self.held.get("FMT", 0) + 1
            at, new_format = self._define(data, tail, formats), True
        elif eof:
            rest = d.size - at
            if 0 < rest < 3:
                self.cut_at_byte = start + at
            elif rest > 0:
                self.skipped_bytes += rest
            return items, None, False
        elif at < end:  # no message starts in the rest of the block: skipped to its end
            self.skipped_bytes += end - at
            at = end
        return items, start + at, new_format

    def _define(self, data: bytes, at: int, formats: dict[int, Any]) -> int:
        """Read the ``FMT`` at ``at`` as the stream does; where reading goes on."""
        f = formats[_DF_FMT_ID]
        try:
            e = struct.unpack(f.msg_struct, data[at + 3 : at + f.len])
            null_term = DFReader.null_term
            defined = _df_format(e[0], null_term(e[2]), e[1], null_term(e[3]), null_term(e[4]))
        except (struct.error, ValueError):
            self.corrupt += 1
            return at + 3
        formats[defined.type] = defined
        return at + int(f.len)

    def _messages(
        self,
        data: bytes,
        pos: np.ndarray,
        type_id: np.ndarray,
        action: np.ndarray,
        formats: dict[int, Any],
    ) -> list[Any]:
        """The items of the messages at ``pos`` (file order): IMU blocks the numpy way, the other
        wanted messages as ``DFMessage``; every message counted in ``held``."""
        counts = np.bincount(type_id, minlength=256)
        for t in np.flatnonzero(counts).tolist():
            name = formats[t].name
            self.held[name] = self.held.get(name, 0) + int(counts[t])
        self.corrupt += int((action == _BAD).sum())
        d = np.frombuffer(data, dtype=np.uint8)
        items: list[tuple[int, Any]] = []
        fast: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool, int]] = []
        for t in np.flatnonzero(counts).tolist():
            fmt = formats[t]
            if fmt.name not in self.wanted:
                continue
            seq = np.flatnonzero((type_id == t) & (action == _MSG))
            if not seq.size:  # all of them corrupt (a body size the format does not have)
                continue
            layout = _ImuLayout.of(fmt) if fmt.name in DATAFLASH_IMU_NAMES else None
            if layout is None:
                unpack = struct.Struct(fmt.msg_struct).unpack
                for k in seq.tolist():
                    p = int(pos[k])
                    elements = list(unpack(data[p + 3 : p + fmt.len]))
                    items.append((k, DFReader.DFMessage(fmt, elements, True, None)))
                continue
            body = np.lib.stride_tricks.sliding_window_view(d, fmt.len - 3)[pos[seq] + 3]
            valid, imu, t_s, values = layout.decode(body)
            self.corrupt += int((~valid).sum())
            if fmt.name not in self._names:
                self._names.append(fmt.name)
            if not layout.has_temp:
                values = np.column_stack([values, np.full(values.shape[0], np.nan)])
            code = self._names.index(fmt.name)
            fast.append((seq[valid], imu[valid], t_s[valid], values[valid], layout.has_temp, code))
        if fast:
            seq = np.concatenate([f[0] for f in fast])
            order = np.argsort(seq, kind="stable")
            kind = np.concatenate([np.full(f[0].size, f[5]) for f in fast])
            with_temp = np.concatenate([np.full(f[0].size, f[4]) for f in fast])
            barriers = np.array(sorted(k for k, _ in items), dtype=np.int64)
            blocks = self._blocker.add(
                seq[order],
                np.concatenate([f[1] for f in fast])[order],
                (
                    kind[order],
                    np.concatenate([f[2] for f in fast])[order],
                    np.concatenate([f[3] for f in fast])[order],
                    with_temp[order],
                ),
                barriers,
            )
            items.extend(blocks)
        items.sort(key=lambda item: item[0])
        return [item for _, item in items]
