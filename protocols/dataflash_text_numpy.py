"""Text DataFlash IMU lines parsed with numpy, for :class:`protocols.logs.LogReader`.

:class:`protocols.logs.DataFlashStream` splits every line of a text ``.log`` in Python and reads
each IMU line as a pymavlink ``DFMessage``, one attribute at a time (``_imu_sample``): 61 k
samples/s, slower than pymavlink's own ``DFReader_text``. This reads the same lines with the same
rules (the stream's docstring) and pymavlink's formats (``DFFormat`` of every ``FMT`` line), a
block of bytes at a time:

* the lines of a block are found at its line breaks, and each one's message type by its first
  eight bytes: the name and the delimiter, against the formats defined so far;
* the fields ``_imu_sample`` reads of an ``IMU``/``IMU2``/``IMU3`` line (time, instance, the
  triads, temperature) are parsed in bulk, to the values Python's ``int`` and ``float`` give
  (:func:`parse_numbers`);
* every other line, and an IMU line that grammar does not cover (``nan``, a space or ``+`` in a
  field, a byte that is not ASCII, fields missing, whitespace at its end), goes through the
  stream's own code in its place (``_text_line``, then ``_imu_sample`` for an IMU message);
* the samples are cut into the blocks ``_rows_from_samples`` makes of the stream's per-message
  samples (:class:`protocols.dataflash_numpy.Blocker`).

An ``FMT`` line ends a block (the formats after it are new). The reader's memory is a block's,
whatever the log's length. The stream stays the oracle (tests/test_dataflash_text_numpy.py: the
same batches and counts on every log, damaged ones too).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from protocols.dataflash_numpy import Blocker
from protocols.logs import (
    _MAX_TEXT_LINE,
    DATAFLASH_IMU_NAMES,
    FIELD_ERRORS,
    DataFlashStream,
    _bounded_lines,
    _imu_sample,
    _Sample,
)

MIN_BLOCK = 1 << 16
"""Bytes of the first block and of the one after an ``FMT`` line: a whole line of the longest the
stream reads (:data:`protocols.logs._MAX_TEXT_LINE`) fits in it."""
MAX_BLOCK = 1 << 18
"""Bytes of a block once no ``FMT`` line came for a while (each block without one doubles the next):
no faster above (the 5-minute benchmark log reads in 0.6 s at 256 KB and 0.8 s at 1 MB), and the
arrays of a block's fields peak at a few MB (the read's RSS 56 MB at 256 KB, 66 MB at 1 MB)."""

_PAD = 32
"""Bytes before and after a block's data: the digits of a field are read eight at a time, as the
word that ends at the field's last digit, up to three words back."""
_WHITESPACE = np.zeros(256, dtype=bool)
_WHITESPACE[[9, 10, 11, 12, 13, 32]] = True
"""What ``bytes.rstrip`` strips."""
_INT_CODES = frozenset("bBhHiIqQM")
"""Format characters whose text value the stream reads with ``int`` (``M`` stays text in a text
log: ``int`` of it for the instance, ``float`` of it for a value)."""
_FLOAT_CODES = frozenset("fdgcCeEL")
"""Format characters whose text value the stream reads with ``float`` (no multiplier in text)."""

_U64 = np.uint64
_ASCII_ZERO = _U64(0x3030303030303030)
_DIGIT_CARRY = _U64(0x7676767676767676)
_HIGH_BITS = _U64(0x8080808080808080)
_KEEP = np.array([0] + [(1 << 64) - (1 << (8 * (8 - k))) for k in range(1, 9)], dtype=_U64)
"""The high ``k`` bytes of a word: the last ``k`` characters before where the word ends."""
_POW10 = np.array([10.0**k for k in range(23)])
"""Powers of ten that float64 holds exactly."""
_EXACT_MANTISSA = 1 << 53
_LONG_EXACT = 27
"""10**27 is the largest power of ten an x87 long double (64-bit mantissa) holds exactly."""
_LONG_OK = np.finfo(np.longdouble).nmant >= 63
"""Whether long double has the 64-bit mantissa the rounding argument of :func:`parse_numbers` needs
(x86 Linux; elsewhere those fields are left to Python)."""
_POW10_LONG = np.cumprod(np.r_[1, np.full(_LONG_EXACT, 10)].astype(np.longdouble))
"""10**k in long double, each product exact (a Python int would pass through float64)."""


def _words(buf: np.ndarray) -> np.ndarray:
    """The eight bytes from every position of ``buf`` as a little-endian uint64 (an unaligned view)."""
    words: np.ndarray = np.ndarray(shape=(buf.size - 7,), dtype="<u8", buffer=buf, strides=(1,))
    return words


@dataclass
class _Block:
    """A block of a text log as numpy arrays: its bytes (padded by :data:`_PAD`), their words, and
    where its exponent letters are (found once, for every float field)."""

    buf: np.ndarray
    words: np.ndarray
    _exponents: np.ndarray | None = None

    @classmethod
    def of(cls, data: bytes) -> _Block:
        pad = bytes(_PAD)
        buf = np.frombuffer(pad + data + pad, dtype=np.uint8)
        return cls(buf, _words(buf))

    def exponents(self) -> np.ndarray:
        """Where the block's ``e`` and ``E`` are."""
        if self._exponents is None:
            self._exponents = np.flatnonzero((self.buf | 0x20) == ord("e"))
        return self._exponents


def _swar(x: np.ndarray) -> np.ndarray:
    """The number of a word of digit values (0…9, the first digit in the lowest byte), summed
    pairwise in place: 2, then 4, then 8 digits (the usual SIMD-within-a-register parse)."""
    x = (x * _U64(10) + (x >> _U64(8))) & _U64(0x00FF00FF00FF00FF)
    x = (x * _U64(100) + (x >> _U64(16))) & _U64(0x0000FFFF0000FFFF)
    return (x * _U64(10000) + (x >> _U64(32))) & _U64(0xFFFFFFFF)


def _digits(words: np.ndarray, end: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The value (uint64) of the ``n`` characters before ``end`` as decimal digits, and whether they
    are: at most 24 of them (leading zeros included), the value below 10**19.

    Eight at a time: the word that ends where they do, masked to them (the bytes before them become
    leading zeros); a byte that is no digit sets its high bit in ``x | (x + 0x76…)``."""
    k = np.minimum(np.maximum(n, 0), 24)
    x = (words[end - 8] ^ _ASCII_ZERO) & _KEEP[np.minimum(k, 8)]
    bad = (x + _DIGIT_CARRY) | x
    value = _swar(x)
    ok = (n >= 0) & (n <= 24)
    if (k > 8).any():
        x = (words[end - 16] ^ _ASCII_ZERO) & _KEEP[np.minimum(np.maximum(k - 8, 0), 8)]
        bad |= (x + _DIGIT_CARRY) | x
        value += _swar(x) * _U64(10**8)
        if (k > 16).any():
            x = (words[end - 24] ^ _ASCII_ZERO) & _KEEP[np.maximum(k - 16, 0)]
            bad |= (x + _DIGIT_CARRY) | x
            top = _swar(x)
            ok &= top < 1000
            value += top * _U64(10**16)
    return value, ok & ((bad & _HIGH_BITS) == 0)


_DOTS = _U64(0x2E2E2E2E2E2E2E2E)
_ONES = _U64(0x0101010101010101)


def _dot(block: _Block, first: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Where the first ``.`` in each ``[first, end)`` is (``end`` where none): in the word at
    ``first`` (its lowest zero byte after XOR with dots, found by the usual zero-byte test and the
    exponent of its bit), else searched for."""
    x = block.words[first] ^ _DOTS
    zero = (x - _ONES) & ~x & _HIGH_BITS
    lowest = zero & (~zero + _U64(1))
    at = first + np.where(lowest != 0, np.frexp(lowest.astype(np.float64))[1] // 8 - 1, 8)
    far = np.flatnonzero((lowest == 0) & (end - first > 8))
    if far.size:
        at[far], _ = _first_after(np.flatnonzero(block.buf == ord(".")), first[far], end[far])
    dot: np.ndarray = np.minimum(at, end)
    return dot


def _first_after(
    marks: np.ndarray, start: np.ndarray, end: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The first of ``marks`` (sorted positions) in each ``[start, end)`` (``end`` where none), and how many there are."""
    k = np.searchsorted(marks, start)
    n = np.searchsorted(marks, end) - k
    at = np.append(marks, 0)[np.minimum(k, marks.size)]
    return np.where(n > 0, at, end), n


def _exponents(
    marks: np.ndarray, start: np.ndarray, first: np.ndarray, end: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where the first exponent letter (of ``marks``) in each field ``[first, end)`` is (``end``
    where none), and how many there are. The fields are in file order (``start`` increasing), and
    few of them have one: each letter is given its field, not each field searched."""
    at, n = end.copy(), np.zeros(end.size, dtype=np.int64)
    if marks.size:
        owner = np.searchsorted(start, marks, side="right") - 1
        mine = owner >= 0
        mine[mine] = (marks[mine] >= first[owner[mine]]) & (marks[mine] < end[owner[mine]])
        owner, marks = owner[mine], marks[mine]
        n += np.bincount(owner, minlength=end.size)
        fields, firsts = np.unique(owner, return_index=True)
        at[fields] = marks[firsts]
    return at, n


_POW10_U64 = np.array([10**k for k in range(20)], dtype=_U64)


def parse_numbers(
    block: _Block, start: np.ndarray, end: np.ndarray, integer: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The fields ``[start, end)`` of ``block`` (in file order: disjoint, ``start`` increasing) as ``float(int(text))`` (``integer``) or ``float(text)``
    would give them, and whether they are in the grammar read here (the rest are left to Python).

    Grammar: ``-?\\d+`` (``integer``), else ``-?(\\d+\\.?\\d*|\\.\\d+)([eE][+-]?\\d{1,3})?``, with at
    most 19 significant digits. The mantissa M (an integer) and the power of ten p are exact; M·10^p
    is rounded once: in float64 where M < 2**53 and |p| ≤ 22 (both exact there, one correctly rounded
    operation: Clinger's fast path), else in long double (M and 10^|p| ≤ 10^27 exact, the product or
    quotient rounded once to 64 bits), whose rounding to float64 is that of the exact value unless it
    landed exactly halfway between two doubles (a halfway point has 54 significant bits, so rounding
    to 64 cannot cross one): those few are left to Python.
    """
    buf, words = block.buf, block.words
    neg = buf[start] == ord("-")
    first = start + neg
    if integer:
        mantissa, ok = _digits(words, end, end - first)
        ok &= end > first
        value = mantissa.astype(np.float64)  # correctly rounded, as float(int) is
        return np.where(neg, 0.0 - value, value), ok  # float(int("-0")) is 0.0, not -0.0
    exp_at, n_exp = _exponents(block.exponents(), start, first, end)
    dot_at = _dot(block, first, exp_at)
    whole_n = dot_at - first
    frac_n = np.maximum(exp_at - dot_at - 1, 0)
    whole, ok = _digits(words, dot_at, whole_n)
    frac, ok_frac = _digits(words, exp_at, frac_n)
    ok &= ok_frac & (whole_n + frac_n > 0) & ((whole == 0) | (whole_n + frac_n <= 19))
    power = -frac_n
    if n_exp.any():
        after = np.minimum(exp_at + 1, end)
        exp_neg = (n_exp > 0) & (buf[after] == ord("-"))
        signed = (n_exp > 0) & (exp_neg | (buf[after] == ord("+")))
        exp_n = np.where(n_exp > 0, end - after - signed, 0)
        ok &= (n_exp == 0) | ((exp_n >= 1) & (exp_n <= 3))
        exp, ok_exp = _digits(words, end, np.minimum(exp_n, 3))
        ok &= ok_exp
        power = power + np.where(exp_neg, -exp.astype(np.int64), exp.astype(np.int64))
    mantissa = whole * _POW10_U64[np.minimum(frac_n, 19)] + frac
    exact = (mantissa < _EXACT_MANTISSA) & (np.abs(power) <= 22)
    m = mantissa.astype(np.float64)
    scale = _POW10[np.minimum(np.abs(power), 22)]
    value = np.where(power >= 0, m * scale, m / scale)
    rest = np.flatnonzero(ok & ~exact)
    if rest.size:
        value[rest], ok[rest] = _rounded_long(mantissa[rest], power[rest])
    return np.where(neg, -value, value), ok


def _rounded_long(mantissa: np.ndarray, power: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """M·10^p rounded to float64 through long double (:func:`parse_numbers`), and where that is sure."""
    if not _LONG_OK:
        return np.zeros(power.size), np.zeros(power.size, dtype=bool)
    m = mantissa.astype(np.longdouble)
    scale = _POW10_LONG[np.minimum(np.abs(power), _LONG_EXACT)]
    below = power < 0
    rounded = np.empty_like(m)
    np.divide(m, scale, out=rounded, where=below)
    np.multiply(m, scale, out=rounded, where=~below)
    value = rounded.astype(np.float64)
    # Halfway to the next double toward ``rounded``: half the spacing above ``value``; below a power
    # of two (``value`` >= 0 here), where the spacing halves, a quarter.
    off = (rounded - value).astype(np.float64)
    half = np.spacing(value) / 2
    half = np.where((off < 0) & (np.frexp(value)[0] == 0.5), half / 2, half)
    sure = (np.abs(power) <= _LONG_EXACT) & (np.abs(off) != half)
    return value, sure


@dataclass(frozen=True)
class _TextLayout:
    """Where the fields ``_imu_sample`` reads are in the values of a text IMU line, and how each is
    read (``int`` or ``float``); from the type's pymavlink ``DFFormat``."""

    fields: tuple[int, ...]
    """Value index of the time, the instance (-1: none), AccX…Z, GyrX…Z and T (-1: none)."""
    integer: tuple[bool, ...]
    time_scale: float
    imu: int
    """The IMU of a type without instance field (its name's place in ``DATAFLASH_IMU_NAMES``)."""

    @classmethod
    def of(cls, fmt: Any) -> _TextLayout | None:
        """The layout, or None where a field the sample needs is missing or not a number (the
        stream reads those lines: corrupt, or converted from text as pymavlink's types say)."""
        cols: dict[str, int] = fmt.colhash
        codes = fmt.msg_fmts
        time_col = "TimeUS" if "TimeUS" in cols else "TimeMS"
        names = [time_col, "I", *(f"{p}{a}" for p in ("Acc", "Gyr") for a in "XYZ"), "T"]
        fields, integer = [], []
        for name in names:
            if name not in cols:
                if name in ("I", "T"):
                    fields.append(-1)
                    integer.append(True)
                    continue
                return None
            code = codes[cols[name]]
            if code not in _INT_CODES | _FLOAT_CODES or (name == "I" and code not in _INT_CODES):
                return None
            fields.append(cols[name])
            integer.append(code in _INT_CODES and (name == "I" or code != "M"))
        imu = DATAFLASH_IMU_NAMES.index(fmt.name)
        return cls(tuple(fields), tuple(integer), 1e-6 if time_col == "TimeUS" else 1e-3, imu)


_Samples = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""Samples in file order: line index in the block, IMU, type code, t_s, values (accel, gyro,
temperature or NaN), whether the type has a temperature."""


class DataFlashTextScan(DataFlashStream):
    """The wanted messages of a text DataFlash log in file order (module docstring).

    Yields pymavlink ``DFMessage`` values, as :class:`protocols.logs.DataFlashStream` does, except
    for the IMU messages: those come as :class:`~protocols.ulog.ImuRows` blocks of ``flush``
    samples of an IMU where the last sample of the block was; :meth:`pending_samples` gives the
    rest after the iteration. Counts as the stream's (``held``, :attr:`corrupt`,
    :attr:`cut_at_byte`); :attr:`offset` the bytes read so far.
    """

    def __init__(
        self, path: Path, *, wanted: frozenset[str], held: dict[str, int], flush: int
    ) -> None:
        super().__init__(path, binary=False, wanted=wanted, held=held)
        self._names: list[str] = []
        self._blocker = Blocker(flush, self._names)
        self._layouts: dict[Any, _TextLayout | None] = {}

    def pending_samples(self) -> Iterator[_Sample]:
        return self._blocker.pending_samples()

    def __iter__(self) -> Iterator[Any]:
        size = os.path.getsize(self.path)
        with open(self.path, "rb") as fh:
            at: int | None = 0
            while at is not None and not self.delimiter:  # header lines, to the first FMT line
                items, at = self._one_line(fh, at)
                yield from items
            block = MIN_BLOCK
            while at is not None:
                fh.seek(at)
                data = fh.read(block)
                self.offset = at + len(data)
                items, at, new_format = self._block(fh, data, at, self.offset >= size)
                yield from items
                block = MIN_BLOCK if new_format else min(2 * block, MAX_BLOCK)

    def _one_line(self, fh: Any, start: int) -> tuple[list[Any], int | None]:
        """The stream's reading of the line at ``start``; where the next one starts."""
        fh.seek(start)
        line = next(_bounded_lines(fh, _MAX_TEXT_LINE), b"")
        self.offset = fh.tell()
        if line is None:
            self.corrupt += 1
            return [], self.offset
        if not line:
            return [], None
        if not line.endswith(b"\n"):
            self.cut_at_byte = start
            return [], None
        return self._emit(*self._read_slow([line], np.zeros(1, dtype=np.int64))), self.offset

    def _block(
        self, fh: Any, data: bytes, start: int, eof: bool
    ) -> tuple[list[Any], int | None, bool]:
        """The items of the whole lines of ``data`` up to the first ``FMT`` line (that one read
        too), where reading goes on (None: the log ended) and whether an ``FMT`` line ended it."""
        raw = np.frombuffer(data, dtype=np.uint8)
        breaks = np.flatnonzero(raw == ord("\n"))
        if not breaks.size:
            if not eof:  # a line longer than the block: read past as the stream does
                items, at = self._one_line(fh, start)
                return items, at, False
            if data:
                if len(data) < _MAX_TEXT_LINE:
                    self.cut_at_byte = start
                else:
                    self.corrupt += 1
            return [], None, False
        block = _Block.of(data)
        ends = breaks + 1 + _PAD
        starts = np.concatenate([[_PAD], ends[:-1]])
        kind = self._kinds(block, starts)
        fmt_code = len(self._key_names) - 1  # the FMT format's code (_kinds puts it last)
        at_fmt = np.flatnonzero(kind == fmt_code)
        stop = int(at_fmt[0]) if at_fmt.size else starts.size
        starts, ends, kind = starts[:stop], ends[:stop], kind[:stop]
        content_end = ends - 1 - (block.buf[ends - 2] == ord("\r"))
        simple = (~_WHITESPACE[block.buf[content_end - 1]]) & (ends - starts <= _MAX_TEXT_LINE)
        fast = simple & (kind >= 0)
        fast_samples: list[_Samples] = []
        for code, name in enumerate(self._key_names[:-1]):
            if name not in self.wanted:
                continue
            mine = fast & (kind == code)
            layout = self._layout(name) if name in DATAFLASH_IMU_NAMES else None
            if layout is None:
                fast &= ~mine
                continue
            lines = np.flatnonzero(mine)
            if lines.size:
                samples, left = self._parse(block, layout, name, lines, starts, content_end)
                fast[left] = False
                fast_samples.append(samples)
        counts = np.bincount(kind[fast], minlength=len(self._key_names))
        for code in np.flatnonzero(counts).tolist():
            name = self._key_names[code]
            self.held[name] = self.held.get(name, 0) + int(counts[code])
        slow = np.flatnonzero(~fast)
        slow_lines: list[bytes | None] = [
            data[s - _PAD : e - _PAD]
            for s, e in zip(starts[slow].tolist(), ends[slow].tolist(), strict=True)
        ]
        others, slow_samples = self._read_slow(slow_lines, slow)
        items = self._emit(others, slow_samples, _concat_samples(fast_samples))
        if at_fmt.size:  # the FMT line: new formats from here on
            line = data[int(ends[-1] if stop else _PAD) - _PAD :]
            fmt_line = line[: line.index(b"\n") + 1]
            self._read_slow([fmt_line], np.zeros(1, dtype=np.int64))
            return items, start + len(data) - len(line) + len(fmt_line), True
        done = int(ends[-1]) - _PAD
        if eof and done < len(data):
            tail = len(data) - done
            if tail < _MAX_TEXT_LINE:
                self.cut_at_byte = start + done
            else:
                self.corrupt += 1
            return items, None, False
        if eof:
            return items, None, False
        return items, start + done, False

    @property
    def _key_names(self) -> list[str]:
        return self._keys[1]

    def _kinds(self, block: _Block, starts: np.ndarray) -> np.ndarray:
        """Per line, the code of its message type (an index of :attr:`_key_names`), -1 where its
        first bytes are no defined name and the delimiter (or the name is too long for a word)."""
        self._keys = self._build_keys()
        first = block.words[starts]
        kind = np.full(starts.size, -1, dtype=np.int64)
        for length, (keys, codes) in self._keys[0].items():
            masked = first & _U64((1 << (8 * length)) - 1)
            j = np.minimum(np.searchsorted(keys, masked), keys.size - 1)
            hit = keys[j] == masked
            kind[hit] = codes[j[hit]]
        return kind

    def _build_keys(self) -> tuple[dict[int, tuple[np.ndarray, np.ndarray]], list[str]]:
        """Per key length, the sorted keys (name and delimiter as little-endian words) and their
        codes; and the names by code, ``FMT`` last."""
        names = [n for n in self.formats if n != "FMT"] + ["FMT"]
        by_length: dict[int, list[tuple[int, int]]] = {}
        for code, name in enumerate(names):
            try:
                key = (name + self.delimiter).encode("ascii")
            except UnicodeEncodeError:
                continue
            if len(key) <= 8 and b"\n" not in key:
                by_length.setdefault(len(key), []).append((int.from_bytes(key, "little"), code))
        table = {}
        for length, pairs in by_length.items():
            pairs.sort()
            table[length] = (
                np.array([k for k, _ in pairs], dtype=_U64),
                np.array([c for _, c in pairs], dtype=np.int64),
            )
        return table, names

    def _layout(self, name: str) -> _TextLayout | None:
        fmt = self.formats[name]
        if fmt not in self._layouts:
            self._layouts[fmt] = _TextLayout.of(fmt)
        return self._layouts[fmt]

    def _code(self, name: str) -> int:
        if name not in self._names:
            self._names.append(name)
        return self._names.index(name)

    def _parse(
        self,
        block: _Block,
        layout: _TextLayout,
        name: str,
        lines: np.ndarray,
        starts: np.ndarray,
        content_end: np.ndarray,
    ) -> tuple[_Samples, np.ndarray]:
        """The samples of the IMU lines ``lines`` of type ``name`` the grammar reads, and the lines
        it does not (too few fields, or one outside it)."""
        fmt = self.formats[name]
        bounds = self._bounds(block)
        first = np.searchsorted(bounds, starts[lines])
        n_bounds = np.searchsorted(bounds, content_end[lines]) - first
        few = n_bounds < len(fmt.format)
        left = lines[few]
        if left.size:
            lines, first, n_bounds = lines[~few], first[~few], n_bounds[~few]
        after = np.append(bounds, 0)  # the field after the last delimiter ends at the line's end
        ok = np.ones(lines.size, dtype=bool)
        # A field the format lacks (instance, temperature) stays NaN.
        values = [np.full(lines.size, np.nan)] * len(layout.fields)
        for integer in (True, False):
            # The fields read alike, in file order (parse_numbers wants them so), parsed at once.
            which = [
                k
                for k in np.argsort(layout.fields).tolist()
                if layout.fields[k] >= 0 and layout.integer[k] == integer
            ]
            if not which:
                continue
            field = first[:, None] + np.array([layout.fields[k] for k in which])
            begin = bounds[field] + len(self.delimiter)
            end = np.where(
                field + 1 < (first + n_bounds)[:, None],
                after[field + 1],
                content_end[lines][:, None],
            )
            value, good = parse_numbers(block, begin.ravel(), end.ravel(), integer)
            ok &= good.reshape(begin.shape).all(axis=1)
            for j, k in enumerate(which):
                values[k] = value[j :: len(which)]
        t_s = values[0] * layout.time_scale
        if layout.fields[1] < 0:
            imu = np.full(lines.size, layout.imu, dtype=np.int64)
        else:
            ok &= (values[1] >= 0) & (values[1] < 256)
            imu = np.where(ok, values[1], 0).astype(np.int64)
        samples: _Samples = (
            lines,
            imu,
            np.full(lines.size, self._code(name), dtype=np.int64),
            t_s,
            np.column_stack(values[2:]),
            np.full(lines.size, layout.fields[8] >= 0),
        )
        if ok.all():
            return samples, left
        seq, imu, code, t_s, data, with_temp = (a[ok] for a in samples)
        return (seq, imu, code, t_s, data, with_temp), np.concatenate([left, lines[~ok]])

    def _bounds(self, block: _Block) -> np.ndarray:
        """Where the delimiters of the block are (``", "`` never overlaps itself: ``split`` finds them all)."""
        buf = block.buf
        if self.delimiter == ",":
            return np.flatnonzero(buf == ord(","))
        return np.flatnonzero((buf[:-1] == ord(",")) & (buf[1:] == ord(" ")))

    def _read_slow(
        self, lines: list[bytes | None], index: np.ndarray
    ) -> tuple[list[tuple[int, Any]], _Samples]:
        """The stream's reading of ``lines`` (a line over :data:`_MAX_TEXT_LINE` bytes is corrupt):
        the wanted messages other than IMU ones with their ``index``, and the IMU samples."""
        others: list[tuple[int, Any]] = []
        samples: list[tuple[int, _Sample]] = []
        for k, line in zip(index.tolist(), lines, strict=True):
            if line is None or len(line) > _MAX_TEXT_LINE:
                self.corrupt += 1
                continue
            msg = self._text_line(line)
            if msg is None:
                continue
            if msg.get_type() not in DATAFLASH_IMU_NAMES:
                others.append((k, msg))
                continue
            try:
                samples.append((k, _imu_sample(msg, msg.get_fieldnames())))
            except FIELD_ERRORS:
                self.corrupt += 1
        if not samples:
            return others, _no_samples()
        return others, (
            np.array([k for k, _ in samples], dtype=np.int64),
            np.array([s[1] for _, s in samples], dtype=np.int64),
            np.array([self._code(s[0]) for _, s in samples], dtype=np.int64),
            np.array([s[2] for _, s in samples], dtype=float),
            np.array(
                [[*s[3], *s[4], np.nan if s[5] is None else s[5]] for _, s in samples], dtype=float
            ),
            np.array([s[5] is not None for _, s in samples], dtype=bool),
        )

    def _emit(self, others: list[tuple[int, Any]], *parts: _Samples) -> list[Any]:
        """The items in file order: the other messages, and the IMU blocks the samples complete."""
        samples = _concat_samples([p for p in parts if p[0].size])
        items: list[tuple[int, Any]] = list(others)
        if samples[0].size:
            order = np.argsort(samples[0], kind="stable")
            seq, imu, code, t_s, values, with_temp = (a[order] for a in samples)
            barriers = np.array([k for k, _ in others], dtype=np.int64)
            items += self._blocker.add(seq, imu, (code, t_s, values, with_temp), barriers)
        items.sort(key=lambda item: item[0])
        return [item for _, item in items]


def _no_samples() -> _Samples:
    return (
        np.zeros(0, dtype=np.int64),
        np.zeros(0, dtype=np.int64),
        np.zeros(0, dtype=np.int64),
        np.zeros(0),
        np.zeros((0, 7)),
        np.zeros(0, dtype=bool),
    )


def _concat_samples(parts: list[_Samples]) -> _Samples:
    if not parts:
        return _no_samples()
    if len(parts) == 1:
        return parts[0]
    seq, imu, code, t_s, values, with_temp = (
        np.concatenate([p[k] for p in parts]) for k in range(6)
    )
    return seq, imu, code, t_s, values, with_temp
