"""Session files ⇄ :class:`estimators.session.ImuSession` (SI).

Two formats:

**CSV session file** (read and write). A header row names the columns, then one
sample a line::

    # comment lines start with '#'; '# key = value' lines are kept as metadata
    # gravity_mps2 = 9.80619
    t,ax,ay,az,gx,gy,gz,temp
    0.00,0.0012,-0.0031,9.8071,0.0001,-0.0002,0.0000,21.5

``t`` in s, ``ax ay az`` specific force in m/s², ``gx gy gz`` angular rate in
rad/s, ``temp`` in °C (optional), unless the file says otherwise with
``# accel_unit = g`` (``m/s2``, ``g``, ``mg``), ``# gyro_unit = deg/s``
(``rad/s``, ``deg/s``) or ``# time_unit = ms`` (``s``, ``ms``, ``us``, ``ns``) comment
lines, or the caller declares the units (:class:`SessionUnits`; a declaration
overrides the file's). Values are converted to SI here, once
(``g`` = 9.80665 m/s², the unit a data sheet means). Columns may come in any order; a file may
hold one triad only (all three of its columns). Blank lines are skipped.
``nan``/``inf`` values are passed through: :func:`estimators.session.validate_session`
counts and drops them. The only rows this reader drops are those with no number in any field
(a spreadsheet's empty ``,,,,,,`` rows, a label), wherever they are, counted in
``LoadedSession.notes``: they hold no sample. A row with some numbers and some text is a damaged
sample whose meaning is unknown (which column slipped?), refused naming its line and column.

**Other tools' IMU CSV files** (read, :data:`CSV_DIALECTS`): EuRoC/ASL
``imu0/data.csv`` (``#timestamp [ns],w_RS_S_x [rad s^-1],…,a_RS_S_z [m s^-2]``,
the layout Kalibr, OpenVINS and Basalt read), Kalibr's ``imu0.csv``
(``timestamp,omega_x,…,alpha_z``) and a ROS ``sensor_msgs/Imu`` topic written
by ``rostopic echo -p`` (``field.header.stamp`` and the angular velocity and
linear acceleration fields; its other columns are not read). Their units are the
format's (ns, rad/s, m/s²) unless declared otherwise; ``LoadedSession.metadata``
says the format (``format``) and the units, as a file's comments would.

**Xsens raw-count pair** (read). Two whitespace-separated text files on the same
time stamps, ``time_s x y z`` per line, accelerometer and gyro in raw 16-bit
counts (IMU-TK's test data, ``../shared/data/measured/xsens-multiposition``).
Counts become SI with a nominal offset and scale per axis from a TOML sidecar
(:class:`XsensNominal`); the packaged default ``sidecars/xsens_mti.toml``
documents where its numbers come from.

Every problem with a file is a :class:`SessionFileError` (a ``ValueError``)
whose one-line message names the file, the line and the column.

Plausibility of the units (:func:`check_units`)
-----------------------------------------------
A file in the wrong units gives no positions or nonsense, so the values are
checked against what the declared units make them, and a session that only
makes sense in another unit is refused with one line naming that unit:

* accelerometers: the median of ``|a|`` over the session must lie in
  ``[5, 20] m/s²`` (a calibration or flight session rests or moves about
  ``g``); a median near 1 is ``g``, near 1000 ``mg``. A median no unit puts
  in that range is no unit mistake but a dead or faulty accelerometer (0.35 g
  at rest): the verdicts (``diagnose``, ``publish`` to the daemon) test it as
  read, the fits refuse it;
* gyros: declared rad/s, a median ``|ω|`` above 5 rad/s (290 °/s: faster on
  average than rate tables and flights turn) or a 99.5th percentile above
  20 rad/s (1150 °/s, beyond what vehicles and fixtures turn at) looks like
  deg/s. A deg/s session whose turns never exceed about 20 °/s cannot be told
  from a rad/s one by its values and passes; a rad/s session declared deg/s
  is not detected either (its rates only look small);
* time: the median sample interval must lie in ``[100 µs, 2 s]``, i.e. a rate
  of 10 kHz … 0.5 Hz: the rates the service accepts from a stream
  (:class:`estimators.stream_validity.ValidityLimits`; outside it the detector's
  windows and buffers, sized in samples, are nonsense), so a file refused here
  would be refused streamed, and the reverse. A file in s declared ms has its
  rate multiplied by 1000: a 100 Hz session would read as 100 kHz. The range
  spans more than a factor 1000, so an interval can be plausible in two units
  (0.5 is 2 Hz in s and 2 kHz in ms); the refusal then names the unit that puts
  the rate nearest the middle of the range on a log scale (about 70 Hz, the
  rates such sessions are logged at). A file that does not declare its time
  unit is refused too when another unit puts the rate nearer that middle than
  seconds do (steps of 1 read as seconds are 1 Hz, as milliseconds 1 kHz):
  such a file calibrates without error either way, so the unit must be said.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path

import numpy as np

from estimators.conventions import STANDARD_GRAVITY_MPS2
from estimators.quantiles import median, percentile
from estimators.session import ImuSession, SessionError
from estimators.validity_limits import ValidityLimits
from protocols.atomic_file import atomic_write_bytes

CSV_COLUMNS = ("t", "ax", "ay", "az", "gx", "gy", "gz", "temp")
ACCEL_COLUMNS = ("ax", "ay", "az")
GYRO_COLUMNS = ("gx", "gy", "gz")
XSENS_SIDECAR_FORMAT = "ins-health/xsens-nominal"
XSENS_SIDECAR_VERSION = 1
GRAVITY_KEY = "gravity_mps2"


class SessionFileError(SessionError):
    """A session file cannot be read; the message names file, line and column."""


class UnitsError(SessionFileError):
    """The values of a session are implausible in their declared units; the message names the likely unit.

    ``kind``: which columns, ``accel``, ``gyro`` or ``time``."""

    def __init__(self, message: str, kind: str):
        super().__init__(message)
        self.kind = kind


class AccelUnit(StrEnum):
    MPS2 = "m/s2"
    G = "g"
    MG = "mg"


class GyroUnit(StrEnum):
    RPS = "rad/s"
    DPS = "deg/s"


class TimeUnit(StrEnum):
    S = "s"
    MS = "ms"
    US = "us"
    NS = "ns"


SI_PER_UNIT: dict[StrEnum, float] = {
    AccelUnit.MPS2: 1.0,
    AccelUnit.G: STANDARD_GRAVITY_MPS2,
    AccelUnit.MG: STANDARD_GRAVITY_MPS2 * 1e-3,
    GyroUnit.RPS: 1.0,
    GyroUnit.DPS: math.pi / 180.0,
    TimeUnit.S: 1.0,
    TimeUnit.MS: 1e-3,
    TimeUnit.US: 1e-6,
    TimeUnit.NS: 1e-9,
}
"""Factor from each unit to SI (m/s², rad/s, s)."""

UNIT_KEYS = {"accel": "accel_unit", "gyro": "gyro_unit", "time": "time_unit"}
"""The ``# key = value`` comment of a CSV file that declares each unit."""
SCALE_KEYS = {"accel": "accel_scale", "gyro": "gyro_scale"}
"""The ``# key = value`` comment (or ``key,value`` line, or sidecar key) that states a count's size."""
RATE_KEYS = ("fs", "rate_hz", "sample_rate_hz", "sampling_rate_hz", "rate")
"""Metadata keys (any case) whose value is the sample rate, Hz: the time of a file without a time column."""

RATE_AGREEMENT = 0.05
"""A stated rate and a time column's median step disagree beyond this fraction: said (a logger's
clock runs a few per mille off its nominal rate; a header left at another rate's value is off by far more)."""

_UNIT_OPTION = {"accel": "--accel-unit", "gyro": "--gyro-unit", "time": "--time-unit"}
_UNIT_WORD = {"accel": "accelerometer", "gyro": "gyro", "time": "time"}


def _positive(text: str, what: str, *, fraction: bool = False) -> float:
    """``text`` as a positive finite number (or ``a/b`` with ``fraction``); the error names ``what``."""
    num, sep, den = text.partition("/") if fraction else (text, "", "")
    try:
        value = float(num) / (float(den) if sep else 1.0)
    except (ValueError, ZeroDivisionError):
        kind = "a number or a fraction such as 1/16384" if fraction else "a number"
        raise SessionFileError(f"{what} is not {kind}: {text!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise SessionFileError(f"{what} must be positive and finite, got {text!r}")
    return value


def parse_scale(text: str | float) -> float:
    """A count's size, a number or a fraction (``1/16384``): what a data sheet states as counts per unit."""
    return _positive(str(text), "a scale", fraction=True)


@dataclass(frozen=True)
class SessionUnits:
    """Units of a session file's columns; None: not declared (the file's comment, else SI).

    ``accel_scale``, ``gyro_scale``: the size of one count in the triad's unit when its columns hold
    raw counts (``1/16384`` with ``accel = g`` for a ±2 g MPU-6050); None: the columns hold values.
    """

    accel: AccelUnit | None = None
    gyro: GyroUnit | None = None
    time: TimeUnit | None = None
    accel_scale: float | None = None
    gyro_scale: float | None = None

    def __post_init__(self) -> None:
        for name in ("accel_scale", "gyro_scale"):
            if (value := getattr(self, name)) is not None:
                object.__setattr__(self, name, parse_scale(value))
        for name, kind in (("accel", AccelUnit), ("gyro", GyroUnit), ("time", TimeUnit)):
            value = getattr(self, name)
            if value is not None:
                try:
                    object.__setattr__(self, name, kind(value))
                except ValueError:
                    choices = ", ".join(u.value for u in kind)
                    raise SessionFileError(
                        f"unknown {_UNIT_WORD[name]} unit {value!r} (one of {choices})"
                    ) from None

    def over(self, other: SessionUnits) -> SessionUnits:
        """These units where declared, else ``other``'s."""
        return SessionUnits(
            self.accel or other.accel,
            self.gyro or other.gyro,
            self.time or other.time,
            self.accel_scale or other.accel_scale,
            self.gyro_scale or other.gyro_scale,
        )

    def resolved(self) -> SessionUnits:
        """Undeclared units as SI (an undeclared scale stays None: the columns hold values)."""
        return self.over(SessionUnits(AccelUnit.MPS2, GyroUnit.RPS, TimeUnit.S))

    def to_si(self, session: ImuSession) -> ImuSession:
        """A new session in SI (the input arrays are not modified)."""
        u = self.resolved()

        def scaled(
            x: np.ndarray | None, unit: StrEnum | None, count: float | None
        ) -> np.ndarray | None:
            if x is None or unit is None:
                return None
            return x * (SI_PER_UNIT[unit] * (1.0 if count is None else count))

        return replace(
            session,
            t_s=session.t_s * SI_PER_UNIT[u.time or TimeUnit.S],
            accel_mps2=scaled(session.accel_mps2, u.accel, u.accel_scale),
            gyro_rps=scaled(session.gyro_rps, u.gyro, u.gyro_scale),
        )

    def to_dict(self) -> dict[str, str]:
        u = self.resolved()
        out = {k: str(getattr(u, k)) for k in UNIT_KEYS}
        out.update({SCALE_KEYS[k]: repr(v) for k in SCALE_KEYS if (v := getattr(u, f"{k}_scale"))})
        return out


@dataclass(frozen=True)
class LoadedSession:
    """A session read from files, with what the files say about it.

    Attributes
    ----------
    session : the samples, SI.
    gravity_mps2 : local gravity stated by the file or sidecar, m/s², or None.
    metadata : ``key = value`` comment lines of a CSV file (strings).
    source : the file or files read.
    units : the units the columns were read in (converted to SI in ``session``).
    notes : what the reader did that a user must be told (metadata lines read, the time made
        from a rate, columns not read, rows dropped, with their counts): one line each.
    """

    session: ImuSession
    gravity_mps2: float | None
    metadata: dict[str, str] = field(default_factory=dict)
    source: str = ""
    units: SessionUnits = field(default_factory=lambda: SessionUnits().resolved())
    notes: tuple[str, ...] = ()


# --- generic numeric table ---------------------------------------------------


MAX_LINE_BYTES = 1 << 16
"""Longest line of a session file, bytes. A line holds one sample: eight numbers of ours, or a ROS
``rostopic echo -p`` row of sensor_msgs/Imu with its three covariances (about 40 fields, 1 KB);
64 KiB is sixty times that. The whole file was read and split before a line was looked at: one
200 MB line took 1.4 GB before it was refused."""
_SCAN_BYTES = 1 << 20


def _check_line_lengths(path: Path) -> None:
    """:class:`SessionFileError` naming the first line longer than :data:`MAX_LINE_BYTES`, found
    reading 1 MiB at a time (nothing else held)."""
    with open(path, "rb") as f:
        lineno, run = 1, 0  # the line under way and its bytes so far
        while chunk := f.read(_SCAN_BYTES):
            ends = np.flatnonzero(np.frombuffer(chunk, np.uint8) == 0x0A)
            starts = np.concatenate([[-run], ends[:-1] + 1])
            too_long = np.flatnonzero(ends - starts > MAX_LINE_BYTES)
            run = run + len(chunk) if ends.size == 0 else len(chunk) - int(ends[-1]) - 1
            if too_long.size or run > MAX_LINE_BYTES:
                at = lineno + (int(too_long[0]) if too_long.size else ends.size)
                raise SessionFileError(
                    f"{path}: line {at} is longer than {MAX_LINE_BYTES} bytes: not a session "
                    "file (a line holds one sample)"
                )
            lineno += ends.size


def _read_text(path: Path) -> str:
    _check_line_lengths(path)
    try:
        # utf-8-sig: a byte-order mark (Windows editors and spreadsheets save one) is not text.
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SessionFileError(
            f"{path}: not a text file ({exc.reason} at byte {exc.start})"
        ) from None


def _parse_rows(
    path: Path,
    rows: list[tuple[int, str]],
    names: tuple[str, ...],
    delimiter: str | None,
    used_cols: list[int] | None = None,
    n_fields: int | None = None,
) -> np.ndarray:
    """(R, len(names)) floats from ``rows`` of (line number, text): the fields at ``used_cols`` of
    lines of ``n_fields`` fields (the others not read), else every field of lines of ``len(names)``.

    numpy parses the whole table at once; only when that fails is the table
    scanned line by line, to name the first bad line and column.
    """
    if not rows:
        return np.empty((0, len(names)))
    cols = list(range(len(names))) if used_cols is None else used_cols
    n_fields = len(names) if n_fields is None else n_fields
    try:
        data = np.loadtxt(
            [text for _, text in rows],
            delimiter=delimiter,
            comments=None,
            ndmin=2,
            dtype=float,
            usecols=used_cols,
        )
        # loadtxt reads the used columns of a line with fields more or fewer than the header names.
        if data.shape[1] == len(names) and (
            used_cols is None or all(len(t.split(delimiter)) == n_fields for _, t in rows)
        ):
            return data
    except ValueError:
        pass
    for lineno, text in rows:
        fields = text.split(delimiter)
        if len(fields) != n_fields:
            raise SessionFileError(
                f"{path}: line {lineno}: expected {n_fields} fields"
                + (f" ({','.join(names)})" if used_cols is None else "")
                + f", got {len(fields)}"
            )
        for name, k in zip(names, cols, strict=True):
            try:
                float(fields[k])
            except ValueError:
                raise SessionFileError(
                    f"{path}: line {lineno}, column {name!r}: not a number: {fields[k].strip()!r}"
                ) from None
    raise SessionFileError(f"{path}: the numeric table cannot be parsed")


def _split_lines(path: Path, text: str) -> tuple[list[tuple[int, str]], list[str]]:
    """Non-blank, non-comment lines with their 1-based numbers, and the comment texts."""
    rows, comments = [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s[1:].strip())
        else:
            rows.append((lineno, s))
    return rows, comments


# --- CSV ---------------------------------------------------------------------


def _metadata(comments: list[str]) -> dict[str, str]:
    out = {}
    for c in comments:
        key, sep, value = c.partition("=")
        if sep and key.strip() and " " not in key.strip():
            out[key.strip()] = value.strip()
        elif not sep and len(words := c.split()) == 2 and words[0].lower() in RATE_KEYS:
            # A rate as a space-separated table's logger writes it: ``# rate_hz 100``.
            out[words[0]] = words[1]
    return out


def _gravity_from(metadata: dict[str, str], path: Path) -> float | None:
    if GRAVITY_KEY not in metadata:
        return None
    return _positive(metadata[GRAVITY_KEY], f"{path}: comment {GRAVITY_KEY}")


def _all_numbers(fields: list[str]) -> bool:
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return True


def _check_header(path: Path, lineno: int, names: list[str], *, has_rate: bool = False) -> None:
    expected = "t,ax,ay,az,gx,gy,gz[,temp]"
    if len(names) == 1 and (sep := next((c for c in ";\t" if c in names[0]), None)):
        # A spreadsheet's export in a locale whose list separator is ';' (its decimals then ',').
        word = "tabs" if sep == "\t" else "';'"
        raise SessionFileError(
            f"{path}: line {lineno}: the header is separated by {word}; a session file is "
            f"comma-separated with '.' decimals ({expected})"
        )
    for n in names:
        if n not in CSV_COLUMNS:
            raise SessionFileError(
                f"{path}: line {lineno}: unknown column {n!r} (expected {expected})"
            )
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SessionFileError(f"{path}: line {lineno}: duplicate column {dup[0]!r}")
    if "t" not in names and not has_rate:
        raise SessionFileError(
            f"{path}: line {lineno}: missing column 't' (expected {expected}), and no rate line "
            f"({', '.join(RATE_KEYS)}) to give the time"
        )
    for triad in (ACCEL_COLUMNS, GYRO_COLUMNS):
        present = [c for c in triad if c in names]
        if present and len(present) < 3:
            missing = next(c for c in triad if c not in names)
            raise SessionFileError(
                f"{path}: line {lineno}: missing column {missing!r} (expected {expected})"
            )
    if not any(c in names for c in ACCEL_COLUMNS + GYRO_COLUMNS):
        raise SessionFileError(
            f"{path}: line {lineno}: missing columns ax,ay,az and gx,gy,gz (expected {expected})"
        )


@dataclass(frozen=True)
class CsvDialect:
    """The IMU CSV file of another tool: its column names (lower case) for ours, and its units."""

    name: str
    columns: dict[str, str]
    units: SessionUnits
    ignored_prefixes: tuple[str, ...] = ()
    """Columns of the format that hold nothing read here (a ROS message's other fields)."""
    ignore_others: bool = False
    """Any column not in ``columns`` is not read (and said), rather than not this format."""
    delimiter: str | None = ","
    """Between fields (None: white space)."""

    def ours(self, names: list[str]) -> list[str | None] | None:
        """Our column for each of ``names`` (None: ignored), or None when they are not this format."""
        out: list[str | None] = []
        for n in names:
            if n in self.columns:
                out.append(self.columns[n])
            elif self.ignore_others or n.startswith(self.ignored_prefixes):  # False for no prefixes
                out.append(None)
            else:
                return None
        kept = [n for n in out if n is not None]
        return out if len(kept) == len(set(kept)) else None


_SI_NS = SessionUnits(AccelUnit.MPS2, GyroUnit.RPS, TimeUnit.NS)


def _axes(ours: str, pattern: str) -> dict[str, str]:
    return {pattern.format(axis): f"{ours}{axis}" for axis in "xyz"}


CSV_DIALECTS = (
    CsvDialect(
        "EuRoC/ASL imu0/data.csv",
        {
            "#timestamp [ns]": "t",
            "timestamp [ns]": "t",
            **_axes("g", "w_rs_s_{} [rad s^-1]"),
            **_axes("a", "a_rs_s_{} [m s^-2]"),
        },
        _SI_NS,
    ),
    CsvDialect(
        "Kalibr imu0.csv",
        {"timestamp": "t", **_axes("g", "omega_{}"), **_axes("a", "alpha_{}")},
        _SI_NS,
    ),
    CsvDialect(
        "ROS sensor_msgs/Imu (rostopic echo -p)",
        {
            "field.header.stamp": "t",
            **_axes("g", "field.angular_velocity.{}"),
            **_axes("a", "field.linear_acceleration.{}"),
        },
        _SI_NS,
        ignored_prefixes=("%time", "field."),
    ),
)
"""IMU CSV files other tools write, read as they are (nanosecond time stamps, rad/s, m/s²).
EuRoC's header line starts with ``#`` (a comment here): it is taken as the header when it
names that format's columns."""


WHITESPACE_TABLE = CsvDialect(
    "whitespace-separated table with a '#' header",
    {
        **{name: "t" for name in ("t", "time", "timestamp", "time_s")},
        **{
            pattern.format(axis): f"{ours}{axis}"
            for axis in "xyz"
            for ours, patterns in (
                ("a", ("a{}", "t{}", "acc_{}", "accel_{}")),
                ("g", ("g{}", "w{}", "gyr_{}", "gyro_{}")),
            )
            for pattern in patterns
        },
    },
    SessionUnits(AccelUnit.MPS2, GyroUnit.RPS, None),
    ignore_others=True,
    delimiter=None,
)
"""A space-separated table whose ``#`` line names its columns, TUM-style (``# time tx ty tz wx wy wz
mx my mz qw qx qy qz``: ``t`` for the translational acceleration, ``w`` the angular rate), in SI
with the time in s unless declared; columns not named here (magnetometer, quaternion) are not read,
and said."""


def _dialect_of(names: list[str]) -> tuple[CsvDialect, list[str | None]] | None:
    for dialect in CSV_DIALECTS:
        ours = dialect.ours(names)
        if ours is not None and "t" in ours:
            return dialect, ours
    return None


def _head_lines(text: str) -> Iterator[str]:
    """``text.splitlines()`` one line at a time, splitting only as far as the reader gets: a
    header is found in the first lines, and a session holds thousands more."""
    start, size = 0, 4096
    while start < len(text):
        chunk = text[start : start + size]
        ended = chunk.splitlines(keepends=True)
        # The chunk's last line may go on past it (or its "\r" be half a "\r\n"): read it again
        # with the next chunk.
        n = len(ended) if start + size >= len(text) else len(ended) - 1
        if n == 0:
            size *= 2
            continue
        yield from chunk.splitlines()[:n]
        start += sum(map(len, ended[:n]))


def _commented_header(text: str) -> tuple[int, str] | None:
    """The first line, when it is a ``#``-commented header of a :data:`CSV_DIALECTS` format (EuRoC's)."""
    for lineno, line in enumerate(_head_lines(text), start=1):
        s = line.strip()
        if not s:
            continue
        names = [n.strip().lower() for n in s.split(",")]
        return (lineno, s) if s.startswith("#") and _dialect_of(names) else None
    return None


def _meta_get(metadata: dict[str, str], *keys: str) -> tuple[str, str] | None:
    """The first of ``keys`` the metadata holds, in any case: (its key as written, its value)."""
    lower = {k.lower(): k for k in metadata}
    for key in keys:
        if key in lower:
            return lower[key], metadata[lower[key]]
    return None


def _file_units(metadata: dict[str, str], path: Path) -> SessionUnits:
    declared = [
        None if (kv := _meta_get(metadata, key)) is None else kv[1]
        for key in (*UNIT_KEYS.values(), *SCALE_KEYS.values())
    ]
    try:
        return SessionUnits(*declared)  # type: ignore[arg-type]
    except SessionFileError as exc:
        raise SessionFileError(f"{path}: comment {exc}") from None


def _whitespace_header(text: str) -> tuple[int, list[str]] | None:
    """The last ``#`` line above the first data line that names a :data:`WHITESPACE_TABLE`'s
    columns, as many as that data line's whitespace-separated fields (a line of units may follow it;
    ``key value`` metadata lines such as ``Fs 100`` may come before it). Without a time column the
    names are a header only when a rate line above gives the time."""
    comments: list[tuple[int, str]] = []
    rate_said = False
    for lineno, line in enumerate(_head_lines(text), start=1):
        s = line.strip()
        if not s:
            continue
        words = s.lstrip("#").replace("=", " ").split()
        rate_said |= len(words) == 2 and words[0].lower() in RATE_KEYS
        if not s.startswith("#"):
            if "," in s:
                return None
            if len(words) == 2 and not _all_numbers(words[:1]):
                continue
            for number, comment in reversed(comments):
                names = comment.lstrip("#").lower().split()
                ours = WHITESPACE_TABLE.ours(names)
                # The time or a rate line, and a triad: a comment's words are no header ("# time
                # series").
                named = [] if ours is None else [o for o in ours if o is not None]
                if (
                    "," not in comment
                    and len(named) >= 3 + ("t" in named)
                    and ("t" in named or rate_said)
                ):
                    return (number, names) if len(s.split()) == len(names) else None
            return None
        comments.append((lineno, s))
    return None


def _metadata_fields(text: str, delimiter: str | None = ",") -> list[str]:
    """A row's fields, less the empty ones a spreadsheet pads it with to the widest row (``Fs,100,,,,``)."""
    fields = [f.strip() for f in text.split(delimiter)]
    while len(fields) > 2 and not fields[-1]:
        fields.pop()
    return fields


def _metadata_rows(rows: list[tuple[int, str]], delimiter: str | None) -> int:
    """How many leading rows are ``key,value`` metadata (an Arduino logger's ``Fs,100``, or
    ``Fs 100`` above a space-separated table): rows of two fields, the first not a number, before
    a header of more fields that is not all numbers."""
    k = 0
    while (
        k < len(rows)
        and len(fields := _metadata_fields(rows[k][1], delimiter)) == 2
        and not _all_numbers(fields[:1])
    ):
        k += 1
    if k == 0 or k == len(rows):
        return 0
    header = rows[k][1].split(delimiter)
    return k if len(header) > 2 and not _all_numbers(header) else 0


def _no_data_rows(rows: list[tuple[int, str]], delimiter: str | None) -> list[int]:
    """Indices of the rows that hold no number at all (a spreadsheet's empty ``,,,,,,`` rows, a
    label, a separator line), wherever they are: no sample, so nothing is lost by dropping them.
    A row with a number in it is a damaged sample, refused by name."""
    return [
        k
        for k, (_, text) in enumerate(rows)
        if not any(_all_numbers([f]) for f in text.split(delimiter))
    ]


def _line_spans(lines: list[int]) -> str:
    """Ascending line numbers as runs: ``7, 1003-1008``."""
    spans: list[list[int]] = []
    for n in lines:
        if spans and n == spans[-1][1] + 1:
            spans[-1][1] = n
        else:
            spans.append([n, n])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)


def _counts_without_scale(
    path: Path, data: dict[str, np.ndarray], declared: SessionUnits
) -> SessionFileError | None:
    """Whole-number triads no unit or scale was declared for, implausible as SI: raw counts (an
    MPU-6050's ±16384 per g), whose scale only the user knows. The error names what is missing."""
    missing = []
    for kind, cols, word in (
        ("accel", ACCEL_COLUMNS, "accelerometer"),
        ("gyro", GYRO_COLUMNS, "gyro"),
    ):
        if cols[0] not in data or getattr(declared, kind) or getattr(declared, f"{kind}_scale"):
            continue
        x = np.column_stack([data[c] for c in cols])
        x = x[np.all(np.isfinite(x), axis=1)]
        if not x.size or np.any(x != np.round(x)):
            continue
        norm = np.linalg.norm(x, axis=1)
        median = float(np.median(norm))
        si_plausible = (
            _plausible("accel", median, AccelUnit.MPS2)
            if kind == "accel"
            else median <= GYRO_MEDIAN_LIMIT_RPS
            and float(np.percentile(norm, 99.5)) <= GYRO_P995_LIMIT_RPS
        )
        if not si_plausible:
            missing.append((kind, word, median))
    if not missing:
        return None
    said = " and ".join(
        f"the {word} values are whole numbers (median {m:.6g})" for _, word, m in missing
    )
    what = ", ".join(f"--{kind}-scale (one count in --{kind}-unit)" for kind, _, _ in missing)
    keys = " and ".join(f"'{SCALE_KEYS[kind]}'" for kind, _, _ in missing)
    return SessionFileError(
        f"{path}: {said}: raw counts, whose scale is not stated; missing: {what}, or {keys} "
        "in the file or a sidecar (e.g. an MPU-6050 at ±2 g and ±250 °/s: --accel-scale 1/16384 "
        "--accel-unit g --gyro-scale 1/131 --gyro-unit deg/s)"
    )


def read_csv_session(
    path: str | os.PathLike[str],
    *,
    units: SessionUnits = SessionUnits(),
    sidecar: dict[str, str] | None = None,
) -> LoadedSession:
    """Read a CSV session file (format in the module docstring) and convert it to SI.

    ``units`` declares the columns' units and count sizes; where it leaves one None the
    ``sidecar``'s key applies, then the file's ``# <triad>_unit = …`` comment or ``key,value``
    line, else SI. The units used are in ``LoadedSession.units``; call :func:`check_units` to
    refuse implausible ones. What the reader did beyond reading (metadata lines, a time made from
    the rate, columns not read, rows with no number dropped) is in ``LoadedSession.notes``.
    """
    path = Path(path)
    text = _read_text(path)
    rows, comments = _split_lines(path, text)
    notes: list[str] = []
    delimiter: str | None = ","
    if (commented := _commented_header(text)) is not None:
        rows.insert(0, commented)
        comments.remove(commented[1][1:].strip())
    elif (spaced := _whitespace_header(text)) is not None:
        # In file order: ``key value`` metadata lines may come before the header.
        rows.append((spaced[0], " ".join(spaced[1])))
        rows.sort()
        delimiter = None
    meta = _metadata(comments)
    if n_meta := _metadata_rows(rows, delimiter):
        pairs = [_metadata_fields(text, delimiter) for _, text in rows[:n_meta]]
        meta.update({k: v for k, v in pairs if k not in meta})
        notes.append(
            f"{n_meta} metadata line(s) before the header read: "
            + ", ".join(f"{k}={v}" for k, v in pairs)
        )
        del rows[:n_meta]
    meta.update(sidecar or {})
    if not rows:
        raise SessionFileError(f"{path}: empty file (no header row t,ax,ay,az,gx,gy,gz[,temp])")
    header_line, header = rows[0]
    if delimiter == "," and _all_numbers(fields := header.split()):
        # A raw-count pair's files hold time x y z: four fields.
        pair = (
            "this looks like one file of a raw-count pair (give the gyro file too, or the "
            "directory holding both); "
            if len(fields) == 4
            else ""
        )
        raise SessionFileError(
            f"{path}: line {header_line}: no header row; {pair}a space-separated table needs "
            "a '#' line naming its columns above the first row (# time ax ay az gx gy gz; "
            f"without a time column, a rate line above it: # {RATE_KEYS[1]} 100)"
        )
    names = [n.strip().lower() for n in header.split(delimiter)]
    n_fields = len(names)
    file_units = _file_units(meta, path)
    used_cols: list[int] | None = None
    found = (
        (WHITESPACE_TABLE, WHITESPACE_TABLE.ours(names))
        if delimiter is None
        else _dialect_of(names)
    )
    if found is not None and found[1] is not None:
        dialect, ours = found[0], found[1]
        used_cols = [k for k, n in enumerate(ours) if n is not None]
        if ignored := [n for n, o in zip(names, ours, strict=True) if o is None]:
            if dialect.ignore_others:
                notes.append(f"{len(ignored)} column(s) not read: {' '.join(ignored)}")
        names = [n for n in ours if n is not None]
        # The format fixes its units: written down as if the file had said them.
        file_units = file_units.over(dialect.units)
        said = {
            k: v
            for k, v in dialect.units.to_dict().items()
            if k != "time_unit" or dialect.units.time
        }
        meta = {"format": dialect.name, **said, **meta}
    rate = _meta_get(meta, *RATE_KEYS)
    try:
        _check_header(path, header_line, names, has_rate=rate is not None)
    except SessionFileError as exc:
        if found is None:
            raise
        theirs = ", ".join(n for n in found[0].columns if n != "#timestamp [ns]")
        raise SessionFileError(
            f"{exc}; read as {found[0].name}, whose columns are {theirs}"
        ) from None
    if len(rows) == 1:
        raise SessionFileError(f"{path}: no data rows after the header (line {header_line})")
    used = list(range(n_fields)) if used_cols is None else used_cols
    try:
        data = _parse_rows(path, rows[1:], tuple(names), delimiter, used_cols, n_fields)
    except SessionFileError:
        # A table that parses whole has no row without a number: they are looked for only now.
        junk = _no_data_rows(rows[1:], delimiter)
        # Rows that are all junk are a wrong file, not a spreadsheet's padding: the first is named.
        if not 0 < len(junk) < len(rows) - 1:
            raise
        lines = [rows[1 + k][0] for k in junk]
        notes.append(
            f"{len(junk)} row(s) that are no data dropped (lines {_line_spans(lines)}, "
            f"first {rows[1 + junk[0]][1][:40]!r})"
        )
        dropped = set(junk)
        rows = rows[:1] + [r for k, r in enumerate(rows[1:]) if k not in dropped]
        data = _parse_rows(path, rows[1:], tuple(names), delimiter, used_cols, n_fields)
    col = {n: data[:, k] for k, n in enumerate(names)}
    if (problem := _counts_without_scale(path, col, units.over(file_units))) is not None:
        raise problem
    if "t" not in col:
        assert rate is not None  # _check_header refuses a file with neither
        rate_hz = _positive(rate[1], f"{path}: rate {rate[0]} (Hz)")
        col["t"] = np.arange(data.shape[0]) / rate_hz
        notes.append(
            f"no time column: time from {rate[0]}={rate[1]} Hz (sample k at k/{rate[1]} s)"
        )
        if (declared_time := units.time or file_units.time) not in (None, TimeUnit.S):
            notes.append(
                f"the declared time unit {declared_time} is not used: the time comes from the rate"
            )
        units, file_units = replace(units, time=None), replace(file_units, time=TimeUnit.S)
        meta.setdefault(UNIT_KEYS["time"], "s")
    elif "e" in (first_t := rows[1][1].split(delimiter)[used[names.index("t")]]).lower():
        # A spreadsheet writes large stamps so, rounded to its digits: repeats are dropped and
        # counted by the validation, as any repeated stamp.
        repeats = int(np.count_nonzero(np.diff(col["t"]) <= 0))
        notes.append(
            f"time stamps in E-notation (first {first_t.strip()!r}): {repeats} repeat an earlier "
            "one or go back at the precision written"
        )

    if rate is not None and "t" in names:
        step = np.diff(col["t"]) * SI_PER_UNIT[units.over(file_units).resolved().time or TimeUnit.S]
        step = step[np.isfinite(step) & (step > 0)]
        try:
            stated_hz = _positive(rate[1], "")
        except SessionFileError:  # a comment's "rate" that is no number gives no time here
            stated_hz = math.nan
        if step.size and abs(1.0 / float(np.median(step)) / stated_hz - 1.0) > RATE_AGREEMENT:
            notes.append(
                f"{rate[0]}={rate[1]} Hz stated, but the time column's median step is a rate of "
                f"{1.0 / float(np.median(step)):.4g} Hz: the time column is the time"
            )

    def triad(cols: tuple[str, ...]) -> np.ndarray | None:
        return np.column_stack([col[c] for c in cols]) if cols[0] in col else None

    session = ImuSession(
        col["t"].copy(),
        triad(ACCEL_COLUMNS),
        triad(GYRO_COLUMNS),
        col["temp"].copy() if "temp" in col else None,
    )
    used_units = units.over(file_units).resolved()
    return LoadedSession(
        used_units.to_si(session),
        _gravity_from(meta, path),
        meta,
        str(path),
        used_units,
        tuple(notes),
    )


def write_csv_session(
    path: str | os.PathLike[str],
    session: ImuSession,
    *,
    metadata: dict[str, object] | None = None,
    comments: tuple[str, ...] = (),
) -> Path:
    """Write ``session`` as a CSV session file; returns the path.

    Values are written with 17 significant digits, so reading the file back
    gives the same float64 arrays. ``metadata`` becomes ``# key = value``
    lines, ``comments`` plain ``#`` lines, both before the header. The file is
    replaced atomically (:mod:`protocols.atomic_file`).
    """
    path = Path(path)
    cols, names = [session.t_s[:, None]], ["t"]
    if session.accel_mps2 is not None:
        cols.append(session.accel_mps2)
        names += ACCEL_COLUMNS
    if session.gyro_rps is not None:
        cols.append(session.gyro_rps)
        names += GYRO_COLUMNS
    if session.temp_c is not None:
        cols.append(session.temp_c[:, None])
        names.append("temp")
    if session.accel_mps2 is None and session.gyro_rps is None:
        raise SessionFileError(f"{path}: the session has neither accelerometer nor gyro samples")
    table = np.hstack([np.asarray(c, float) for c in cols])
    head = ["ins-health session file: t s, ax..az m/s^2, gx..gz rad/s, temp degC"]
    head += [str(c) for c in comments]
    for key, value in (metadata or {}).items():
        if not str(key).isidentifier():
            raise ValueError(f"metadata key must be an identifier, got {key!r}")
        head.append(f"{key} = {value}")
    text = io.StringIO(newline="\n")
    text.write("".join(f"# {h}\n" for h in head))
    text.write(",".join(names) + "\n")
    np.savetxt(text, table, fmt="%.17g", delimiter=",")
    return atomic_write_bytes(path, text.getvalue().encode("utf-8"))


# --- Xsens raw-count pair ----------------------------------------------------


@dataclass(frozen=True)
class CountScale:
    """Nominal raw-count conversion of one triad: ``SI = (counts − offset_counts) · scale_si_per_count``.

    Both are (3,) per axis; the scale is in m/s² or rad/s per count.
    """

    offset_counts: tuple[float, ...]
    scale_si_per_count: tuple[float, ...]

    def __post_init__(self) -> None:
        for name in ("offset_counts", "scale_si_per_count"):
            a = np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (3,))
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite, got {a.tolist()!r}")
            object.__setattr__(self, name, tuple(a.tolist()))
        if 0.0 in self.scale_si_per_count:
            raise ValueError("scale_si_per_count must not be zero")

    def to_si(self, counts: np.ndarray) -> np.ndarray:
        si: np.ndarray = (counts - np.array(self.offset_counts)) * np.array(self.scale_si_per_count)
        return si


@dataclass(frozen=True)
class XsensNominal:
    """Nominal conversion of an Xsens raw-count pair, and the local gravity, m/s² (or None)."""

    accel: CountScale
    gyro: CountScale
    gravity_mps2: float | None = None
    source: str = ""


DEFAULT_XSENS_SIDECAR = "xsens_mti.toml"


def load_xsens_sidecar(path: str | os.PathLike[str] | None = None) -> XsensNominal:
    """Read a TOML sidecar (``None``: the packaged default for IMU-TK's Xsens MTi).

    Keys: ``format = "ins-health/xsens-nominal"``, ``version = 1``, optional
    ``gravity_mps2``, and tables ``[accel]``, ``[gyro]`` with ``offset_counts``
    and ``scale_si_per_count`` (a number or three).
    """
    if path is None:
        # Imported here: importlib.resources brings tempfile and random, which reading a CSV does not need.
        from importlib import resources

        ref = resources.files(f"{__package__}.sidecars").joinpath(DEFAULT_XSENS_SIDECAR)
        text, where = ref.read_text(encoding="utf-8"), f"packaged {DEFAULT_XSENS_SIDECAR}"
    else:
        text, where = _read_text(Path(path)), str(path)
    import tomllib  # here: a session without a sidecar does not pay for it (1.4 ms of calibrate)

    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SessionFileError(f"{where}: not valid TOML: {exc}") from None
    if doc.get("format") != XSENS_SIDECAR_FORMAT:
        raise SessionFileError(
            f"{where}: format must be {XSENS_SIDECAR_FORMAT!r}, got {doc.get('format')!r}"
        )
    if doc.get("version") != XSENS_SIDECAR_VERSION:
        raise SessionFileError(
            f"{where}: unknown sidecar version {doc.get('version')!r} (this reader knows version {XSENS_SIDECAR_VERSION})"
        )
    scales = {}
    for triad in ("accel", "gyro"):
        table = doc.get(triad)
        if (
            not isinstance(table, dict)
            or "offset_counts" not in table
            or "scale_si_per_count" not in table
        ):
            raise SessionFileError(
                f"{where}: needs a [{triad}] table with offset_counts and scale_si_per_count"
            )
        try:
            scales[triad] = CountScale(table["offset_counts"], table["scale_si_per_count"])
        except (ValueError, TypeError) as exc:
            raise SessionFileError(f"{where}: [{triad}]: {exc}") from None
    g = doc.get(GRAVITY_KEY)
    if g is not None and not (isinstance(g, (int, float)) and math.isfinite(g) and g > 0):
        raise SessionFileError(f"{where}: {GRAVITY_KEY} must be a positive number, got {g!r}")
    return XsensNominal(scales["accel"], scales["gyro"], None if g is None else float(g), where)


def _read_count_file(path: Path) -> np.ndarray:
    rows, _ = _split_lines(path, _read_text(path))
    if not rows:
        raise SessionFileError(f"{path}: empty file (expected lines 'time_s x y z')")
    return _parse_rows(path, rows, ("time_s", "x", "y", "z"), None)


def read_xsens_pair(
    accel_path: str | os.PathLike[str],
    gyro_path: str | os.PathLike[str],
    *,
    nominal: XsensNominal | None = None,
) -> LoadedSession:
    """Read the two-file raw-count format; ``nominal`` defaults to the packaged sidecar."""
    nominal = load_xsens_sidecar() if nominal is None else nominal
    accel_path, gyro_path = Path(accel_path), Path(gyro_path)
    acc = _read_count_file(accel_path)
    gyr = _read_count_file(gyro_path)
    if acc.shape[0] != gyr.shape[0]:
        raise SessionFileError(
            f"{accel_path} has {acc.shape[0]} samples but {gyro_path} has {gyr.shape[0]}: not a pair"
        )
    differ = np.flatnonzero(acc[:, 0] != gyr[:, 0])
    if differ.size:
        k = int(differ[0])
        raise SessionFileError(
            f"{accel_path} and {gyro_path}: time stamps differ at sample {k + 1} ({float(acc[k, 0])!r} vs {float(gyr[k, 0])!r}): not a pair"
        )
    session = ImuSession(
        acc[:, 0].copy(), nominal.accel.to_si(acc[:, 1:]), nominal.gyro.to_si(gyr[:, 1:]), None
    )
    meta = {"sidecar": nominal.source}
    return LoadedSession(session, nominal.gravity_mps2, meta, f"{accel_path} + {gyro_path}")


def find_xsens_pair(directory: Path) -> tuple[Path, Path, Path | None]:
    """The accelerometer file, gyro file and optional sidecar (``*.toml``) of a directory.

    The pair is the one data file whose name contains ``acc`` and the one whose
    name contains ``gyr``.
    """
    files = sorted(
        p
        for p in directory.iterdir()
        if p.is_file() and p.suffix.lower() not in (".md", ".txt", ".toml")
    )
    accs = [p for p in files if "acc" in p.name.lower()]
    gyrs = [p for p in files if "gyr" in p.name.lower()]
    if len(accs) != 1 or len(gyrs) != 1:
        raise SessionFileError(
            f"{directory}: expected one accelerometer file (name with 'acc') and one gyro file (name with 'gyr'), "
            f"found {[p.name for p in accs]} and {[p.name for p in gyrs]}"
        )
    tomls = sorted(directory.glob("*.toml"))
    if len(tomls) > 1:
        raise SessionFileError(f"{directory}: more than one sidecar: {[p.name for p in tomls]}")
    return accs[0], gyrs[0], tomls[0] if tomls else None


# --- dispatch ----------------------------------------------------------------


def load_session(
    path: str | os.PathLike[str],
    gyro_path: str | os.PathLike[str] | None = None,
    *,
    sidecar: str | os.PathLike[str] | None = None,
    nominal: XsensNominal | None = None,
    units: SessionUnits = SessionUnits(),
) -> LoadedSession:
    """Read a session from what ``path`` is.

    * ``path`` + ``gyro_path``: an Xsens raw-count pair (accelerometer file, gyro file);
    * a directory: the raw-count pair inside it (see :func:`find_xsens_pair`),
      with the directory's own ``*.toml`` sidecar if it has one;
    * a file: a CSV session file (or a space-separated table with a ``#`` header).

    The nominal conversion of a pair is ``nominal`` if given, else the
    ``sidecar`` file, else the directory's sidecar, else the packaged default.
    ``units`` declares the units of a CSV file's columns (a raw-count pair is
    converted by its sidecar: declaring units for it is an error); a CSV file's
    ``sidecar`` states what the file does not (:func:`load_csv_sidecar`).
    """
    path = Path(path)
    if gyro_path is None and path.is_dir():
        path, gyro_path, found = find_xsens_pair(path)
        sidecar = sidecar if sidecar is not None else found
    if gyro_path is not None:
        if units != SessionUnits():
            raise SessionFileError(
                f"{path}: a raw-count pair is converted by its sidecar; units cannot be declared for it"
            )
        if nominal is None:
            nominal = load_xsens_sidecar(sidecar)
        return read_xsens_pair(path, gyro_path, nominal=nominal)
    if not path.exists():
        raise FileNotFoundError(f"no such session file: {path}")
    return read_csv_session(
        path, units=units, sidecar=None if sidecar is None else load_csv_sidecar(sidecar)
    )


CSV_SIDECAR_KEYS = (*UNIT_KEYS.values(), *SCALE_KEYS.values(), *RATE_KEYS, GRAVITY_KEY)


def load_csv_sidecar(path: str | os.PathLike[str]) -> dict[str, str]:
    """A CSV session's TOML sidecar: what its file does not say (``accel_scale = "1/16384"``,
    ``accel_unit = "g"``, ``fs = 100`` …, keys :data:`CSV_SIDECAR_KEYS`), as metadata strings."""
    import tomllib  # here: a session without a sidecar does not pay for it

    try:
        doc = tomllib.loads(_read_text(Path(path)))
    except tomllib.TOMLDecodeError as exc:
        raise SessionFileError(f"{path}: not valid TOML: {exc}") from None
    unknown = sorted(set(doc) - set(CSV_SIDECAR_KEYS))
    if unknown:
        raise SessionFileError(
            f"{path}: unknown sidecar key(s) {', '.join(unknown)} (known: {', '.join(CSV_SIDECAR_KEYS)})"
        )
    return {k: str(v) for k, v in doc.items()}


def read_session(
    path: str | os.PathLike[str],
    gyro_path: str | os.PathLike[str] | None = None,
    *,
    sidecar: str | os.PathLike[str] | None = None,
    nominal: XsensNominal | None = None,
) -> ImuSession:
    """The :class:`ImuSession` of :func:`load_session` (same arguments)."""
    return load_session(path, gyro_path, sidecar=sidecar, nominal=nominal).session


# --- plausibility of the units -------------------------------------------------

ACCEL_MEDIAN_RANGE_MPS2 = (5.0, 20.0)
GYRO_MEDIAN_LIMIT_RPS = 5.0
GYRO_P995_LIMIT_RPS = 20.0
SAMPLE_INTERVAL_RANGE_S = (1.0 / ValidityLimits.max_rate_hz, 1.0 / ValidityLimits.min_rate_hz)
"""The rules of the module docstring, "Plausibility of the units"."""
_TYPICAL_INTERVAL_S = math.sqrt(SAMPLE_INTERVAL_RANGE_S[0] * SAMPLE_INTERVAL_RANGE_S[1])


def _plausible(kind: str, raw: float, unit: StrEnum) -> bool:
    si = raw * SI_PER_UNIT[unit]
    if kind == "accel":
        return ACCEL_MEDIAN_RANGE_MPS2[0] <= si <= ACCEL_MEDIAN_RANGE_MPS2[1]
    return SAMPLE_INTERVAL_RANGE_S[0] <= si <= SAMPLE_INTERVAL_RANGE_S[1]


def _refuse(kind: str, declared: StrEnum, looks: StrEnum | None, what: str) -> UnitsError:
    word = _UNIT_WORD[kind]
    if looks is None:
        return UnitsError(
            f"units: the {word} values are implausible in {declared} ({what}) and in every other unit",
            kind,
        )
    return UnitsError(
        f"units: the {word} values look like {looks}, not {declared} ({what}; "
        f"use {_UNIT_OPTION[kind]} {looks} or a '# {UNIT_KEYS[kind]} = {looks}' line)",
        kind,
    )


def check_units(
    session: ImuSession,
    units: SessionUnits,
    *,
    time_declared: bool = True,
    faulty_accel_ok: bool = False,
) -> str | None:
    """Refuse a session (SI, read in ``units``) whose values only make sense in other units.

    Raises :class:`UnitsError` with one line naming the unit the data look like
    (rules in the module docstring). Non-finite samples are ignored. With
    ``time_declared`` False (no option nor file line said it), a time unit that
    another unit would beat is refused too. With ``faulty_accel_ok`` an
    accelerometer implausible in every unit is no unit mistake but what a dead or
    faulty one reads (0.35 g at rest): it passes, for a verdict to test it, and
    the line saying so is returned (None when there is nothing to say).
    """
    used = units.resolved()
    note = None
    a = session.accel_mps2
    if a is not None and used.accel is not None:
        with np.errstate(over="ignore"):  # an absurd value's norm is inf: left out below
            norm = np.linalg.norm(a, axis=1)
        norm = norm[np.isfinite(norm)]
        if norm.size:
            raw = float(median(norm)) / SI_PER_UNIT[used.accel]
            if not _plausible("accel", raw, used.accel):
                looks = next((u for u in AccelUnit if _plausible("accel", raw, u)), None)
                refusal = _refuse("accel", used.accel, looks, f"median |a| {raw:.4g} {used.accel}")
                if looks is not None or not faulty_accel_ok:
                    raise refusal
                note = f"{refusal}: tested as read (a dead or faulty accelerometer reads so)"
    w = session.gyro_rps
    if w is not None and used.gyro is GyroUnit.RPS:
        with np.errstate(over="ignore"):
            rate = np.linalg.norm(w, axis=1)
        rate = rate[np.isfinite(rate)]
        if rate.size:
            med, p995 = (float(v) for v in percentile(rate, [50.0, 99.5]))
            if med > GYRO_MEDIAN_LIMIT_RPS or p995 > GYRO_P995_LIMIT_RPS:
                raise _refuse(
                    "gyro",
                    GyroUnit.RPS,
                    GyroUnit.DPS,
                    f"median |ω| {med:.3g} rad/s, 99.5th percentile {p995:.3g} rad/s",
                )
    dt = np.diff(session.t_s)
    dt = dt[np.isfinite(dt) & (dt > 0)]
    if dt.size and used.time is not None:
        raw = float(median(dt)) / SI_PER_UNIT[used.time]
        looks_t = min(
            (u for u in TimeUnit if _plausible("time", raw, u)),
            key=lambda u: abs(math.log(raw * SI_PER_UNIT[u] / _TYPICAL_INTERVAL_S)),
            default=None,
        )
        if not _plausible("time", raw, used.time):
            raise _refuse(
                "time", used.time, looks_t, f"median sample interval {raw:.4g} {used.time}"
            )
        if not time_declared and looks_t is not None and looks_t is not used.time:
            # Undeclared, and another unit gives a more usual rate: 1 ms steps read as seconds are a
            # 1 Hz session, which calibrates (wrongly) without a word.
            raise UnitsError(
                f"units: the time stamps are {raw:.4g} {used.time} apart, a rate of {1.0 / (raw * SI_PER_UNIT[used.time]):.4g} Hz "
                f"read as {used.time} but {1.0 / (raw * SI_PER_UNIT[looks_t]):.4g} Hz read as {looks_t}: declare the time unit "
                f"({_UNIT_OPTION['time']} {used.time} or {looks_t}, or a '# {UNIT_KEYS['time']} = ...' line)",
                "time",
            )
    return note
